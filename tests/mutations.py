"""Mutation check: does a test go red when the behaviour it names breaks?

Not part of the suite (no ``test_`` prefix): run it by hand, after changing SP code or the tests
that guard it::

    python tests/mutations.py                 # every mutation
    python tests/mutations.py --only "eval perturbed" --only "reflect -> clamp"
    python tests/mutations.py --list

It copies the checkout (``git ls-files``, working-tree contents) to a scratch folder, runs each
mutation's test sets there once unmutated (a set that fails unmutated proves nothing), then, one
at a time, applies a named semantic mutation (an exact replacement that must match once, else the
mutation is reported STALE: the code moved and the mutation needs updating) and runs its test
sets in order until one fails. ``PYTHONPATH`` puts the copy first, so the copy's ``sp_plugins``
is imported (checked once per interpreter), also by the console commands tests start. sdfstudio
mutations run in the sdfstudio environment. Per mutation it prints KILLED by <test> or SURVIVED,
and the seconds; the exit status is 1 when any survived, was stale, or had a failing baseline.
One torch thread per process: the machine is shared.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

ROOT = Path(__file__).resolve().parents[1]
MAIN_PYTHON = Path(os.environ.get("SP_VENV", ROOT / ".venv")) / "bin" / "python"
SDF_PYTHON = Path(os.environ.get("SP_SDFSTUDIO_VENV", ROOT / ".venv-sdfstudio")) / "bin" / "python"
TIMEOUT_S = 1200

TestSet = Tuple[str, Tuple[str, ...]]
"""(environment: "main" or "sdfstudio", pytest arguments)."""

CORE: TestSet = ("main", ("tests/core",))
NS_SEAM: TestSet = ("main", ("tests/nerfstudio/test_seam.py",))
NS_MATRIX: TestSet = ("main", ("tests/nerfstudio/test_sp_option_matrix.py", "-k", "plain"))
RESUME: TestSet = ("main", ("tests/tasks/test_fit_resume.py",))
DEMO_CONFIGS: TestSet = ("main", ("tests/cli/test_demo.py::test_the_demos_two_runs_differ_only_in_sp",))
DEMO_RUN: TestSet = ("main", ("tests/cli/test_demo.py::test_demo_writes_a_results_table_meshes_renders_and_a_plot",))
_ANY = "tests/sdfstudio/test_any_method.py::"
SDF_TRAINS: TestSet = ("sdfstudio", (_ANY + "test_sp_method_trains_two_steps_with_sp_active[neus]",
                                     _ANY + "test_sp_method_trains_two_steps_with_sp_active[neuralangelo]"))
SDF_MOVES: TestSet = ("sdfstudio", (_ANY + "test_the_fields_queries_move_against_the_plain_positions",))
SPARSE_GAP: TestSet = ("main", ("tests/bench/test_sparse_views_gap.py",))
# the exact-value tests: what a field reads equals the paper's formula for a fixed draw
NS_EXACT: TestSet = ("main", ("tests/nerfstudio/test_seam_exact.py",))
SDF_EXACT: TestSet = ("sdfstudio", ("tests/sdfstudio/test_seam_exact.py",))
SDF_SEAM: TestSet = ("sdfstudio", ("tests/sdfstudio/test_seam.py",))
POINTCLOUD_EXACT: TestSet = ("main", ("tests/tasks/test_pointcloud_exact.py",))
IMAGE_EXACT: TestSet = ("main", ("tests/tasks/test_image_exact.py",))
SDF_TASK_EXACT: TestSet = ("main", ("tests/tasks/test_sdf_exact.py",))
NOISE_EXACT: TestSet = ("main", ("tests/core/test_noise_exact.py",))
NS_MODEL_EXACT: TestSet = ("main", ("tests/nerfstudio/test_model_exact.py",))
SDF_MODEL_EXACT: TestSet = ("sdfstudio", ("tests/sdfstudio/test_model_exact.py",))
ALPHA_GRID_EXACT: TestSet = ("main", ("tests/core/test_alpha_grid_exact.py",))
PRECONDITIONER_EXACT: TestSet = ("main", ("tests/core/test_preconditioner_exact.py",))
SAFE_CONFIG_EXACT: TestSet = ("main", ("tests/adapter/test_safe_config_exact.py",))


@dataclass(frozen=True)
class Mutation:
    name: str
    path: str
    old: str
    new: str
    tests: Tuple[TestSet, ...]
    """Run in order until one fails: the cheapest that should kill it first."""


MUTATIONS: List[Mutation] = [
    # -- the hosts' seams: offsets drawn but never applied ----------------------------------------
    Mutation("nerfstudio seam: offsets not applied", "sp_plugins/nerfstudio/seam.py",
             'values["origins"] = frustums.origins + (q - x)', 'values["origins"] = frustums.origins',
             (NS_SEAM, NS_MATRIX)),
    Mutation("MipNeRF's Gaussian means not moved", "sp_plugins/nerfstudio/seam.py",
             'values["origins"] = frustums.origins + (q - x)', 'values["origins"] = frustums.origins',
             (SPARSE_GAP,)),
    Mutation("sdfstudio seam: contraction does not move", "sp_plugins/sdfstudio/seam.py",
             "moved = handle.sp(plain)", "moved = plain", (SDF_TRAINS, SDF_MOVES)),
    Mutation("sdfstudio seam: contraction returns its input", "sp_plugins/sdfstudio/seam.py",
             "        return moved\n", "        return plain\n", (SDF_TRAINS, SDF_MOVES)),
    # -- where SP moved a query, not only that it moved (the exact-value tests) -----------
    Mutation("nerfstudio seam: SDF fields' offset taken at the midpoint", "sp_plugins/nerfstudio/table.py",
             '"nerfstudio.fields.sdf_field.SDFField": "get_start_positions",',
             '"nerfstudio.fields.sdf_field.SDFField": "get_positions",', (NS_EXACT,)),
    Mutation("nerfstudio seam: K-draw normals not recomputed", "sp_plugins/nerfstudio/seam.py",
             "outputs[FieldHeadNames.NORMALS] = F.normalize(outputs[FieldHeadNames.GRADIENT], p=2, dim=-1)",
             "outputs[FieldHeadNames.NORMALS] = outputs[FieldHeadNames.NORMALS]", (NS_EXACT,)),
    Mutation("nerfstudio seam: offset detached (alpha grid)", "sp_plugins/nerfstudio/seam.py",
             'values["origins"] = frustums.origins + (q - x)', 'values["origins"] = frustums.origins + (q - x).detach()',
             (NS_EXACT,)),
    # survivors of the mutation study (bench/mutation_study.py), killed by the tests written for them
    Mutation("nerfstudio seam: boundary clamp not refused on a contracting field", "sp_plugins/nerfstudio/seam.py",
             'if boundary != "none" and getattr(f, "spatial_distortion", None)',
             'if boundary > "none" and getattr(f, "spatial_distortion", None)', (NS_SEAM,)),
    Mutation("nerfstudio seam: boundary compared by identity (a parsed none refused)", "sp_plugins/nerfstudio/seam.py",
             'if boundary != "none" and getattr(f, "spatial_distortion", None)',
             'if boundary is not "none" and getattr(f, "spatial_distortion", None)', (NS_SEAM,)),
    Mutation("nerfstudio seam: K draws of predicted normals without a gradient", "sp_plugins/nerfstudio/seam.py",
             "if not isinstance(outputs, dict) or FieldHeadNames.GRADIENT not in outputs:",
             "if not isinstance(outputs, dict) and FieldHeadNames.GRADIENT not in outputs:", (NS_EXACT,)),
    Mutation("nerfstudio seam: a field's second positional argument dropped", "sp_plugins/nerfstudio/seam.py",
             "return (samples, *args[1:]), kwargs", "return (samples, *args[2:]), kwargs", (NS_EXACT,)),
    Mutation("nerfstudio seam: one draw's heads recomputed", "sp_plugins/nerfstudio/seam.py",
             "if sp.config.num_samples > 1 else outputs", "if sp.config.num_samples > 0 else outputs", (NS_EXACT,)),
    Mutation("sdfstudio seam: first move recorded as |moved + plain| (an unmoved run passes the reach check)",
             "sp_plugins/sdfstudio/seam.py", "(moved - plain).detach()", "(moved + plain).detach()", (SDF_EXACT,)),
    Mutation("sdfstudio seam: queries SP does not move recorded (an evaluation first fails the reach check)",
             "sp_plugins/sdfstudio/seam.py", "if handle is None or handle.sp is None or not handle.sp.active:",
             "if handle is None or handle.sp is None and not handle.sp.active:", (SDF_SEAM,)),
    Mutation("host wiring: alpha0 not scaled by the diagonal", "sp_plugins/adapter/model.py",
             "scene_diagonal=box_diagonal(aabb)", "scene_diagonal=1.0", (NS_EXACT, SDF_EXACT)),
    Mutation("sdfstudio model: folds into the scene box", "sp_plugins/sdfstudio/model.py",
             "return CONTRACTED_BOUNDS", "return aabb.detach().float().cpu()", (SDF_EXACT,)),
    Mutation("sdfstudio model: K > 1 trains one draw", "sp_plugins/sdfstudio/model.py",
             "if k > 1:", "if False:", (SDF_EXACT,)),
    Mutation("point cloud task: field queried plain", "sp_plugins/tasks/pointcloud.py",
             "f = self.sp.blurred(self.field, x).squeeze(-1)", "f = self.field(x).squeeze(-1)", (POINTCLOUD_EXACT,)),
    Mutation("point cloud task: SP box not the frame", "sp_plugins/tasks/pointcloud.py",
             "sp_config = self._setup_sp(bounds=(-1.0, 1.0), dim=3)", "sp_config = self._setup_sp(bounds=(-2.0, 2.0), dim=3)",
             (POINTCLOUD_EXACT,)),
    Mutation("point cloud task: eikonal term added unweighted", "sp_plugins/tasks/pointcloud.py",
             '+ c.w_eikonal * terms["eikonal"]', '+ c.w_eikonal + terms["eikonal"]',
             (("main", ("tests/tasks/test_pointcloud_exact.py::test_the_loss_is_the_weighted_sum_of_the_four_terms",)),)),
    Mutation("point cloud task: lr decay one step short of its end", "sp_plugins/tasks/pointcloud.py",
             "gamma = config.lr_final_ratio ** (1.0 / max(config.steps - 1, 1))",
             "gamma = config.lr_final_ratio ** (1.0 / max(config.steps, 1))",
             (("main", ("tests/tasks/test_pointcloud_exact.py::test_the_learning_rate_decays_exponentially_to_exactly_lr_times_the_final_ratio",)),)),
    Mutation("point cloud task: NaN --grad-clip accepted", "sp_plugins/tasks/pointcloud.py",
             "if not self.grad_clip >= 0:", "if self.grad_clip < 0:",
             (("main", ("tests/tasks/test_pointcloud_exact.py::test_validation_refuses_exactly_the_documented_values_in_one_line",)),)),
    # the host wiring (survivors of the study of nerfstudio/model.py, and sdfstudio/model.py's tests written ahead)
    Mutation("nerfstudio model: SP's schedule advances every other step", "sp_plugins/nerfstudio/model.py",
             "return TrainingCallback([at], func, update_every_num_iters=1)",
             "return TrainingCallback([at], func, update_every_num_iters=2)", (NS_SEAM,)),
    Mutation("nerfstudio model: the divergence watch reads evaluation losses, not training ones", "sp_plugins/nerfstudio/model.py",
             "        if self.training:  # type: ignore[attr-defined]\n            self._sp_watch",
             "        if not self.training:  # type: ignore[attr-defined]\n            self._sp_watch", (NS_MODEL_EXACT,)),
    Mutation("sdfstudio model: SP's schedule advances every other step", "sp_plugins/sdfstudio/model.py",
             "return TrainingCallback([at], func, update_every_num_iters=1)",
             "return TrainingCallback([at], func, update_every_num_iters=2)", (SDF_MODEL_EXACT,)),
    Mutation("image task: field queried plain", "sp_plugins/tasks/image.py",
             "pred = self.sp.blurred(self.rgb, self.positions[idx])", "pred = self.rgb(self.positions[idx])", (IMAGE_EXACT,)),
    Mutation("sdf task: field queried plain", "sp_plugins/tasks/sdf.py",
             "pred = self.sp.blurred(self.field, x).squeeze(-1)", "pred = self.field(x).squeeze(-1)", (SDF_TASK_EXACT,)),
    # -- the core --------------------------------------------------------------------------------
    Mutation("noise kind ignored (preconditioner)", "sp_plugins/core/preconditioner.py",
             "noise=self.config.noise,", 'noise="gaussian",', (CORE, NS_MATRIX)),
    Mutation("noise kind compared by identity", "sp_plugins/core/noise.py",
             'if kind == "gaussian":', 'if kind is "gaussian":', (CORE, NOISE_EXACT)),
    Mutation("noise kind ignored (perturb)", "sp_plugins/core/perturb.py",
             "eps = sample_noise(shape, noise,", 'eps = sample_noise(shape, "gaussian",', (CORE,)),
    Mutation("eval perturbed", "sp_plugins/core/preconditioner.py",
             "return (self.training or _PREVIEW.get() is not None) and self.scheduled", "return self.scheduled", (CORE,)),
    Mutation("schedule never reaches 0", "sp_plugins/core/schedule.py",
             "if step >= T:", "if step >= T + 10**9:", (CORE,)),
    Mutation("end=1.0 ends at total_steps (never 0)", "sp_plugins/core/schedule.py",
             "end_step = min(end_step, total_steps - 1)", "pass", (CORE,)),
    Mutation("resume drops the noise state", "sp_plugins/core/preconditioner.py",
             'saved = {str(kind): value.detach().to("cpu", torch.uint8).clone() for kind, value in state["generators"].items()}',
             "saved = {}", (CORE, RESUME)),
    Mutation("reflect fold -> clamp", "sp_plugins/core/boundary.py",
             "    return reflect(y, lo, hi, origin)",
             "    return torch.where((origin >= lo) & (origin <= hi), torch.maximum(torch.minimum(y, hi), lo), y)",
             (CORE,)),
    Mutation("K-draw originals flat-indexed", "sp_plugins/core/boundary.py",
             "return origin.reshape(-1)[idx % origin.numel()]", "return origin.reshape(-1)[idx.clamp_max(origin.numel() - 1)]",
             (CORE,)),
    Mutation("alpha grid gradient detached (grid)", "sp_plugins/core/alpha_grid.py",
             "alpha = _to_alpha(self.parameterization, sampled.reshape(*batch, 1))",
             "alpha = _to_alpha(self.parameterization, sampled.reshape(*batch, 1)).detach()", (CORE,)),
    Mutation("alpha grid gradient detached (preconditioner)", "sp_plugins/core/preconditioner.py",
             "alpha = self.alpha_grid(x.detach())", "alpha = self.alpha_grid(x.detach()).detach()", (CORE,)),
    Mutation("alpha grid times the schedule (old variant)", "sp_plugins/core/preconditioner.py",
             'self._grid_scale = decay if c.alpha_grid_mode == "scaled" else', "self._grid_scale = decay if True else",
             (CORE,)),
    # the later survivors: what the core's study found no test reading exactly
    Mutation("alpha grid read half a cell off (its cell centres not on the bounds)", "sp_plugins/core/alpha_grid.py",
             'padding_mode="border", align_corners=True)', 'padding_mode="border", align_corners=False)', (ALPHA_GRID_EXACT,)),
    Mutation("unseeded noise: every rank draws the same stream", "sp_plugins/core/preconditioner.py",
             "return (drawn + rank) % (1 << 63)", "return drawn % (1 << 63)", (PRECONDITIONER_EXACT,)),
    Mutation("config.yml: a subscription imports any module before its package is checked", "sp_plugins/adapter/safe_config.py",
             "if not _within(generic, self._allowed.classes):", "if False:", (SAFE_CONFIG_EXACT,)),
    Mutation("half precision rounded back", "sp_plugins/core/perturb.py",
             "x = x.to(compute_dtype(x.dtype))", "pass", (CORE,)),
    # -- the demo --------------------------------------------------------------------------------
    Mutation("demo: SP run off (its config)", "sp_plugins/cli/demo.py",
             'sp = replace(base, sp=SPConfig(alpha0=args.alpha0, schedule="step", end=args.sp_end))', "sp = replace(base)",
             (DEMO_CONFIGS, DEMO_RUN)),
    Mutation("demo: SP run trains the baseline's config", "sp_plugins/cli/demo.py",
             "trainers = {name: cfg.setup(data, device=device) for name, cfg in configs.items()}",
             'trainers = {name: configs["baseline"].setup(data, device=device) for name in configs}',
             (DEMO_CONFIGS, DEMO_RUN)),
]


def copy_checkout(dest: Path) -> None:
    """The tracked files of the checkout, as they are in the working tree."""
    files = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True).stdout.split(b"\0")
    for name in filter(None, (f.decode() for f in files)):
        src = ROOT / name
        if src.is_file():
            (dest / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / name)


def environment(copy: Path) -> Dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("SP_SDFSTUDIO_TESTS", "SP_SDFSTUDIO_MISSING")}
    env["PYTHONPATH"] = os.pathsep.join([str(copy), *filter(None, [os.environ.get("PYTHONPATH")])])
    env.update(OMP_NUM_THREADS="1", OMP_WAIT_POLICY="PASSIVE", PYTHONDONTWRITEBYTECODE="1",
               SP_SLOW_TESTS="1")  # (the opt-in tests too: tests/bench/test_sparse_views_gap.py)
    # the copy is not beside ../shared: the tests and benches look for the shared data here
    shared = ROOT.parent / "shared" / "data"
    if shared.is_dir():
        env.setdefault("SP_SHARED_DATA", str(shared))
    return env


def python_of(kind: str) -> Path:
    return MAIN_PYTHON if kind == "main" else SDF_PYTHON


def check_imports_copy(kind: str, copy: Path, env: Dict[str, str]) -> None:
    found = subprocess.run([str(python_of(kind)), "-c", "import sp_plugins; print(sp_plugins.__file__)"], cwd=copy, env=env,
                           capture_output=True, text=True, timeout=300).stdout.strip()
    if not found.startswith(str(copy)):
        raise SystemExit(f"mutations: the {kind} environment imports sp_plugins from {found or '?'}, not the copy {copy}")


def run_set(test_set: TestSet, copy: Path, env: Dict[str, str]) -> Tuple[int, str]:
    """Exit status and the first failing test (or the output's tail)."""
    kind, args = test_set
    cmd = [str(python_of(kind)), "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider", "-rfE", *args]
    try:
        proc = subprocess.run(cmd, cwd=copy, env=env, capture_output=True, text=True, timeout=TIMEOUT_S)
    except subprocess.TimeoutExpired:
        return 124, f"timeout after {TIMEOUT_S} s"
    failed = [line for line in proc.stdout.splitlines() if re.match(r"(FAILED|ERROR) ", line)]
    what = failed[0] if failed else (proc.stdout + proc.stderr).strip().splitlines()[-1:] or ["no output"]
    return proc.returncode, (what if isinstance(what, str) else what[0])[:220]


def label(test_set: TestSet) -> str:
    kind, args = test_set
    return ("[sdfstudio] " if kind == "sdfstudio" else "") + " ".join(args)


def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", action="append", default=[], help="run only this mutation (by name; repeatable)")
    ap.add_argument("--list", action="store_true", help="list the mutations and their test sets")
    ap.add_argument("--no-baseline", action="store_true", help="skip the unmutated runs of the test sets")
    ap.add_argument("--keep", action="store_true", help="keep the scratch copy")
    args = ap.parse_args(argv)
    chosen = [m for m in MUTATIONS if not args.only or m.name in args.only]
    unknown = set(args.only) - {m.name for m in MUTATIONS}
    if unknown:
        ap.error(f"no mutation named {sorted(unknown)}; --list shows them")
    if args.list:
        for m in MUTATIONS:
            print(f"{m.name}: {m.path}; tests: {' | '.join(label(t) for t in m.tests)}")
        return 0
    scratch = Path(tempfile.mkdtemp(prefix="sp-mutations-"))
    copy = scratch / "checkout"
    copy.mkdir()
    status = 0
    try:
        copy_checkout(copy)
        env = environment(copy)
        for kind in sorted({t[0] for m in chosen for t in m.tests}):
            check_imports_copy(kind, copy, env)
        broken: Dict[TestSet, str] = {}
        if not args.no_baseline:
            for test_set in dict.fromkeys(t for m in chosen for t in m.tests):
                start = time.perf_counter()
                rc, what = run_set(test_set, copy, env)
                print(f"baseline  {label(test_set)}: {'ok' if rc == 0 else 'FAILS: ' + what} ({time.perf_counter() - start:.0f} s)",
                      flush=True)
                if rc != 0:
                    broken[test_set] = what
                    status = 1
        print(f"{'mutation':<46} {'result':<8} {'seconds':>7}  killed by", flush=True)
        for m in chosen:
            target = copy / m.path
            original = target.read_text()
            count = original.count(m.old)
            if count != 1:
                print(f"{m.name:<46} {'STALE':<8} {0:>7}  '{m.old[:60]}' found {count} times in {m.path}", flush=True)
                status = 1
                continue
            target.write_text(original.replace(m.old, m.new))
            start, result, killer = time.perf_counter(), "SURVIVED", ""
            try:
                for test_set in m.tests:
                    if test_set in broken:
                        continue
                    rc, what = run_set(test_set, copy, env)
                    if rc != 0:
                        result = "KILLED" if rc != 124 else "TIMEOUT"
                        killer = f"{what}  [{label(test_set)}]"
                        break
            finally:
                target.write_text(original)
            if result != "KILLED":
                status = 1
            print(f"{m.name:<46} {result:<8} {time.perf_counter() - start:>7.0f}  {killer}", flush=True)
    finally:
        if args.keep:
            print(f"scratch copy kept: {copy}")
        else:
            shutil.rmtree(scratch, ignore_errors=True)
    return status


if __name__ == "__main__":
    raise SystemExit(main())
