"""Mutation study: every mutant a mutation tool makes of SP's modules, each module run
against the test files that cover it, resumable, one torch thread. Outside the suite.

The tool is cosmic-ray (the ``dev`` extra), chosen over mutmut because:

- its test command is any shell command, set per session: each module gets its own covering test
  files (not the whole suite per mutant) and its own interpreter, so the sdfstudio modules run in
  ``.venv-sdfstudio`` while cosmic-ray itself lives in ``.venv`` (mutmut 3 runs pytest in-process in
  its own environment, over a ``mutants/`` copy of the whole project, with one test selection);
- a session is a SQLite file of work items: ``cosmic-ray exec`` runs only the items without a
  result, so a study stopped at any point (the machine is shared; sessions end) resumes where it
  stopped;
- it mutates one source file on disk and restores it: it runs here in a scratch copy of the checkout
  (``git ls-files``, ``PYTHONPATH`` first), never in the shared work tree; the copied module file
  is refreshed from the checkout before each run, so a run killed mid-mutant leaves nothing behind.

Usage (the full study is long: run it when the CPU is free)::

    python bench/mutation_study.py --list                       # modules and their covering tests
    python bench/mutation_study.py sp_plugins/core/schedule.py  # one module (the pilot)
    setsid nohup python bench/mutation_study.py --all > /tmp/mutation_study.log 2>&1 &   # every module, resumable, lowest priority
    python bench/mutation_study.py --before --all               # the same without the *_exact.py tests (before)
    python bench/mutation_study.py --report                     # the table from what has run

Per module it writes ``bench/results/mutation_study/<module>.json`` (generated, killed, survived,
timeout, equivalent, pending, wall time, the survivors' diffs) and the table
``bench/results/mutation_study/summary.md``. A surviving mutant that cannot change behaviour is
listed with its reason in ``bench/results/mutation_study/equivalent.json`` (module -> list of
``{"operator", "line", "reason"}``, ``line`` the original source line, stripped, and optionally
``occurrence``, cosmic-ray's index of the mutant, where only one of the line's mutants is); it is then counted
as equivalent, not survived. Which mutants each test was written for (and kills) is kept by hand in
``bench/results/mutation_study/kills.json`` (pytest id -> note), not in the tests' docstrings. The sessions
live in ``$SP_MUTATION_DIR`` (default ``~/.cache/sp-mutation-study``): delete a module's ``.sqlite`` there to
start it afresh. After the module changed the study does so itself; after only its covering tests (or their
list) changed, it runs the surviving mutants again and keeps the rest (a test added cannot revive a killed
mutant).

Each mutant's pytest runs in a fork of a server that imported torch & co. once
(``bench/mutation_forkserver.py``): ``core/noise.py``'s 43 mutants took 65 s this way against 512 s
in fresh interpreters, with the same outcome for every mutant (2026-12-05); ``SP_MUTATION_FORK=0``
runs a fresh interpreter per mutant. Stopping a study: ``pkill -f bench/mutation_study.py; pkill -f
"cosmic-ray exec"`` (its server stops within a second of the study; a test command that finds no
server runs the same pytest in a fresh interpreter, so a result is never a false "killed").

Two studies at once (one per core): give each its own ``SP_MUTATION_DIR`` (its own scratch copy and
sessions) and different modules; one process per directory. ``--report`` reads the default directory:
copy the other's ``<module>.sqlite``, ``.toml`` and ``.meta.json`` files there first.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import os
import re
import shutil
import sqlite3
import subprocess
import sys
import time
from pathlib import Path
from typing import Dict, Iterator, List, Optional, Tuple

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from bench.mutation_forkserver import NERFSTUDIO_PRELOAD, PRELOAD  # noqa: E402
from tests.mutations import MAIN_PYTHON, SDF_PYTHON, copy_checkout, environment  # noqa: E402

RESULTS = ROOT / "bench" / "results" / "mutation_study"
WORK = Path(os.environ.get("SP_MUTATION_DIR", Path.home() / ".cache" / "sp-mutation-study"))
COSMIC_RAY = MAIN_PYTHON.parent / "cosmic-ray"

_TASKS_EXACT = ["tests/tasks/test_pointcloud_exact.py", "tests/tasks/test_image_exact.py", "tests/tasks/test_sdf_exact.py"]
_NS_SEAM = ["tests/nerfstudio/test_seam_exact.py", "tests/nerfstudio/test_seam.py"]
_SDF_SEAM = ["tests/sdfstudio/test_seam_exact.py", "tests/sdfstudio/test_seam.py"]
_HOST_NEUTRAL = ["tests/adapter/test_extension_points.py"]  # the adapter on a toy host: 1 s, no host import
_CORE_PROPS = "tests/core/test_properties.py"
COVERING: Dict[str, Tuple[str, List[str]]] = {
    # module -> (environment, covering test files), cheapest first (pytest -x stops at the first failure).
    # Seconds (pytest's own, 2 shared cores, 5 Dec 2026) per file: ns seam_exact 11, ns test_seam 14, sdf seam_exact 5,
    # sdf test_seam 5, sdf test_methods 24, sdf test_any_method ~60, extension_points 1, test_with_sp 65,
    # test_sp_option_matrix 35, test_divergence 1, tasks *_exact 3 each, test_pointcloud 6, test_image 19,
    # test_image_modes 14, test_sdf 5, test_syncs 4, test_fields 3, test_fit_resume 36 (+5-7 s of imports per run).
    "sp_plugins/core/schedule.py": ("main", ["tests/core/test_schedule_exact.py", "tests/core/test_schedule.py",
                                             f"{_CORE_PROPS}::test_schedule_equals_its_formula_and_is_zero_at_and_after_the_end",
                                             f"{_CORE_PROPS}::test_preconditioner_returns_exactly_x_in_eval_and_at_and_after_the_end"]),
    "sp_plugins/core/boundary.py": ("main", ["tests/core/test_boundary_exact.py", "tests/core/test_perturb.py", _CORE_PROPS,
                                             "tests/tasks/test_syncs.py"]),  # (the dense fold's no-sync promise)
    "sp_plugins/core/perturb.py": ("main", ["tests/core/test_perturb_exact.py", "tests/core/test_perturb.py", _CORE_PROPS]),
    "sp_plugins/core/noise.py": ("main", ["tests/core/test_noise_exact.py", "tests/core/test_perturb.py",
                                          f"{_CORE_PROPS}::test_perturb_equals_the_reference",
                                          f"{_CORE_PROPS}::test_preconditioner_draws_the_configured_noise_kind"]),
    "sp_plugins/core/stencil.py": ("main", ["tests/core/test_stencil_exact.py", "tests/core/test_stencil.py"]),
    "sp_plugins/core/alpha_grid.py": ("main", ["tests/core/test_alpha_grid_exact.py", "tests/core/test_alpha_grid.py", _CORE_PROPS]),
    "sp_plugins/core/config.py": ("main", ["tests/core/test_config_exact.py", "tests/core/test_preconditioner.py", _CORE_PROPS]),
    "sp_plugins/core/preconditioner.py": ("main", ["tests/core/test_preconditioner_exact.py", "tests/core/test_preconditioner.py", _CORE_PROPS]),
    # the seams and the host wiring
    "sp_plugins/nerfstudio/seam.py": ("main", _NS_SEAM),
    "sp_plugins/sdfstudio/seam.py": ("sdfstudio", _SDF_SEAM + ["tests/sdfstudio/test_any_method.py::test_a_field_that_moved_nothing_is_refused_in_one_line"]),
    "sp_plugins/nerfstudio/model.py": ("main", ["tests/nerfstudio/test_model_exact.py", "tests/nerfstudio/test_divergence.py", *_NS_SEAM,
                                               "tests/nerfstudio/test_sp_option_matrix.py", "tests/nerfstudio/test_with_sp.py"]),
    "sp_plugins/sdfstudio/model.py": ("sdfstudio", ["tests/sdfstudio/test_model_exact.py", "tests/sdfstudio/test_seam_exact.py", "tests/sdfstudio/test_methods.py"]),
    "sp_plugins/nerfstudio/variants.py": ("main", ["tests/nerfstudio/test_variants_exact.py", "tests/nerfstudio/test_with_sp.py"]),
    "sp_plugins/sdfstudio/variants.py": ("sdfstudio", ["tests/sdfstudio/test_variants_exact.py", "tests/sdfstudio/test_methods.py", "tests/sdfstudio/test_any_method.py"]),
    # the adapter (host-neutral modules: the toy host first, then nerfstudio's)
    "sp_plugins/adapter/field.py": ("main", _HOST_NEUTRAL + _NS_SEAM),
    "sp_plugins/adapter/model.py": ("main", _HOST_NEUTRAL + _NS_SEAM),
    "sp_plugins/adapter/callbacks.py": ("main", ["tests/adapter/test_callbacks_exact.py", *_HOST_NEUTRAL, "tests/nerfstudio/test_seam.py",
                                                                "tests/nerfstudio/test_neuralangelo_schedule.py"]),
    "sp_plugins/adapter/presets.py": ("main", ["tests/adapter/test_presets_exact.py", "tests/test_defaults_table.py", "tests/nerfstudio/test_with_sp.py"]),
    "sp_plugins/adapter/tables.py": ("main", ["tests/adapter/test_tables_exact.py", "tests/nerfstudio/test_method_table.py", "tests/nerfstudio/test_seam.py",
                                             "tests/nerfstudio/test_with_sp.py"]),
    "sp_plugins/adapter/variants.py": ("main", ["tests/adapter/test_variants_exact.py", "tests/nerfstudio/test_with_sp.py"]),
    "sp_plugins/adapter/checks.py": ("main", ["tests/adapter/test_checks_exact.py", "tests/cli/test_device_flags.py", "tests/nerfstudio/test_bad_input_ns.py"]),
    "sp_plugins/adapter/lpips.py": ("main", ["tests/adapter/test_lpips_exact.py", "tests/nerfstudio/test_ns_lpips.py"]),
    "sp_plugins/adapter/errors.py": ("main", ["tests/adapter/test_errors_exact.py", "tests/cli/test_bad_input.py", "tests/nerfstudio/test_safe_config_ns.py"]),
    "sp_plugins/adapter/safe_config.py": ("main", ["tests/adapter/test_safe_config_exact.py", "tests/cli/test_fuzz_inputs.py", "tests/nerfstudio/test_safe_config_ns.py"]),
    "sp_plugins/adapter/shrink.py": ("main", ["tests/adapter/test_shrink_exact.py", "tests/nerfstudio/test_seam_exact.py", "tests/nerfstudio/test_sp_option_matrix.py"]),
    # the sp-fit tasks
    "sp_plugins/tasks/pointcloud.py": ("main", ["tests/tasks/test_pointcloud_exact.py", "tests/tasks/test_pointcloud.py"]),
    "sp_plugins/tasks/image.py": ("main", ["tests/tasks/test_image_exact.py", "tests/tasks/test_image.py", "tests/tasks/test_image_modes.py"]),
    "sp_plugins/tasks/sdf.py": ("main", ["tests/tasks/test_sdf_exact.py", "tests/tasks/test_sdf.py"]),
    "sp_plugins/tasks/trainer.py": ("main", ["tests/tasks/test_trainer_exact.py"] + _TASKS_EXACT + ["tests/tasks/test_syncs.py", "tests/tasks/test_fit_resume.py"]),
    "sp_plugins/tasks/common.py": ("main", ["tests/tasks/test_common_exact.py"] + _TASKS_EXACT + ["tests/tasks/test_fit_resume.py"]),
    "sp_plugins/tasks/fields.py": ("main", ["tests/tasks/test_fields_exact.py", "tests/tasks/test_fields.py"] + _TASKS_EXACT),
    "sp_plugins/tasks/checkpoint.py": ("main", ["tests/tasks/test_checkpoint_exact.py", "tests/tasks/test_fit_resume.py"]),
    "sp_plugins/tasks/settings.py": ("main", ["tests/tasks/test_settings_exact.py", "tests/tasks/test_sdf_exact.py",
                                             "tests/tasks/test_cli_fit.py"]),
}
"""The issue's modules (the seams, the adapter, the nerfstudio model wiring, the tasks, the core),
each with its covering test files or test ids. An adapter module not listed here (errors, checks,
safe_config, ...) gets the test files that name it (:func:`covering`)."""
ISSUE_FOLDERS = ["sp_plugins/core", "sp_plugins/adapter", "sp_plugins/tasks"]


BEFORE = os.environ.get("SP_MUTATION_BEFORE") == "1"
"""``--before``: the covering tests without the exact-value modules (``*_exact.py``), in
sessions and results of their own (``*.before.*``): the figures before those tests existed."""


def covering(module: str) -> Tuple[str, List[str]]:
    """The environment and covering test files of ``module``: :data:`COVERING`, else the test files
    whose source imports it by its dotted name (without the exact-value tests under ``--before``)."""
    kind, tests = _covering(module)
    return kind, [t for t in tests if not (BEFORE and t.split("::")[0].endswith("_exact.py"))]


def _covering(module: str) -> Tuple[str, List[str]]:
    if module in COVERING:
        return COVERING[module]
    dotted = module[:-3].replace("/", ".")
    env = "sdfstudio" if module.startswith("sp_plugins/sdfstudio/") else "main"
    found = sorted(str(p.relative_to(ROOT)) for p in (ROOT / "tests").rglob("test_*.py")
                   if dotted in p.read_text() and (env == "sdfstudio") == ("tests/sdfstudio" in str(p)))
    return env, found


def modules_of(args: List[str]) -> List[str]:
    out = []
    for a in args:
        p = ROOT / a
        out += sorted(str(f.relative_to(ROOT)) for f in p.rglob("*.py") if f.name != "__init__.py") if p.is_dir() else [a]
    return out


def slug(module: str) -> str:
    return module[:-3].replace("/", ".") + (".before" if BEFORE else "")


def python_of(kind: str) -> Path:
    return MAIN_PYTHON if kind == "main" else SDF_PYTHON


FORK = os.environ.get("SP_MUTATION_FORK", "1") != "0"
"""Each mutant's pytest in a fork of a server that has imported torch & co. once
(``bench/mutation_forkserver.py``; 3-8x faster); ``SP_MUTATION_FORK=0``: a fresh interpreter each."""
FORKSERVER = ROOT / "bench" / "mutation_forkserver.py"


def socket_of(kind: str) -> Path:
    return WORK / f"forkserver-{kind}.sock"


def test_command(module: str) -> str:
    kind, tests = covering(module)
    runner = f"-S {FORKSERVER} run {socket_of(kind)}" if FORK else "-m pytest"
    return f"{python_of(kind)} {runner} -q -x -p no:cacheprovider -p pytest_timeout " + " ".join(tests)


@contextlib.contextmanager
def forkserver(kind: str, copy: Path, env: Dict[str, str]) -> Iterator[None]:
    """The fork server of ``kind``'s environment, ready for the block and stopped after it (nothing
    without ``FORK``)."""
    if not FORK:
        yield
        return
    preload = PRELOAD + (NERFSTUDIO_PRELOAD if kind == "main" else [])
    server = subprocess.Popen([str(python_of(kind)), str(FORKSERVER), "serve", str(socket_of(kind)), *preload], cwd=copy, env=env,
                              stdout=subprocess.PIPE, text=True)
    try:
        if server.stdout.readline().strip() != "ready":
            raise SystemExit(f"mutation_study: the fork server of {kind} did not start (SP_MUTATION_FORK=0 runs without it)")
        yield
    finally:
        server.kill()
        server.wait()


def study_environment(copy: Path) -> Dict[str, str]:
    """The tests' environment, without pytest's plugin autoload: the environments' third-party plugins
    (anyio, typeguard, jaxtyping, xdist, ...) cost ~2 s of a ~9 s mutant run and no covering test uses
    them (the unmutated baseline must pass under the same environment, so a test that did would stop
    the study, never count a mutant killed)."""
    return dict(environment(copy), PYTEST_DISABLE_PLUGIN_AUTOLOAD="1")


def fingerprint(module: str) -> str:
    """Hash of the module's source: its session is redone from scratch when it changed."""
    return hashlib.sha256((ROOT / module).read_bytes()).hexdigest()[:16]


