"""The fitting tasks' checkpoint file (sp_plugins.tasks.checkpoint), exactly: where it is, what a save
writes (the payload, its format and version) and what an interrupted save leaves (nothing), which stale
files are cleaned, each refusal of a load in its one line (missing, unreadable, a pickled global, not
ours, another version, another task), the data digest, and the settings comparison a resume makes.
The mutants each test kills are listed in ``bench/results/mutation_study/kills.json``."""

from __future__ import annotations

import hashlib
import os

import pytest
import torch

from sp_plugins.tasks import checkpoint as ckpt

LONG = type("Setting" + "x" * 200, (), {})  # a class whose name alone is longer than a refusal's detail
globals()[LONG.__name__] = LONG  # where pickle looks it up


def test_the_checkpoint_is_checkpoint_pt_in_the_output_folder(tmp_path):
    """The checkpoint is ``checkpoint.pt`` in the output folder, given as a path or a string."""
    assert ckpt.checkpoint_path(tmp_path) == tmp_path / "checkpoint.pt"
    assert ckpt.checkpoint_path(str(tmp_path)) == tmp_path / "checkpoint.pt"


def test_a_save_writes_the_payload_with_format_and_version_1_and_leaves_no_temporary(tmp_path):
    """The file holds the payload plus ``format`` / ``version`` 1, replaces an earlier one, and no
    temporary file is left; a load of it for its task gives it back."""
    path = ckpt.checkpoint_path(tmp_path)
    path.write_bytes(b"an earlier checkpoint")
    assert ckpt.save(path, {"task": "sdf", "step": 3, "w": torch.arange(3.0)}) == path
    raw = torch.load(path, weights_only=True)
    assert raw.keys() == {"task", "step", "w", "format", "version"}
    assert (raw["format"], raw["version"], raw["step"]) == ("sp-fit-checkpoint", 1, 3) and torch.equal(raw["w"], torch.arange(3.0))
    assert os.listdir(tmp_path) == ["checkpoint.pt"]
    assert ckpt.load(path, "sdf")["step"] == 3


class Interrupt:
    """Pickling it is a Ctrl-C in the middle of the write."""

    def __reduce__(self):
        raise KeyboardInterrupt


def test_an_interrupted_save_removes_its_temporary_and_keeps_the_earlier_checkpoint(tmp_path):
    """A save stopped by Ctrl-C (a ``BaseException``, not an ``Exception``) mid-write deletes its temporary
    file and re-raises; the previous checkpoint is untouched. A save into a folder that is not there raises
    the write's own error (no second one from the clean-up)."""
    path = ckpt.checkpoint_path(tmp_path)
    ckpt.save(path, {"task": "image", "step": 1})
    before = path.read_bytes()
    with pytest.raises(KeyboardInterrupt):
        ckpt.save(path, {"task": "image", "step": 2, "x": Interrupt()})
    assert os.listdir(tmp_path) == ["checkpoint.pt"] and path.read_bytes() == before
    with pytest.raises(FileNotFoundError) as e:
        ckpt.save(tmp_path / "missing" / "checkpoint.pt", {"task": "image"})
    assert e.value.__context__ is None and e.value.filename == str(tmp_path / "missing" / f".checkpoint.pt.tmp-{os.getpid()}")


def test_remove_stale_deletes_the_temporaries_and_the_checkpoint_only_when_asked(tmp_path):
    """Every ``.checkpoint.pt.tmp-*`` goes (a killed writer's); the checkpoint only with
    ``checkpoint_too``, and asking for it when there is none is fine; other files stay."""
    for name in (".checkpoint.pt.tmp-12", ".checkpoint.pt.tmp-345", "checkpoint.pt", "mesh.ply", "checkpoint.pt.tmp-1"):
        (tmp_path / name).write_text(name)
    ckpt.remove_stale(tmp_path, False)
    assert sorted(os.listdir(tmp_path)) == ["checkpoint.pt", "checkpoint.pt.tmp-1", "mesh.ply"]
    ckpt.remove_stale(str(tmp_path), True)
    assert sorted(os.listdir(tmp_path)) == ["checkpoint.pt.tmp-1", "mesh.ply"]
    ckpt.remove_stale(tmp_path, True)  # none there: no error
    assert sorted(os.listdir(tmp_path)) == ["checkpoint.pt.tmp-1", "mesh.ply"]


def refused(path, task="sdf") -> str:
    with pytest.raises(ValueError) as e:
        ckpt.load(path, task)
    return str(e.value)


def test_a_missing_checkpoint_is_one_line(tmp_path):
    """``--resume`` without a checkpoint is refused in one line saying how a run writes one."""
    assert refused(tmp_path / "checkpoint.pt") == (f"--resume: no checkpoint in {tmp_path} (checkpoint.pt is missing); "
                                                   "a run writes one with --checkpoint-every N")


