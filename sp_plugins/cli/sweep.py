"""sp-sweep: a grid of flag values (with SP on/off as a paired axis) over any of our nerfstudio
methods (through ``ns-train`` + ``ns-eval``) or any ``sp-fit`` task, on Ray Tune.

    sp-sweep study.yaml --out runs/study                      # local Ray on the free cores
    sp-sweep study.yaml --out runs/study --address auto       # an existing Ray cluster
    sp-sweep --command "sp-fit pointcloud bunny.ply --steps 300" --grid lr=1e-3,1e-2 \\
        --grid encoding.max-resolution=256,1024 --success "sound == 1" --out runs/pc

Restarting the same command skips finished trials (also after a crash or Ctrl-C); a failed trial
is recorded with its error and the sweep goes on. A trial's device (cpu, or cuda with
--gpus-per-trial) is part of it: a folder of finished trials from another device is refused. Results: ``results.csv``, ``results.md``
(table, success rates, per-axis medians) and ``histogram.png`` in --out.
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import List, Literal, Optional, Tuple, TypeVar

import tyro

from sp_plugins.cli import threads
from sp_plugins.sweeps.ray_runner import run_on_ray
from sp_plugins.sweeps.report import load_results, other_devices, write_report
from sp_plugins.sweeps.spec import SpecError, SweepSpec, expand, flag_name, load_spec, spec_from_dict
from sp_plugins.sweeps.trial import RESULT, TRIAL, _write_result

T = TypeVar("T")


# a list flag given twice must add up, not keep its last value (tyro's default): --grid a=1 --grid b=2
Repeatable = tyro.conf.UseAppendAction[List[T]]


@dataclass
class SweepArgs:
    spec: tyro.conf.Positional[Optional[Path]] = None
    """A YAML / JSON spec file (fields: command, data, grid, sp, sp_methods, seeds, sample, success,
    metric); the flags below override its fields."""
    command: Optional[str] = None
    """Base command, e.g. 'sp-fit pointcloud mesh.ply --steps 300' or 'ns-train neus-hashgrid --max-num-iterations 300'."""
    data: Optional[str] = None
    """ns-train: the dataparser and its flags, e.g. 'blender-data --data scene/blender'."""
    grid: Repeatable[Tuple[str, ...]] = dataclasses.field(default_factory=list)
    """Axes as FLAG=V1,V2,... (flag without leading dashes), e.g. lr=1e-3,1e-2; repeat --grid for more axes
    (each flag once); replaces the spec's grid."""
    sp: Optional[Literal["both", "on", "off"]] = None
    """SP axis: both (each grid point with and without SP), on, off. Default: both."""
    sp_methods: Optional[Tuple[str, str]] = None
    """ns-train: a baseline and an SP method (e.g. neus-hashgrid sp-neus-hashgrid) instead of --pipeline.model.sp.enabled."""
    seeds: Repeatable[Tuple[int, ...]] = dataclasses.field(default_factory=list)
    """Seeds (default: 0)."""
    sample: Optional[int] = None
    """Run only this many grid points, chosen at random (a fractional grid); SP pairs stay together."""
    success: Repeatable[Tuple[str, ...]] = dataclasses.field(default_factory=list)
    """What counts as success, e.g. 'psnr >= 24' or 'sound == 1' 'fscore >= 0.9' (all must hold)."""
    metric: Optional[str] = None
    """Metric of the histogram and the medians (default: psnr for ns-train, chamfer for sp-fit)."""
    out: Path = Path("outputs/sp-sweep")
    """Folder of the sweep: trials/<key>/ per trial, results.csv / .md, histogram.png."""
    address: Optional[str] = None
    """Ray cluster to use ('auto' or HOST:PORT); default: start a local Ray."""
    num_cpus: Optional[int] = None
    """Local Ray: CPUs to use (default: the cores other processes leave idle)."""
    num_gpus: Optional[int] = None
    """Local Ray: GPUs to use (default: 0)."""
    cpus_per_trial: float = 1.0
    """CPUs each trial reserves (also its torch threads)."""
    gpus_per_trial: float = 0.0
    """GPUs each trial reserves (ns-train trials then train on cuda)."""
    timeout: Optional[float] = None
    """Seconds after which a trial's command is stopped and the trial recorded as failed."""
    retry_failed: bool = False
    """Run failed trials again (by default a restart skips every finished trial, failed or not)."""
    summarize_only: bool = False
    """Only rebuild the table, histogram and success line from the results so far."""
    dry_run: bool = False
    """List the trials and which of them have finished, and stop."""
    ray_temp_dir: Optional[Path] = None
    """Local Ray's temporary folder (removed at the end; keep it short: Ray's socket paths are limited)."""


