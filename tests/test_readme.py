"""The README and the docs are executable: every fenced block of README.md and the docs pages
(in the order of the site's tables of contents) runs here as a user types it, in order, in one working
folder, through ``tests/helpers/readme_runner.py`` (Sybil, with a shell evaluator of ours; why Sybil:
see that module). The blocks of docs/guides/sdfstudio.md run in sdfstudio's environment
(tests/sdfstudio/test_readme_sdfstudio.py). What the runner
may change is declared there (budget flags, placeholders, fixtures, Python preludes); a block that
cannot run here carries ``<!-- readme-runner: skip (reason) -->``.

The fast tests below check the runner itself: it fails on a failing command or a traceback,
honours and requires reasons, lowers only the declared flags and fills ``outputs/...``.
"""

from __future__ import annotations

import os
import re
import time
from pathlib import Path

import pytest

from tests.helpers import forkshim
from tests.helpers import readme_runner as rr


@pytest.fixture(scope="module")
def shim_env(tmp_path_factory):
    """ns-* / sp-train / sp-fit ... as typed, each started once, but forked from one interpreter that
    imported nerfstudio (tests/helpers/forkshim.py): their 8-20 s import each was most of the README
    run's time. One server for this module's tests (its own start imports every shimmed command)."""
    with forkshim.shims(tmp_path_factory.mktemp("shims"), rr.block_env()) as env:
        yield env


@pytest.mark.timeout(1800)  # about 4 minutes on 2 idle cores (the README's commands, lowered); a loaded machine takes longer
def test_every_readme_block_runs_or_carries_a_reason(tmp_path, record_property, shim_env):
    start = time.monotonic()
    runner = rr.Runner(tmp_path, mine=lambda block: block.path != rr.SDFSTUDIO_PAGE, env=shim_env)
    for document in rr.documents():
        runner.run(document)
    text = f"{rr.summary(runner.outcomes)}\nwall time {time.monotonic() - start:.0f} s"
    record_property("readme_runner", text)
    print(text)
    statuses = [o.status for o in runner.outcomes]
    assert all(o.detail for o in runner.outcomes if o.status == "skipped"), text
    assert statuses.count("as written") + statuses.count("lowered") >= 8, text
    assert "elsewhere" in statuses, "the sdfstudio page's blocks were not found: " + text
    check_the_readmes_ns_train_sweep(tmp_path / "runs" / "neus")


def check_the_readmes_ns_train_sweep(out: Path) -> None:
    """What the README's ``sp-sweep study.yaml`` run must show (it replaced tests/sweeps' own ns-train
    sweep, which ran the same path): ``ns-train`` then ``ns-eval`` per trial on a local Ray, a
    baseline and an SP trial of the grid point, each with a PSNR, the grid value and the SP axis in
    the trainer's ``config.yml``."""
    from tests.sweeps.conftest import result_rows

    table = result_rows(out)
    assert len(table) == 2 and sorted(r["sp"] for r in table) == ["SP", "baseline"], table
    for r in table:
        assert r["status"] == "ok", r["error"]
        assert 0 < float(r["psnr"]) < 60 and 0 < float(r["ssim"]) <= 1, r
        (config,) = (out / "trials" / r["trial"]).glob("train/**/config.yml")
        text = config.read_text()
        grid = re.search(r"^  field_grid:\n    optimizer: .*\n(?:      .*\n)*?      lr: (\S+)$", text, flags=re.M)
        assert grid and float(grid[1]) == float(r["lr"]) in (1e-2, 1e-1), r  # the grid value reached the trainer
        assert ("enabled: true" in text) == (r["sp"] == "SP")  # the SP axis reached the trainer
    assert (out / "results.md").is_file()


def _doc(tmp_path: Path, body: str) -> Path:
    path = tmp_path / "DOC.md"
    path.write_text(body)
    (tmp_path / "work").mkdir(exist_ok=True)
    return path


def _run(path: Path):
    return rr.Runner(path.parent / "work", mine=lambda block: True).run(path)


def test_a_failing_command_fails_the_run(tmp_path):
    doc = _doc(tmp_path, "# x\n\n```bash\necho ok\nfalse   # a command that fails\necho never\n```\n")
    with pytest.raises(AssertionError, match=r"DOC.md:3 .*exit status 1"):
        _run(doc)


def test_a_traceback_fails_the_run_even_with_exit_status_0(tmp_path):
    doc = _doc(tmp_path, "```python\nimport traceback\ntry:\n    1 / 0\nexcept ZeroDivisionError:\n"
                         "    traceback.print_exc()\n```\n")
    with pytest.raises(AssertionError, match="printed a traceback"):
        _run(doc)


