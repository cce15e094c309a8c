"""The checks of files and settings a run is given (sp_plugins.adapter.checks), exactly and without a host:
which checkpoint bytes are refused and with which line, which settings of a saved config are unknown or
missing (nested dataclasses, dicts, lists, cycles), the device checks' bounds, the output folder checks.
The mutants each test kills are listed in ``bench/results/mutation_study/kills.json``."""

from __future__ import annotations

import dataclasses
import errno
import os
import zipfile
from typing import List

import pytest
import torch

from sp_plugins.adapter import checks
from sp_plugins.adapter.errors import InputError
from sp_plugins.adapter.hosts import Flags

NS = Flags()
"""nerfstudio's flag names (the defaults of :class:`Flags`)."""


def checkpoint(path, value=1.0):
    torch.save({"w": torch.full((64,), value)}, path)
    return path


def test_a_complete_checkpoint_passes_and_the_flag_is_named_in_every_refusal(tmp_path):
    """A complete checkpoint passes; a missing file or a folder is refused as not found, naming the flag when one is
    given."""
    ok = checkpoint(tmp_path / "step-1.ckpt")
    checks.check_checkpoint_file(ok)
    checks.check_checkpoint_file(ok, "--load-checkpoint")
    with pytest.raises(InputError, match=rf"^--load-checkpoint {tmp_path / 'none.ckpt'}: checkpoint not found$"):
        checks.check_checkpoint_file(tmp_path / "none.ckpt", "--load-checkpoint")
    with pytest.raises(InputError, match=rf"^{tmp_path}: checkpoint not found$"):
        checks.check_checkpoint_file(tmp_path)  # a folder is not a checkpoint file


def test_a_truncated_checkpoint_is_refused_with_its_size(tmp_path):
    """A truncated or empty checkpoint is refused in one line giving the file's size in bytes."""
    path = checkpoint(tmp_path / "cut.ckpt")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match=rf"^{path}: not a complete PyTorch checkpoint \(.*; {len(data) // 2} bytes\): the file is truncated"):
        checks.check_checkpoint_file(path)
    empty = tmp_path / "empty.ckpt"
    empty.write_bytes(b"")
    with pytest.raises(InputError, match=r"; 0 bytes\): the file is truncated or damaged"):
        checks.check_checkpoint_file(empty)


def test_a_checkpoint_damaged_in_place_is_refused_naming_the_member(tmp_path):
    """Bytes flipped inside a stored member: the zip directory is intact, the member's CRC is not (``torch.load``
    would read it)."""
    path = checkpoint(tmp_path / "flip.ckpt", 1.0)
    data = bytearray(path.read_bytes())
    at = bytes(data).find(torch.full((64,), 1.0).numpy().tobytes())
    assert at > 0
    data[at + 10] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(InputError, match=rf"^{path}: damaged PyTorch checkpoint \(member .*/data/0 fails its CRC check\)"):
        checks.check_checkpoint_file(path)


def test_a_zip_that_is_not_a_checkpoint_is_refused(tmp_path):
    """A zip file without a ``data.pkl`` is refused as not a PyTorch checkpoint."""
    path = tmp_path / "notes.zip"
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("notes/readme.txt", "hello")
    with pytest.raises(InputError, match=rf"^{path}: a zip file but not a PyTorch checkpoint \(no data\.pkl\)$"):
        checks.check_checkpoint_file(path)


@dataclasses.dataclass
class Inner:
    lr: float = 1e-3
    steps: int = 10


@dataclasses.dataclass
class Outer:
    inner: Inner = dataclasses.field(default_factory=Inner)
    groups: dict = dataclasses.field(default_factory=dict)
    stack: List[Inner] = dataclasses.field(default_factory=list)
    name: str = "run"

    @property
    def derived(self) -> str:  # a class attribute: not an unknown setting
        return self.name


@dataclasses.dataclass
class Required:
    needed: int


def test_unknown_and_missing_settings_are_found_anywhere_in_the_tree():
    """An attribute no class declares (a newer version's setting), a declared field without a value (an older
    version's config) and without a class default, in nested dataclasses, dict values and list items, each
    named by its dotted path."""
    config = Outer(groups={"fields": Inner()}, stack=[Inner(), Inner()])
    assert checks.settings_problems(config, "pipeline") == ([], [])
    config.inner.warmup = 5
    config.groups["fields"].momentum = 0.9
    config.stack[1].decay = 0.5
    del config.stack[0].lr  # falls back to the class default: not missing
    required = Required(needed=1)
    del required.needed  # no value and no default
    config.groups["other"] = required
    config.__dict__["derived"] = "x"  # shadows a property of the class: known
    unknown, missing = checks.settings_problems(config, "pipeline")
    assert unknown == ["pipeline.inner.warmup", "pipeline.groups.fields.momentum", "pipeline.stack[1].decay"]
    assert missing == ["pipeline.groups.other.needed"]


def test_a_config_that_refers_to_itself_is_walked_once():
    """A config that holds itself (or an object twice) is walked once and has no problems."""
    config = Outer()
    config.groups["self"] = config
    config.stack.append(config.inner)
    assert checks.settings_problems(config, "c") == ([], [])