def _flat(groups: List[Tuple]) -> list:
    """Values of a repeatable flag, every occurrence in order (``--grid a=1 b=2 --grid c=3``)."""
    return [v for group in groups for v in group]


def _grid(entries: List[str]) -> dict:
    grid, seen = {}, {}
    for e in entries:
        flag, sep, values = e.partition("=")
        if not sep or not flag.strip() or not values.strip():
            raise SpecError(f"--grid {e!r}: write FLAG=V1,V2 (e.g. lr=1e-3,1e-2)")
        flag, values = flag.strip(), [v.strip() for v in values.split(",")]
        name = flag_name(flag)
        if name in seen:  # which values would win is a guess: ask for one list
            both = ",".join(seen[name] + values)
            raise SpecError(f"--grid {name.lstrip('-')} is given twice: give all its values in one --grid "
                            f"{name.lstrip('-')}={both}")
        seen[name] = grid[flag] = values
    return grid


def build_spec(args: SweepArgs) -> SweepSpec:
    import shlex

    raw = {}
    if args.spec is not None:
        spec = load_spec(args.spec)
        raw = dataclasses.asdict(spec)
    overrides = {
        "command": args.command and shlex.split(args.command), "data": args.data and shlex.split(args.data),
        "grid": _grid(_flat(args.grid)) or None, "sp": args.sp, "sp_methods": args.sp_methods,
        "seeds": _flat(args.seeds) or None, "sample": args.sample, "success": _flat(args.success) or None, "metric": args.metric,
    }
    raw.update({k: v for k, v in overrides.items() if v is not None})
    if "command" not in raw:
        raise SpecError("nothing to sweep: give a spec file or --command")
    return spec_from_dict(raw)


def _local_cpus(args: SweepArgs, log) -> int:
    if args.num_cpus is not None:
        if args.num_cpus < 1:
            raise SpecError(f"--num-cpus {args.num_cpus}: must be at least 1")
        return args.num_cpus
    free, cores = threads.free_cores(), threads.usable_cores()
    if free < cores:
        log(f"[sp-sweep] {cores - free} of {cores} cores are busy with other processes: local Ray gets {free} "
            f"(--num-cpus N overrides)")
    return free


def _mixed_devices(out: Path, found: dict, trials, args: SweepArgs) -> str:
    """The refusal when ``out`` holds results of this sweep from another device."""
    theirs = ", ".join(f"{n} on {d}" for d, n in sorted(found.items()))
    mine = "/".join(sorted({t.device for t in trials}))
    back = "--gpus-per-trial 0" if "cpu" in found else "--gpus-per-trial 1 (on a local Ray with --num-gpus)"
    return (f"{out} holds finished trials of this sweep run elsewhere ({theirs}); with --gpus-per-trial "
            f"{args.gpus_per_trial:g} they run on {mine}, and one table of both would compare devices, not settings: "
            f"give the {mine} sweep another --out (or pass {back} to go on with the trials there)")