def test_a_damaged_file_is_one_line_with_torch_s_reason(tmp_path):
    """Bytes that are no pickle: the weights-only unpickler's reason (the first byte, ``n`` = 110, is no
    opcode it allows); a checkpoint cut in half: torch's first line, cut at 200 characters."""
    path = tmp_path / "checkpoint.pt"
    path.write_bytes(b"not a checkpoint at all")
    assert refused(path) == f"--resume: {path} cannot be read as an sp-fit checkpoint (weights-only unpickling: Unsupported operand 110)"
    ckpt.save(path, {"task": "sdf", "w": torch.zeros(100)})
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(RuntimeError) as raw:
        torch.load(path, map_location="cpu", weights_only=True)
    first = str(raw.value).strip().splitlines()[0]
    assert len(first) > 200  # torch's first line is long: cut to 197 characters and "..."
    assert refused(path) == f"--resume: {path} cannot be read as an sp-fit checkpoint ({first[:197]}...)"


def test_a_pickled_global_is_refused_unrun_and_the_detail_is_cut_at_200(tmp_path):
    """A checkpoint (ours in every other way) holding an instance of a class is not unpickled: the line
    names the class, cut to 200 characters of detail."""
    path = tmp_path / "checkpoint.pt"
    torch.save({"format": "sp-fit-checkpoint", "version": 1, "task": "sdf", "x": LONG()}, path)
    detail = f"it holds a pickled {__name__}.{LONG.__name__}, which weights-only loading refuses; nothing in it was run"
    assert len(detail) > 200
    assert refused(path) == f"--resume: {path} cannot be read as an sp-fit checkpoint ({detail[:200]})"


@pytest.mark.parametrize("payload", [[1, 2], {"version": 1, "task": "sdf"}, {"format": "sp-fit-checkpoint!", "version": 1, "task": "sdf"}])
def test_something_else_saved_with_torch_is_not_ours(tmp_path, payload):
    """A list, a dict without our format, another format."""
    path = tmp_path / "checkpoint.pt"
    torch.save(payload, path)
    assert refused(path) == f"--resume: {path} is not an sp-fit checkpoint"


@pytest.mark.parametrize("version", [0, 2, None])
def test_another_version_is_refused_naming_both(tmp_path, version):
    """Versions 0, 2 and none: refused with the file's and ours."""
    path = tmp_path / "checkpoint.pt"
    torch.save({"format": "sp-fit-checkpoint", "version": version, "task": "sdf"}, path)
    assert refused(path) == (f"--resume: {path} was written by another version of sp-fit (format {version}, this one reads 1); "
                             "start anew with --overwrite")


def test_a_checkpoint_of_another_task_is_refused_and_its_own_is_loaded(tmp_path):
    """A checkpoint of another task is refused naming both tasks; the task's own loads (its name built at run time)."""
    path = ckpt.save(tmp_path / "checkpoint.pt", {"task": "image", "step": 5})
    assert refused(path, "pointcloud") == f"--resume: {path} is a checkpoint of sp-fit image, not sp-fit pointcloud"
    assert refused(path, "dft") == f"--resume: {path} is a checkpoint of sp-fit image, not sp-fit dft"  # either order
    task = "".join(["ima", "ge"])  # built at run time: equal, not the same object
    assert ckpt.load(path, task) == {"task": "image", "step": 5, "format": "sp-fit-checkpoint", "version": 1}


def test_file_digest_is_the_sha256_of_all_the_bytes(tmp_path):
    """Over 1 MiB (more than one block), a small file, an empty one, and None."""
    data = bytes(range(256)) * 4500
    for name, content in (("big", data), ("small", b"abc"), ("empty", b"")):
        (tmp_path / name).write_bytes(content)
        assert ckpt.file_digest(tmp_path / name) == hashlib.sha256(content).hexdigest()
    assert ckpt.file_digest(None) is None


def test_flatten_names_nested_settings_with_dots_and_tuples_become_lists():
    """``flatten`` names nested settings with dots, in order, and turns tuples into lists."""
    flat = ckpt.flatten({"steps": 3, "hidden": (64, 64), "sp": {"alpha0": 0.5, "grid": {"on": True}}, "l": [1]})
    assert flat == {"steps": 3, "hidden": [64, 64], "sp.alpha0": 0.5, "sp.grid.on": True, "l": [1]}
    assert type(flat["hidden"]) is list and list(flat) == ["steps", "hidden", "sp.alpha0", "sp.grid.on", "l"]
    assert ckpt.flatten({}) == {}


def test_differences_are_name_current_saved_in_current_s_order_then_the_saved_only():
    """Equal values (also equal floats that are different objects) are no difference; a setting only one
    side has is None on the other."""
    saved = {"steps": 100, "lr": float("0.001"), "sp": {"alpha0": 0.5, "end": 0.2}, "old": 1}
    current = {"seed": 0, "sp": {"end": 0.2, "alpha0": 0.25}, "lr": float("1e-3"), "steps": 200}
    assert ckpt.differences(saved, current) == [("seed", 0, None), ("sp.alpha0", 0.25, 0.5), ("steps", 200, 100), ("old", None, 1)]
    assert ckpt.differences(saved, saved) == []