def tests_fingerprint(module: str) -> str:
    """Hash of the covering test files: when only they changed, the survivors are run again."""
    h = hashlib.sha256()
    for test in dict.fromkeys(t.split("::")[0] for t in covering(module)[1]):
        h.update((ROOT / test).read_bytes())
    return h.hexdigest()[:16]


def rerun_survivors(session: Path, module: str) -> int:
    """Forget the results of the surviving mutants not listed as equivalent (``cosmic-ray exec``
    then runs them again); returns how many. Tests that were added or tightened cannot revive a
    killed mutant, so only the survivors need the new tests (delete the ``.sqlite`` for a full run)."""
    source = (ROOT / module).read_text().splitlines()
    known = {(e["operator"], e["line"], e.get("occurrence")) for e in _equivalents().get(module, [])}
    with sqlite3.connect(session) as db:
        rows = db.execute("SELECT r.job_id, m.operator_name, m.start_pos_row, m.occurrence FROM work_results r "
                          "JOIN mutation_specs m ON m.job_id = r.job_id WHERE lower(r.test_outcome) = 'survived'").fetchall()
        again = [job for job, op, row, occ in rows
                 if not {(op, source[row - 1].strip(), occ), (op, source[row - 1].strip(), None)} & known]
        db.executemany("DELETE FROM work_results WHERE job_id = ?", [(job,) for job in again])
    return len(again)


