"""sp-fit --checkpoint-every / --resume: a run killed with SIGKILL after a checkpoint, then resumed,
ends exactly as the uninterrupted run (CPU): parameters, optimiser, loss trajectory, metrics.json
(apart from the timings) and the written mesh / image. Plus the one-line refusals."""

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from trimesh.exchange.ply import export_ply

from sp_plugins.cli.fit import main
from sp_plugins.tasks import checkpoint as ckpt_io
from sp_plugins.tasks.image import ImageFitTrainer, save_image
from sp_plugins.tasks.pointcloud import PointCloudSDFTrainer
from sp_plugins.tasks.sdf import SDFFitTrainer
from tests.helpers.kill_resume import assert_same

ROOT = Path(__file__).resolve().parents[2]
TINY = ["--encoding.levels", "4", "--encoding.log2-table-size", "12", "--encoding.base-resolution", "8",
        "--encoding.max-resolution", "64", "--hidden", "16", "--quiet"]
TINY_SDF = TINY + ["--mesh-resolution", "32", "--refine", "2", "--metric-points", "3000"]
TIMINGS = {"seconds", "seconds_per_step"}  # wall time: differs between any two runs

# The killed run: sp-fit in a subprocess whose checkpoint writer is wrapped. "after:K": once the
# checkpoint of step K is in place the process stops and the test kills it with SIGKILL; "in-replace:K":
# the process SIGKILLs itself inside os.replace of step K's checkpoint (its temporary file is complete
# but not yet renamed: the window the atomic write protects).
KILLABLE = r"""
import os, signal, sys, time
import torch
torch.set_num_threads(int(os.environ["SP_TEST_THREADS"]))
from sp_plugins.tasks import checkpoint as io
mode, at = os.environ["SP_TEST_KILL"].split(":")
at, save = int(at), io.save

def save_then_maybe_die(path, payload):
    step = payload["trainer"]["step"]
    if mode == "in-replace" and step == at:
        io.os.replace = lambda src, dst: os.kill(os.getpid(), signal.SIGKILL)
    result = save(path, payload)
    if mode == "after" and step == at:
        print(f"checkpoint {step} written", flush=True)
        time.sleep(300)  # killed by the test meanwhile
    return result

io.save = save_then_maybe_die
from sp_plugins.cli.fit import main
sys.exit(main(sys.argv[1:]))
"""