def test_skip_needs_a_reason_and_a_bare_fence_is_not_a_command(tmp_path):
    doc = _doc(tmp_path, "<!-- readme-runner: skip (needs a GPU) -->\n```bash\nexit 1\n```\n\n```\ntree/\n```\n")
    outcomes = _run(doc)
    assert [(o.status, o.detail) for o in outcomes] == [("skipped", "needs a GPU"), ("not a command", "a ``` block")]
    with pytest.raises(AssertionError, match="marker without a reason"):
        _run(_doc(tmp_path, "<!-- readme-runner: skip -->\n```bash\nexit 1\n```\n"))


def test_outputs_placeholder_is_the_newest_run_of_the_blocks_before(tmp_path):
    doc = _doc(tmp_path, "```bash\nmkdir -p outputs/s/m/old outputs/s/m/new && echo a > outputs/s/m/old/config.yml\n"
                         "sleep 0.05; echo b > outputs/s/m/new/config.yml\n```\n\n"
                         "```bash\ntest \"$(cat outputs/.../m/.../config.yml)\" = b\n```\n")
    assert [o.status for o in _run(doc)] == ["as written", "as written"]


def test_only_the_declared_budget_flags_change():
    line = ("ns-train sp-neus-hashgrid --machine.device-type cpu --max-num-iterations 2000 "
            "--pipeline.model.sp.alpha0 0.013 sdfstudio-data --data my-scene/sdfstudio   # a comment")
    lowered, changes = rr.lower(line)
    assert lowered == ("ns-train sp-neus-hashgrid --machine.device-type cpu --max-num-iterations 2 "
                       "--pipeline.model.sp.alpha0 0.013 --pipeline.datamanager.train-num-rays-per-batch 64 "
                       "sdfstudio-data --data my-scene/sdfstudio # a comment")
    assert sorted(changes) == ["ns-train --max-num-iterations 2", "ns-train --pipeline.datamanager.train-num-rays-per-batch 64"]
    assert rr.lower("sp-train --help   # every method")[0] == "sp-train --help   # every method"
    inner, _ = rr.lower('sp-sweep --command "sp-fit pointcloud $spot --steps 300" --grid lr=1,2 --out runs/pc')
    assert inner == ('sp-sweep --sample 1 --command "sp-fit pointcloud $spot --steps 2 --mesh-resolution 32 '
                     '--n-points 5000 --metric-points 2000" --grid lr=1,2 --out runs/pc')
    declared = {flag for _, flag, _ in rr.BUDGET}
    assert all(re.search(r"(steps|iterations|rays|resolution|points|sample|views)", flag) for flag in declared), declared


def test_readme_chamfer_claims_match_bench_results():
    """The demo's per-mesh Chamfer ratios (docs/getting-started.md) are the raw-Chamfer table's of the point-cloud study."""
    results = (rr.REPO / "docs" / "results" / "pointcloud-sdf.md").read_text()
    table = results[results.index("**Chamfer (raw mesh)**"):results.index("**Chamfer after keeping the largest component**")]
    ratio = {m.group(1): m.group(2) for m in re.finditer(r"^\| (\w+) \|(?: [^|]+ \|){4} \**([\d.]+)\** \|", table, flags=re.M)}
    readme = (rr.REPO / "docs" / "getting-started.md").read_text()
    assert f"on Spot\nSP's raw Chamfer is {ratio['spot']}x" in readme and f"on the bunny {ratio['bunny']}x" in readme
    least = max(ratio, key=lambda mesh: float(ratio[mesh]))  # the largest ratio: the smallest gain
    assert least == "bunny" and "Spot is the mesh where SP's raw Chamfer gain is" not in readme, ratio


def test_the_fork_shims_pass_on_the_exit_status_and_the_output_of_the_command(tmp_path, shim_env):
    """A shimmed command fails as the real one does (the README run relies on it to turn red): its
    exit status and its stderr reach the shell, in the shell's folder."""
    import subprocess

    env = dict(rr.block_env(), **shim_env)
    shims = Path(shim_env["PATH"].split(os.pathsep)[0])
    proc = subprocess.run(["bash", "-c", "command -v sp-train; sp-train nerfacto --machine.device-type cuda"],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert proc.stdout.splitlines()[0] == str(shims / "sp-train"), proc.stdout[:500]
    assert proc.returncode == 2 and proc.stderr.strip().splitlines()[-1].startswith(
        "sp-train: error: --machine.device-type cuda: CUDA is not available"), proc.stderr[-2000:]
    proc = subprocess.run(["bash", "-c", "ns-eval --load-config missing.yml"], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 1 and "missing.yml" in proc.stderr and "Traceback" in proc.stderr, proc.stderr[-2000:]