def prepare_copy() -> Path:
    """The scratch checkout the tool mutates: copied once, its sources refreshed on every call."""
    copy = WORK / "checkout"
    copy.mkdir(parents=True, exist_ok=True)
    copy_checkout(copy)
    return copy


def run_module(module: str, timeout_floor: float) -> Optional[dict]:
    """Init (unless a session of this source exists), baseline once, exec the pending mutants;
    None (and a line saying so) for a module no test file covers."""
    kind, tests = covering(module)
    if not tests:
        print(f"mutation_study: no test file covers {module}: skipped (add it to COVERING)", flush=True)
        return None
    copy = prepare_copy()
    env = study_environment(copy)
    source_hash, tests_hash = fingerprint(module), tests_fingerprint(module)
    session, config, meta_path = (WORK / f"{slug(module)}{ext}" for ext in (".sqlite", ".toml", ".meta.json"))
    meta = json.loads(meta_path.read_text()) if meta_path.exists() else {}
    cmd = test_command(module)
    with forkserver(kind, copy, env):
        fresh = meta.get("source") != source_hash or not session.exists()
        if fresh or meta.get("command") != cmd or meta.get("tests") != tests_hash:
            start = time.perf_counter()
            base = subprocess.run(cmd.split(), cwd=copy, env=env, capture_output=True, text=True)
            baseline_s = time.perf_counter() - start
            if base.returncode != 0:
                tail = (base.stdout + base.stderr).strip().splitlines()[-3:]
                raise SystemExit(f"mutation_study: the covering tests of {module} fail unmutated: {' | '.join(tail)}")
            timeout = max(timeout_floor, 4.0 * baseline_s)
            config.write_text(
                "[cosmic-ray]\n"
                f'module-path = "{module}"\ntimeout = {timeout:.0f}\nexcluded-modules = []\n'
                f"test-command = {json.dumps(cmd)}\n\n[cosmic-ray.distributor]\nname = \"local\"\n"
            )
            if fresh:
                session.unlink(missing_ok=True)
                subprocess.run([str(COSMIC_RAY), "init", str(config), str(session)], cwd=copy, env=env, check=True)
                meta = {"exec_s": 0.0}
            else:
                print(f"mutation_study: {module}: its tests changed; running its {rerun_survivors(session, module)} survivors "
                      "(not listed as equivalent) again", flush=True)
            meta.update(source=source_hash, tests=tests_hash, command=cmd, baseline_s=round(baseline_s, 1), timeout_s=round(timeout))
            meta_path.write_text(json.dumps(meta))
        start = time.perf_counter()
        try:
            subprocess.run([str(COSMIC_RAY), "exec", str(config), str(session)], cwd=copy, env=env, check=True)
        finally:
            meta["exec_s"] = round(meta.get("exec_s", 0.0) + time.perf_counter() - start, 1)
            meta_path.write_text(json.dumps(meta))
            shutil.copy2(ROOT / module, copy / module)  # whatever the tool left, the copy is the checkout's again
        return summarise(module)