def run_killed(args, out: Path, mode: str, at: int) -> None:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p),
               SP_TEST_THREADS=str(torch.get_num_threads()), SP_TEST_KILL=f"{mode}:{at}")
    proc = subprocess.Popen([sys.executable, "-c", KILLABLE, *args, "--out", str(out)], env=env, cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        if mode == "after":
            line = proc.stdout.readline()  # the process holds still once step `at`'s checkpoint is in place
            assert line == f"checkpoint {at} written\n", f"sp-fit ended before its checkpoint: {proc.communicate()[1][-2000:]}"
            assert ckpt_io.checkpoint_path(out).exists()
            os.kill(proc.pid, signal.SIGKILL)
        _, err = proc.communicate(timeout=240)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == -signal.SIGKILL, f"exit status {proc.returncode}: {err[-2000:]}"


def read_checkpoint(out: Path) -> dict:
    return torch.load(ckpt_io.checkpoint_path(out), map_location="cpu", weights_only=True)


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    d = tmp_path_factory.mktemp("in")
    (d / "sphere.ply").write_bytes(export_ply(trimesh.creation.icosphere(2, radius=3.0)))
    img = np.random.default_rng(0).uniform(size=(24, 32, 3)).astype(np.float32)
    save_image(img, d / "in.png")
    return d


STEPS = 12
CASES = {
    # SP (alpha > 0 until step 6) is on across the kill at step 4: the resumed steps draw from the
    # restored noise generator; the pointcloud run also decays its learning rate (a scheduler state)
    "pointcloud": (PointCloudSDFTrainer, lambda d: [
        "pointcloud", str(d / "sphere.ply"), "--steps", str(STEPS), "--seed", "3", "--n-points", "2000",
        "--surface-batch", "64", "--space-batch", "64", "--sp.end", "0.5", "--geometric-init",
        "--lr-final-ratio", "0.5", *TINY_SDF]),
    "image": (ImageFitTrainer, lambda d: [
        "image", str(d / "in.png"), "--steps", str(STEPS), "--batch", "64", "--sp.end", "0.5", *TINY]),
    # the alpha-map run killed in phase 2 (which starts at step 6): frozen map, importance sampling and
    # level masking rebuilt on resume
    "image-phase2": (ImageFitTrainer, lambda d: [
        "image", str(d / "in.png"), "--steps", str(STEPS), "--batch", "64", "--adaptive-alpha",
        "--importance-sampling", "--level-masking", "--level-mask-min-levels", "2", "--sp.schedule", "step",
        "--sp.end", "0.5", *TINY]),
    "sdf": (SDFFitTrainer, lambda d: [
        "sdf", str(d / "sphere.ply"), "--steps", str(STEPS), "--pool", "2000", "--batch", "256",
        "--sp.end", "0.5", *TINY_SDF]),
}


@pytest.fixture(scope="module")
def uninterrupted(inputs, tmp_path_factory):
    """The reference run of each case, made once (its final checkpoint holds the end state)."""
    made = {}

    def get(case):
        if case not in made:
            out = tmp_path_factory.mktemp(f"whole-{case}")
            assert main(CASES[case][1](inputs) + ["--checkpoint-every", "4", "--out", str(out)]) == 0
            made[case] = out
        return made[case]

    return get


def results(out: Path) -> dict:
    files = {p.name: p.read_bytes() for p in sorted(out.iterdir()) if p.suffix in (".ply", ".png") and p.name != "loss.png"}
    metrics = json.loads((out / "metrics.json").read_text())
    return {"metrics": {k: v for k, v in metrics.items() if k not in TIMINGS}, "files": files}


def resume_counting_steps(args, trainer_cls, monkeypatch) -> int:
    """Resume in this process; the number of training steps it ran."""
    ran = []
    step = trainer_cls.step
    monkeypatch.setattr(trainer_cls, "step", lambda self: ran.append(1) or step(self))
    assert main(args + ["--resume"]) == 0
    monkeypatch.undo()
    return len(ran)


@pytest.mark.parametrize("case, mode, at", [
    ("pointcloud", "after", 4),
    ("pointcloud", "in-replace", 8),
    ("image", "after", 4),
    ("image-phase2", "after", 8),
    ("sdf", "after", 4),
])
def test_killed_run_resumes_to_the_uninterrupted_result(case, mode, at, inputs, uninterrupted, tmp_path, monkeypatch):
    trainer_cls, make_args = CASES[case]
    args = make_args(inputs)
    out = tmp_path / "run"
    run_killed(args + ["--checkpoint-every", "4"], out, mode, at)
    saved_at = at if mode == "after" else at - 4  # in-replace: step `at` never became the checkpoint
    assert read_checkpoint(out)["trainer"]["step"] == saved_at
    assert not (out / "metrics.json").exists()
    leftovers = list(out.glob(".checkpoint.pt.tmp-*"))
    assert bool(leftovers) == (mode == "in-replace")  # the complete but unrenamed temporary file

    ran = resume_counting_steps(args + ["--out", str(out)], trainer_cls, monkeypatch)
    assert ran == STEPS - saved_at  # it continued; it did not train again from step 0
    assert not list(out.glob(".checkpoint.pt.tmp-*"))

    whole = uninterrupted(case)
    end, ref = read_checkpoint(out), read_checkpoint(whole)
    for part in ("field", "sp", "optimizer", "generator", "history", "step"):  # the loss trajectory is history
        assert_same(end["trainer"][part], ref["trainer"][part], part)
    assert len(end["trainer"]["history"]["loss"]) == STEPS
    if "scheduler" in ref["trainer"]:
        assert_same(end["trainer"]["scheduler"], ref["trainer"]["scheduler"], "scheduler")
    if case == "image-phase2":
        assert end["trainer"]["phase2_step"] == ref["trainer"]["phase2_step"] == 6
    assert results(out) == results(whole)  # metrics.json (timings aside), mesh.ply / fitted.png / alpha_map.png


def test_resume_without_the_noise_state_would_not_match(inputs, uninterrupted, tmp_path, monkeypatch):
    """The comparison above can fail: the same resume with the SP generators' saved states emptied
    from the checkpoint (the noise restarts from its seed) ends elsewhere."""
    args = CASES["pointcloud"][1](inputs)
    out = tmp_path / "run"
    whole = uninterrupted("pointcloud")

    class Stop(Exception):
        pass

    save = ckpt_io.save

    def save_then_stop(path, payload):  # in this process: a stop right after the step-4 checkpoint
        save(path, payload)
        raise Stop

    monkeypatch.setattr(ckpt_io, "save", save_then_stop)
    with pytest.raises(Stop):
        main(args + ["--checkpoint-every", "4", "--out", str(out)])
    monkeypatch.undo()
    state = read_checkpoint(out)
    assert state["trainer"]["step"] == 4
    state["trainer"]["sp"]["_extra_state"]["generators"] = {}
    ckpt_io.save(ckpt_io.checkpoint_path(out), state)
    assert main(args + ["--out", str(out), "--resume"]) == 0
    end, ref = read_checkpoint(out)["trainer"], read_checkpoint(whole)["trainer"]
    assert not torch.equal(end["field"]["mlp.0.weight"], ref["field"]["mlp.0.weight"])
    assert end["history"]["loss"][:4] == ref["history"]["loss"][:4] and end["history"]["loss"][4] != ref["history"]["loss"][4]


@pytest.fixture(scope="module")
def checkpointed(inputs, tmp_path_factory):
    """A finished 3-step pointcloud run with its checkpoint."""
    out = tmp_path_factory.mktemp("ck") / "run"
    args = ["pointcloud", str(inputs / "sphere.ply"), "--steps", "3", "--n-points", "1000", "--surface-batch", "32",
            "--space-batch", "32", "--geometric-init", *TINY_SDF]
    assert main(args + ["--out", str(out), "--checkpoint-every", "2"]) == 0
    return args, out


def refused(argv, capsys, message):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("sp-fit: error: ") and err.count("\n") == 1 and "Traceback" not in err, err
    assert message in err, err
    return err


def test_resume_refusals_are_one_line_and_write_nothing(checkpointed, inputs, tmp_path, capsys):
    args, out = checkpointed
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    refused(args + ["--out", str(tmp_path / "none"), "--resume"], capsys, "--resume: no checkpoint in")
    assert not (tmp_path / "none").exists()
    err = refused(args + ["--out", str(out), "--resume", "--lr", "0.002"], capsys, "--lr is 0.002 here but 0.001 in the checkpoint")
    assert "--overwrite" in err
    refused(args + ["--out", str(out), "--resume", "--no-sp"], capsys, "--sp.enabled (or --no-sp) is False here but True")
    refused(args + ["--out", str(out), "--resume", "--steps", "5", "--encoding.log2-table-size", "11"], capsys,
            "--steps is 5 here but 3 in the checkpoint; --encoding.log2-table-size is 11 here but 12")
    refused(args + ["--out", str(out), "--resume", "--sp.num-samples", "2"], capsys, "--sp.num-samples is 2 here but 1")
    refused(args + ["--out", str(out), "--resume", "--estimate-normals"], capsys, "--estimate-normals is True here")
    refused(args + ["--out", str(out)], capsys, "holds the checkpoint of an earlier run (checkpoint.pt); pass --resume")
    refused(args + ["--out", str(out), "--checkpoint-every", "-1"], capsys, "--checkpoint-every -1: give a number of steps")
    refused(["sdf", args[1], "--out", str(out), "--resume", "--quiet"], capsys, "is a checkpoint of sp-fit pointcloud, not sp-fit sdf")
    other = tmp_path / "other.ply"  # another input file at the same flags
    other.write_bytes(export_ply(trimesh.creation.icosphere(2, radius=2.0)))
    refused([args[0], str(other), *args[2:], "--out", str(out), "--resume"], capsys, "INPUT is not the file the checkpoint was trained on")
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before  # nothing written or removed

    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "checkpoint.pt").write_bytes(b"not a checkpoint")
    refused(args + ["--out", str(broken), "--resume"], capsys, "cannot be read as an sp-fit checkpoint")
    torch.save({"something": 1}, broken / "checkpoint.pt")
    refused(args + ["--out", str(broken), "--resume"], capsys, "is not an sp-fit checkpoint")


def test_resume_of_a_finished_run_only_redoes_the_outputs_and_overwrite_drops_the_checkpoint(checkpointed, tmp_path, capsys):
    args, out = checkpointed
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    metrics = json.loads((copy / "metrics.json").read_text())
    (copy / "metrics.json").unlink()  # killed while meshing: no results yet
    assert main(args + ["--out", str(copy), "--resume"]) == 0
    again = json.loads((copy / "metrics.json").read_text())
    assert {k: v for k, v in again.items() if k not in TIMINGS} == {k: v for k, v in metrics.items() if k not in TIMINGS}
    # a new run over it with --overwrite and no --checkpoint-every leaves no stale checkpoint to resume
    assert main(args + ["--out", str(copy), "--overwrite"]) == 0
    assert not (copy / "checkpoint.pt").exists()
    capsys.readouterr()
    refused(args + ["--out", str(copy), "--resume"], capsys, "--resume: no checkpoint in")