def test_a_config_of_another_version_is_refused_naming_up_to_four_settings_each(monkeypatch):
    """A clean config passes; one of another version is refused naming at most four unknown settings and four
    missing values, each list ending with ``...`` past four."""
    checks.check_known_settings(Outer(), "pipeline", source="x")  # clean: nothing raised
    config = Outer()
    for i in range(4):
        setattr(config.inner, f"new{i}", i)
    with pytest.raises(InputError, match=r"^--load-config a/config\.yml: written by another version of sp-plugins or its host: "
                                         r"settings this version does not know \(pipeline\.inner\.new0, pipeline\.inner\.new1, "
                                         r"pipeline\.inner\.new2, pipeline\.inner\.new3\); load it with the version"):
        checks.check_known_settings(config, "pipeline", source="--load-config a/config.yml")
    config.inner.new4 = 4
    required = Required(needed=1)
    del required.needed
    config.groups["r"] = required
    with pytest.raises(InputError, match=r"pipeline\.inner\.new3, \.\.\.\) and no value for pipeline\.groups\.r\.needed; load it"):
        checks.check_known_settings(config, "pipeline", source="s")
    many = Outer()
    for n in range(5):
        r = Required(needed=n)
        del r.needed
        many.groups[f"g{n}"] = r
    with pytest.raises(InputError, match=r"another version of sp-plugins or its host: no value for pipeline\.groups\.g0\.needed, "
                                         r"pipeline\.groups\.g1\.needed, pipeline\.groups\.g2\.needed, pipeline\.groups\.g3\.needed, \.\.\.; load"):
        checks.check_known_settings(many, "pipeline", source="s")
    del many.groups["g4"]
    with pytest.raises(InputError, match=r"pipeline\.groups\.g3\.needed; load it"):  # four: all named, no "..."
        checks.check_known_settings(many, "pipeline", source="s")
    monkeypatch.setattr(checks.sys, "argv", ["ns-eval", "--load-config", "runs/x/config.yml"])
    with pytest.raises(InputError, match=r"^--load-config runs/x/config\.yml: written by another version"):
        checks.check_known_settings(config, "pipeline")


@pytest.mark.parametrize("argv, source", [
    (["--load-config", "a.yml"], "--load-config a.yml"),
    (["--x", "1", "--load-config=b.yml"], "--load-config b.yml"),
    (["--load-config=c=d.yml"], "--load-config c=d.yml"),
    (["--load-config"], "the run's config (config.yml)"),
    ([], "the run's config (config.yml)"),
    (["--x", "--load-config", "e.yml"], "--load-config e.yml"),  # at an odd index: i | 1 is i there
    (["--x", "--load-config"], "the run's config (config.yml)"),
    (["--data", "d"], "the run's config (config.yml)"),  # a flag that sorts before --load-config
])
def test_the_config_source_is_the_load_config_flag_as_typed(argv, source):
    """The config's source is ``--load-config`` and its value as typed (``--load-config PATH`` or
    ``--load-config=PATH``), else the run's config.yml."""
    assert checks.config_source(argv) == source


def test_devices_are_checked_against_this_machine(monkeypatch):
    """CUDA asked where none is; more CUDA devices than there are; MPS where there is none; several devices of
    anything but CUDA."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    checks.check_device("cpu", flags=NS)
    with pytest.raises(InputError, match=r"^--machine\.device-type cuda: CUDA is not available on this machine; pass --machine\.device-type cpu$"):
        checks.check_device("cuda", flags=NS)
    with pytest.raises(InputError, match=r"^--machine\.num-devices 2: training on more than one device needs --machine\.device-type cuda"):
        checks.check_device("cpu", 2, flags=NS)
    with pytest.raises(InputError, match=r"^--device cuda: CUDA is not available"):
        checks.check_device("cuda", flags=Flags(device="--device"))
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    checks.check_device("cuda", 2, flags=NS)  # as many as there are
    with pytest.raises(InputError, match=r"^--machine\.num-devices 3: this machine has 2 CUDA device\(s\)$"):
        checks.check_device("cuda", 3, flags=NS)
    monkeypatch.setattr(torch.backends.mps, "is_available", lambda: False)
    with pytest.raises(InputError, match=r"^--machine\.device-type mps: Apple's MPS is not available"):
        checks.check_device("mps", flags=NS)
    monkeypatch.setattr(torch.backends.mps, "is_available", lambda: True)
    checks.check_device("mps", flags=NS)
    with pytest.raises(InputError, match=r"^--machine\.num-devices 2: training on more than one device needs"):
        checks.check_device("mps", 2, flags=NS)


def test_fewer_cuda_devices_than_there_are_and_device_types_named_by_parsed_strings_pass(monkeypatch):
    """One of two CUDA devices is fine; ``cuda`` and ``mps`` as tyro hands them over (equal strings, not the
    literals) are the same devices."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    checks.check_device("cuda", 1, flags=NS)
    checks.check_device("".join(list("cuda")), 2, flags=NS)
    monkeypatch.setattr(torch.backends.mps, "is_available", lambda: False)
    with pytest.raises(InputError, match=r"^--machine\.device-type mps: Apple's MPS is not available"):
        checks.check_device("".join(list("mps")), flags=NS)