def _equivalents() -> dict:
    path = RESULTS / "equivalent.json"
    return json.loads(path.read_text()) if path.exists() else {}


def summarise(module: str) -> dict:
    """Figures of the module's session, written to its JSON file."""
    session, meta_path = WORK / f"{slug(module)}.sqlite", WORK / f"{slug(module)}.meta.json"
    meta = json.loads(meta_path.read_text())
    dump = subprocess.run([str(COSMIC_RAY), "dump", str(session)], capture_output=True, text=True, check=True).stdout
    source = (ROOT / module).read_text().splitlines()
    known = {(e["operator"], e["line"], e.get("occurrence")): e["reason"] for e in _equivalents().get(module, [])}
    counts = dict(generated=0, killed=0, survived=0, timeout=0, equivalent=0, incompetent=0, pending=0)
    survivors, equivalent = [], []
    for row in filter(None, dump.splitlines()):
        item, result = json.loads(row)
        counts["generated"] += 1
        if result is None:
            counts["pending"] += 1
            continue
        mutation = item["mutations"][0]
        line_no = mutation["start_pos"][0]
        entry = {"operator": mutation["operator_name"], "occurrence": mutation["occurrence"], "line_no": line_no,
                 "line": source[line_no - 1].strip() if line_no <= len(source) else "", "diff": result.get("diff")}
        outcome, output = result.get("test_outcome"), result.get("output") or ""
        if result.get("worker_outcome") not in ("normal", None) or outcome == "incompetent":
            counts["incompetent"] += 1
        elif outcome == "killed":
            counts["timeout" if output == "timeout" else "killed"] += 1
        elif (known.get((entry["operator"], entry["line"], entry["occurrence"]))
              or known.get((entry["operator"], entry["line"], None))):
            counts["equivalent"] += 1
            reason = known.get((entry["operator"], entry["line"], entry["occurrence"])) or known[(entry["operator"], entry["line"], None)]
            equivalent.append(dict(entry, reason=reason))
        else:
            counts["survived"] += 1
            survivors.append(entry)
    kind, tests = covering(module)
    command = f"python bench/mutation_study.py {'--before ' if BEFORE else ''}{module}"
    figures = dict(module=module, variant="before" if BEFORE else "after", environment=kind, tests=tests, command=command,
                   **counts, baseline_s=meta["baseline_s"], timeout_s=meta["timeout_s"], wall_s=meta["exec_s"],
                   survivors=survivors, equivalent_mutants=equivalent)
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"{slug(module)}.json").write_text(json.dumps(figures, indent=1) + "\n")
    return figures


