"""The command: arguments, the deadline's watchdog, each part in turn (a broken part is recorded
and the others run), the report and the exit status."""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import threading
import time
from pathlib import Path
from typing import Optional, Sequence

import torch

from sp_plugins.cli.gpu_check.budget import DEADLINE_S, Deadline, Sizes
from sp_plugins.cli.gpu_check.checkpoint import check_checkpoint
from sp_plugins.cli.gpu_check.fit import check_fit
from sp_plugins.cli.gpu_check.repeat import check_repeat
from sp_plugins.cli.gpu_check.grid import check_grid
from sp_plugins.cli.gpu_check.machine import cuda_problem, machine_report
from sp_plugins.cli.gpu_check.report import Report, failure, log, summary_lines
from sp_plugins.cli.gpu_check.runs import check_runs

PARTS = ("grid", "runs", "checkpoint", "fit", "repeat")
DESCRIPTION = "sp-gpu-check: the first thing to run on a machine with an NVIDIA GPU (8 minutes at most)."


def parse_args(argv: Optional[Sequence[str]] = None) -> argparse.Namespace:
    """The command line; a bad value is argparse's one-line error (exit status 2)."""
    ap = argparse.ArgumentParser(prog="sp-gpu-check", description=DESCRIPTION)
    ap.add_argument("--out", type=Path, default=Path("gpu-check"), help="folder for the report and the runs (default: ./gpu-check)")
    ap.add_argument("--device", default="cuda", help="cuda, cuda:N or cpu (the CPU paths only; default: cuda)")
    ap.add_argument("--quick", action="store_true", help="tiny sizes (a CPU, or a smoke test)")
    ap.add_argument("--parts", nargs="+", choices=PARTS, default=list(PARTS), help="what to run (default: all)")
    ap.add_argument("--require-tcnn", action="store_true", help="a missing tinycudann is a failure, not a skip")
    ap.add_argument("--deadline", type=float, default=DEADLINE_S, help=f"seconds for everything, start-up included (default: {DEADLINE_S:.0f})")
    ap.add_argument("--tolerance", type=float, default=1e-2, help="relative error per point, tcnn vs torch (default: 1e-2)")
    ap.add_argument("--max-bad-fraction", type=float, default=1e-2, help="points allowed over the tolerance (default: 0.01)")
    ap.add_argument("--table-tolerance", type=float, default=5e-2, help="relative L2 of the table gradients (default: 0.05)")
    args = ap.parse_args(argv)
    for name in ("deadline", "tolerance", "max_bad_fraction", "table_tolerance"):
        if not getattr(args, name) > 0:
            ap.error(f"--{name.replace('_', '-')} must be positive")
    if args.device != "cpu" and not args.device.startswith("cuda"):
        ap.error(f"--device {args.device}: use cuda, cuda:N or cpu")
    return args


def main(argv: Optional[Sequence[str]] = None, own_process: bool = False) -> int:
    """The check; ``own_process`` (the console command): the deadline counts from the process start
    and, once reached, ends the process. Called from Python (a test, another tool), the deadline
    counts from the call and a reached deadline only records itself: the caller's process lives on."""
    args = parse_args(argv)
    deadline = Deadline(args.deadline, since_process_start=own_process)
    device = torch.device(args.device)
    if device.type == "cuda":
        problem = cuda_problem(args.device)
        if problem is not None:
            log(f"error: {problem}")
            return 1
        if device.index is None:
            device = torch.device("cuda", torch.cuda.current_device())
        torch.cuda.set_device(device)
    os.environ.setdefault("PYTHONWARNINGS", "ignore::DeprecationWarning")
    sizes = Sizes(args.quick)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    report = Report(out / "gpu_check.json", {"command": ["sp-gpu-check", *(argv if argv is not None else sys.argv[1:])],
                                             "machine": machine_report(device), "quick": args.quick,
                                             "deadline_s": args.deadline, "parts": {}})
    parts = report.data["parts"]
    if device.type != "cuda":
        report.data["skipped"] = [f"--device {device}: no GPU part runs (tcnn, CUDA timings and memory, CUDA sync debug mode, "
                                  "fp16 autocast); what runs is the CPU path of each part"]
        log(report.data["skipped"][0])
    current = {"part": None}

    def on_deadline() -> None:
        part = current["part"]
        if part is not None:
            parts[part] = {"status": "failed", "error": f"cut by the deadline (--deadline {args.deadline:.0f} s) while running"}
        report.data["deadline_reached"] = True
        report.data["seconds"] = deadline.elapsed()
        report.write()
        log(f"error: the deadline of {args.deadline:.0f} s was reached" + (f" during {part}" if part else "")
            + f"; report -> {report.path}")
        if own_process:
            os._exit(1)

    watchdog = threading.Timer(max(deadline.remaining(), 0.0), on_deadline)
    watchdog.daemon = True
    watchdog.start()
    artifacts: dict = {}
    checks = {
        "grid": lambda: check_grid(device, sizes, deadline, args.tolerance, args.max_bad_fraction, args.table_tolerance,
                                   args.require_tcnn),
        "runs": lambda: check_runs(device, sizes, out, deadline, artifacts),
        "checkpoint": lambda: check_checkpoint(device, sizes, out, deadline, artifacts),
        "fit": lambda: check_fit(device, sizes, deadline),
        "repeat": lambda: check_repeat(device, sizes, deadline),
    }
    needs = {"grid": 20, "runs": 60, "checkpoint": 20, "fit": 15, "repeat": 20}
    log_path = out / "log.txt"
    with open(log_path, "w") as host_output:
        for part in PARTS:
            if part not in args.parts:
                continue
            late = deadline.too_late(needs[part])
            if late:
                parts[part] = {"status": "failed", "reason": late}
                continue
            log(f"{part} ...")
            current["part"] = part
            start = time.perf_counter()
            try:
                with contextlib.redirect_stdout(host_output), contextlib.redirect_stderr(host_output):
                    parts[part] = checks[part]()
            except Exception as exc:  # a broken part is the finding: record it, run the others
                parts[part] = {"status": "failed", "error": failure(exc)}
            current["part"] = None
            parts[part]["seconds"] = time.perf_counter() - start
            report.data["seconds"] = deadline.elapsed()
            report.write()
    watchdog.cancel()
    report.data["seconds"] = deadline.elapsed()
    report.write()
    for line in summary_lines(report.data):
        log(line)
    failed = [p for p, r in parts.items() if r.get("status") == "failed"]
    log(f"{'FAILED: ' + ', '.join(failed) if failed else 'ok'}; report -> {report.path} ({report.data['seconds'] / 60:.1f} min; "
        f"the hosts' output in {log_path})")
    return 1 if failed else 0


def entrypoint() -> None:
    """The ``sp-gpu-check`` console command."""
    sys.exit(main(own_process=True))