def test_the_versions_named_leave_out_a_host_that_is_not_installed(monkeypatch):
    """sdfstudio's environment has no ``nerfstudio`` distribution: the refusal names sp-plugins' version only."""
    import importlib.metadata as metadata

    real = metadata.version

    def version(dist):
        if dist == "nerfstudio":
            raise metadata.PackageNotFoundError(dist)
        return real(dist)

    monkeypatch.setattr(metadata, "version", version)
    assert checks._versions() == f"sp-plugins {real('sp-plugins')}"


def test_a_parsed_cuda_is_checked_as_cuda_and_a_type_it_does_not_know_is_left_to_torch(monkeypatch):
    """``cuda`` as tyro hands it over is refused where there is no CUDA; a device type this check does not know
    (``xpu``, from ``torch.device(...).type`` in the data manager) is left to torch."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(torch.backends.mps, "is_available", lambda: False)
    with pytest.raises(InputError, match=r"^--machine\.device-type cuda: CUDA is not available"):
        checks.check_device("".join(list("cuda")), flags=NS)
    checks.check_device("xpu", flags=NS)


@pytest.mark.parametrize("count", [0, -1])
def test_no_device_at_all_is_refused_in_one_line_and_one_device_passes(count):
    """``--machine.num-devices 0`` used to reach nerfstudio's launcher (``ValueError: world_size cannot be 0``, a
    traceback; ``ns-train`` runs our preflight, and with it this check, before it launches)."""
    with pytest.raises(InputError, match=rf"^--machine\.num-devices {count}: training needs at least one device; "
                                         r"pass --machine\.num-devices 1$"):
        checks.check_device("cpu", count, flags=NS)
    checks.check_device("cpu", 1, flags=NS)


def test_fewer_than_four_unknown_settings_are_all_named_without_an_ellipsis():
    """Fewer than four unknown settings are all named, without ``...``."""
    config = Outer()
    config.inner.extra = 1
    with pytest.raises(InputError) as info:
        checks.check_known_settings(config, "pipeline", source="s")
    assert "settings this version does not know (pipeline.inner.extra); load it with" in str(info.value)


def test_existing_outputs_are_listed_and_a_file_in_place_of_the_folder_refused(tmp_path):
    """The outputs already in the folder are listed (none while it is missing); a file in place of the folder is
    refused."""
    out = tmp_path / "run"
    assert checks.existing_outputs(out, ["mesh.ply", "metrics.json"], "--out") == []  # not there yet
    out.mkdir()
    (out / "metrics.json").write_text("{}")
    assert checks.existing_outputs(out, ["mesh.ply", "metrics.json"], "--out") == ["metrics.json"]
    (tmp_path / "file").write_text("")
    with pytest.raises(ValueError, match=rf"^--out {tmp_path / 'file'}: exists and is not a folder; choose another --out$"):
        checks.existing_outputs(tmp_path / "file", ["x"], "--out")


def test_a_writable_folder_passes_and_leaves_nothing_and_a_file_on_the_way_is_refused(tmp_path):
    """The probe goes in the nearest existing folder above a folder still to be made, and is removed."""
    checks.check_writable_dir(tmp_path / "a" / "b", "--output-dir")
    assert list(tmp_path.iterdir()) == []  # nothing created, the probe removed
    (tmp_path / "f").write_text("")
    with pytest.raises(InputError, match=rf"^--output-dir {tmp_path / 'f'}: exists and is not a folder; choose another --output-dir$"):
        checks.check_writable_dir(tmp_path / "f", "--output-dir")
    with pytest.raises(InputError, match=rf"^--output-dir {tmp_path / 'f' / 'sub'}: {tmp_path / 'f'} is a file, so the folder cannot be created"):
        checks.check_writable_dir(tmp_path / "f" / "sub", "--output-dir")


@pytest.mark.parametrize("code, hint", [(errno.EROFS, "the folder is read-only or not yours"),
                                         (errno.ENOSPC, "the disk is full")])
def test_a_folder_that_cannot_be_written_is_refused_in_one_line(tmp_path, monkeypatch, code, hint):
    """The probe's failure as the file system reports it (as root this machine cannot make a folder
    read-only, so the error is raised where ``mkstemp`` would get it); ENOENT (the folder vanished meanwhile)
    is not a folder problem and propagates."""
    import tempfile

    def fail(*args, **kwargs):
        raise OSError(code, os.strerror(code), str(tmp_path))

    monkeypatch.setattr(tempfile, "mkstemp", fail)
    with pytest.raises(InputError, match=rf"^--output-dir {tmp_path / 'out'}: cannot write \({os.strerror(code)}\); {hint}"):
        checks.check_writable_dir(tmp_path / "out", "--output-dir")
    code = errno.ENOENT
    with pytest.raises(FileNotFoundError):
        checks.check_writable_dir(tmp_path / "out", "--output-dir")