def write_table() -> str:
    rows = [json.loads(p.read_text()) for p in sorted(RESULTS.glob("sp_plugins.*.json"))]
    lines = ["| module | tests | env | covering tests | generated | killed | timeout | equivalent | survived | pending | wall (s) |",
             "| --- | --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in rows:
        tests = ", ".join(re.sub(r"^tests/", "", t) for t in r["tests"])
        lines.append(f"| `{r['module']}` | {r.get('variant', 'after')} | {r['environment']} | {tests} | {r['generated']} | {r['killed']} | {r['timeout']} | "
                     f"{r['equivalent']} | {r['survived']} | {r['pending']} | {r['wall_s']:.0f} |")
    table = "\n".join(lines) + "\n"
    (RESULTS / "summary.md").write_text("# Mutation study (bench/mutation_study.py)\n\n" + table)
    return table


def yield_the_cpu() -> None:
    """Run at the lowest priority against every other job on the machine. ``nice`` alone does not do that
    on Linux with autogroup scheduling (``/proc/sys/kernel/sched_autogroup_enabled``): CPU is shared fairly
    between *sessions* first, so a niced study in its own session took half of a 2-core machine from a CI run
    in another (measured: the suite ran about 2x slower). Started with ``setsid`` the study is its own session,
    and its autogroup is niced too; from a terminal (not a session leader) only the process is niced, never
    the terminal's session."""
    os.nice(19 - os.nice(0))
    if os.getsid(0) == os.getpid():
        try:
            Path("/proc/self/autogroup").write_text("19")
        except OSError:
            pass


def main(argv: Optional[List[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("modules", nargs="*", help="module files or folders (default with --all: every module of COVERING)")
    ap.add_argument("--all", action="store_true", help="every module of the issue (COVERING), one after another")
    ap.add_argument("--list", action="store_true", help="print each module's environment and covering tests")
    ap.add_argument("--report", action="store_true", help="rewrite the JSON figures and the table from the sessions")
    ap.add_argument("--before", action="store_true", help="without the exact-value tests (*_exact.py): the 'before' figures")
    ap.add_argument("--timeout-floor", type=float, default=60.0, help="least seconds per mutant (else 4x the baseline)")
    args = ap.parse_args(argv)
    if not (args.list or args.report):
        yield_the_cpu()
    if args.before:
        global BEFORE
        BEFORE = True
    modules = list(dict.fromkeys(list(COVERING) + modules_of(ISSUE_FOLDERS))) if args.all else modules_of(args.modules)
    if args.list:
        for m in modules or list(COVERING):
            kind, tests = covering(m)
            print(f"{m} [{kind}]: {' '.join(tests) or 'NO COVERING TEST'}")
        return 0
    os.environ.update(OMP_NUM_THREADS="1", OMP_WAIT_POLICY="PASSIVE")
    if args.report:
        for m in modules or list(COVERING):
            if (WORK / f"{slug(m)}.meta.json").exists():
                summarise(m)
        print(write_table())
        return 0
    if not modules:
        ap.error("name modules, or --all")
    for m in modules:
        f = run_module(m, args.timeout_floor)
        if f is None:
            continue
        print(f"{m}: generated {f['generated']}, killed {f['killed']}, timeout {f['timeout']}, equivalent {f['equivalent']}, "
              f"survived {f['survived']}, pending {f['pending']} ({f['wall_s']:.0f} s)", flush=True)
        write_table()
    print(write_table())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