def run(args: SweepArgs, log=print) -> int:
    spec = build_spec(args)
    trials = expand(spec, gpus=args.gpus_per_trial)
    out = args.out.resolve()
    folder = out / "trials"
    elsewhere = other_devices(folder, trials)
    if elsewhere:
        raise SpecError(_mixed_devices(out, elsewhere, trials, args))

    def start_folder() -> None:
        folder.mkdir(parents=True, exist_ok=True)
        (out / "spec.json").write_text(json.dumps(dataclasses.asdict(spec), indent=1) + "\n")

    results = load_results(folder, trials)
    if args.retry_failed:
        results = {k: r for k, r in results.items() if r.get("status") == "ok"}
    pending = [t for t in trials if t.key not in results]
    log(f"[sp-sweep] {len(trials)} trials: {len(trials) - len(pending)} finished already (skipped), {len(pending)} to run")
    if args.dry_run:
        start_folder()
        for t in trials:
            log(f"  {t.key}  {'done   ' if t.key in results else 'pending'}  {t.device:<4}  {t.label()}")
        return 0
    if pending and not args.summarize_only:
        if args.cpus_per_trial <= 0 or args.gpus_per_trial < 0:
            raise SpecError("--cpus-per-trial must be > 0 and --gpus-per-trial >= 0")
        num_cpus = None if args.address else _local_cpus(args, log)
        if num_cpus is not None and args.cpus_per_trial > num_cpus:
            raise SpecError(f"--cpus-per-trial {args.cpus_per_trial:g} is more than the {num_cpus} CPU(s) of the local Ray "
                            "(--num-cpus): no trial could start")
        if not args.address and args.gpus_per_trial > (args.num_gpus or 0):
            raise SpecError(f"--gpus-per-trial {args.gpus_per_trial:g} needs --num-gpus of at least that on a local Ray")

        def payload() -> list:
            """The pending trials' folders and ``trial.json``, written once Ray is up (a cluster that
            does not answer leaves nothing behind)."""
            start_folder()
            items = []
            for t in pending:
                d = folder / t.key
                d.mkdir(exist_ok=True)
                info = {"key": t.key, "params": t.params, "sp": t.sp, "seed": t.seed, "argv": t.argv, "label": t.label(),
                        "device": t.device, "folder": str(d), "cwd": os.getcwd(), "data_args": len(spec.data),
                        "timeout": args.timeout, "eval": spec.eval}
                (d / TRIAL).write_text(json.dumps(info, indent=1) + "\n")
                items.append(info)
            return items

        lost = run_on_ray(payload, storage=out / "ray", address=args.address, num_cpus=num_cpus, num_gpus=args.num_gpus,
                          cpus_per_trial=args.cpus_per_trial, gpus_per_trial=args.gpus_per_trial,
                          temp_dir=args.ray_temp_dir, log=log)
        for item in lost:  # Ray lost the worker before the trial could write its own result
            d = folder / item["key"]
            if not (d / RESULT).is_file():
                t = next(t for t in pending if t.key == item["key"])
                _write_result(d, {"key": t.key, "params": t.params, "sp": t.sp, "seed": t.seed, "device": t.device,
                                  "status": "failed", "error": item["error"], "metrics": {}})
        results = load_results(folder, trials)
    start_folder()
    report = write_report(spec, trials, results, out)
    log(f"[sp-sweep] {report['summary']}")
    log(f"[sp-sweep] wrote {out / 'results.md'}, {out / 'results.csv'}"
        + (f", {report['histogram']}" if report["histogram"] else ""))
    return 0


def main(argv: Optional[List[str]] = None) -> int:
    args = tyro.cli(SweepArgs, args=argv, prog="sp-sweep", description=__doc__.split("\n\n")[0])
    try:
        return run(args)
    except SpecError as err:
        print(f"sp-sweep: error: {err}", file=sys.stderr)
        return 2


def entrypoint() -> None:
    sys.exit(main())


if __name__ == "__main__":
    entrypoint()
