"""The one-line reports of bad input (sp_plugins.adapter.errors), exactly and in-process: ``first_line``'s
type-name fallback and its truncation at ``limit`` (a line of ``limit`` characters kept, ``limit + 1`` cut to
``limit``), ``write_failure``'s place, reason and each errno class's hint, ``load_failure_reason``'s
weights-only reason (torch's boilerplate dropped, the ``WeightsUnpickler error:`` marker split once) and its
edge, ``describe_failure`` on real ``torch.load`` / ``torch.save`` failures (not found, a refused global, a
damaged file, a partial checkpoint removed, an explicit traceback), the write errnos, ``wandb``, and which
exceptions keep Python's report (None); ``is_network_error``, ``provider`` and ``build_failure``.
The mutants each test kills are listed in ``bench/results/mutation_study/kills.json``."""

from __future__ import annotations

import errno
import io
import os
import socket
import urllib.error
from importlib.metadata import packages_distributions, version
from pathlib import Path

import pytest
import torch

from sp_plugins.adapter import errors
from sp_plugins.adapter.errors import InputError

DISK_FULL = "the disk is full (or a quota or file-size limit is reached): free space or write elsewhere"
READ_ONLY = "the folder is read-only or not yours: choose a writable output folder"
ELSEWHERE = "choose another output folder"


def fresh(word: str) -> str:
    """An equal string that is not the interned constant (``==`` -> ``is`` tells them apart)."""
    return "".join(list(word))


def cut(text: str, limit: int) -> str:
    """The rule: a line longer than ``limit`` keeps ``limit - 3`` characters and ends with ``...``."""
    return text[: limit - 3] + "..."


# -- first_line ----------------------------------------------------------------------------------
def test_first_line_keeps_the_first_stripped_line_of_a_message():
    """``first_line`` is the message's first line, stripped, without the exception's type name."""
    assert errors.first_line(ValueError("  first\nsecond\nthird  ")) == "first"
    assert errors.first_line(RuntimeError("only")) == "only"
    assert errors.first_line(OSError(errno.EACCES, "Permission denied", "/x")) == "[Errno 13] Permission denied: '/x'"


def test_first_line_names_the_type_of_an_empty_message_and_of_a_key_error():
    """A ``KeyError``'s str is the repr of its key: the type's name goes first; an empty (or blank) message
    is the type's name alone."""
    assert errors.first_line(KeyError("lr")) == "KeyError: 'lr'"
    assert errors.first_line(KeyError()) == "KeyError"
    assert errors.first_line(ValueError()) == "ValueError"
    assert errors.first_line(ValueError("   \n  ")) == "ValueError"
    assert errors.first_line(InputError("")) == "InputError"


@pytest.mark.parametrize("limit", [200, 10, 4])
def test_first_line_truncates_only_past_its_limit(limit):
    """A line of exactly ``limit`` characters is kept; ``limit + 1`` is cut to ``limit`` ending in ``...``
    (the default limit is 200)."""
    at = "a" * limit
    over = "b" * (limit + 1)
    call = (lambda e: errors.first_line(e)) if limit == 200 else (lambda e: errors.first_line(e, limit))
    assert call(ValueError(at)) == at
    assert call(ValueError(over)) == cut(over, limit)
    assert len(call(ValueError(over))) == limit and call(ValueError(over)).endswith("...")
    assert call(ValueError("c" * (limit - 1))) == "c" * (limit - 1)
    assert call(ValueError("d" * (limit + 50) + "\nmore")) == cut("d" * (limit + 50), limit)


# -- write_failure ---------------------------------------------------------------------------------
@pytest.mark.parametrize("code,hint", [(errno.ENOSPC, DISK_FULL), (errno.EDQUOT, DISK_FULL), (errno.EFBIG, DISK_FULL),
                                       (errno.EACCES, READ_ONLY), (errno.EPERM, READ_ONLY), (errno.EROFS, READ_ONLY),
                                       (errno.ENOENT, ELSEWHERE), (errno.EISDIR, ELSEWHERE)])
def test_write_failure_gives_each_errno_class_its_hint(code, hint):
    """A failed write gives the hint of its errno's class: disk full, not writable (permission, read-only), or any
    other."""
    exc = OSError(code, os.strerror(code), "/out/file.txt")
    assert errors.write_failure(exc) == f"/out/file.txt: cannot write ({os.strerror(code)}); {hint}"


def test_write_failure_without_an_errno_asks_for_another_folder():
    """An ``OSError`` with no errno (``errno`` None) and no strerror: the reason is its first line."""
    exc = OSError("the writer gave up\nsecond line")
    assert errors.write_failure(exc) == f"the output: cannot write (the writer gave up); {ELSEWHERE}"
    assert errors.write_failure(exc, name="a.png") == f"the output: cannot write (a.png: the writer gave up); {ELSEWHERE}"


def test_write_failure_names_the_place_given_else_the_file_else_the_output():
    """A failed write names the place given, else the exception's file, else "the output"."""
    with_file = OSError(errno.EROFS, "Read-only file system", "/ro/renders/a.png")
    no_file = OSError(errno.EROFS, "Read-only file system")
    assert errors.write_failure(with_file, what="--output-dir /ro") == \
        f"--output-dir /ro: cannot write (Read-only file system); {READ_ONLY}"
    assert errors.write_failure(with_file) == f"/ro/renders/a.png: cannot write (Read-only file system); {READ_ONLY}"
    assert errors.write_failure(no_file) == f"the output: cannot write (Read-only file system); {READ_ONLY}"
    assert errors.write_failure(no_file, what="--output-dir /ro") == \
        f"--output-dir /ro: cannot write (Read-only file system); {READ_ONLY}"


def test_write_failure_puts_the_file_being_written_before_the_reason():
    """A failed write puts the name of the file being written before the reason, when one is given."""
    exc = OSError(errno.ENOSPC, "No space left on device", "/data/out")
    assert errors.write_failure(exc, what="/data/out", name="step-100.ckpt") == \
        f"/data/out: cannot write (step-100.ckpt: No space left on device); {DISK_FULL}"
    assert errors.write_failure(exc, name="") == f"/data/out: cannot write (No space left on device); {DISK_FULL}"


def test_write_errnos_are_exactly_the_six_place_errnos():
    assert errors.WRITE_ERRNOS == {errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOSPC, errno.EDQUOT, errno.EFBIG}


# -- _path_of, refused_global ----------------------------------------------------------------------
def test_path_of_a_handle(tmp_path):
    """A str or path is itself (a str); a file object its ``name`` when that is a str; else None."""
    assert errors._path_of("a/b.ckpt") == "a/b.ckpt"
    assert errors._path_of(Path("a") / "b.ckpt") == os.path.join("a", "b.ckpt")
    assert type(errors._path_of(Path("a"))) is str
    with open(tmp_path / "f.bin", "wb") as handle:
        assert errors._path_of(handle) == str(tmp_path / "f.bin")
    assert errors._path_of(io.BytesIO(b"")) is None
    with os.fdopen(os.open(tmp_path / "f.bin", os.O_RDONLY), "rb") as by_fd:  # its name is the descriptor, an int
        assert errors._path_of(by_fd) is None
    assert errors._path_of(None) is None


@pytest.mark.parametrize("message,name", [
    ("Unsupported global: GLOBAL posix.system was not an allowed global by default.", "posix.system"),
    ("unsupported GLOBAL builtins.print", "builtins.print"),
    ("x\nWeightsUnpickler error: Unsupported global: GLOBAL torch.nn.modules.linear.Linear was not", "torch.nn.modules.linear.Linear"),
    ("Unsupported operand 153", None),
    ("GLOBAL posix.system", None),
])
def test_refused_global_reads_the_name_torch_refused(message, name):
    assert errors.refused_global(RuntimeError(message)) == name


# -- load_failure_reason ---------------------------------------------------------------------------
PREFIX = "weights-only unpickling: "


def weights_only(*reasons: str) -> RuntimeError:
    """A weights-only refusal laid out as torch writes it: its boilerplate lines around ``reasons``."""
    return RuntimeError("Weights only load failed. This file can still be loaded, to do so you have two options. \n"
                        "\t(1) In PyTorch 2.6, we changed the default value of `weights_only`.\n"
                        "\t(2) Alternatively, to load with `weights_only=True` please check the recommended steps.\n"
                        + "".join(f"\t{r}\n" for r in reasons) +
                        "\nCheck the documentation of torch.load to learn more.\n"
                        "Please file an issue with the following so that we can make `weights_only=True` compatible.\n"
                        "Re-running `torch.load` with `weights_only` set to `False` will likely succeed.\n")


def test_load_failure_reason_gives_torchs_reason_without_its_boilerplate():
    """A refused weights-only load gives torch's reason after its marker, without torch's boilerplate lines."""
    assert errors.load_failure_reason(weights_only("WeightsUnpickler error: Unsupported operand 153")) == \
        PREFIX + "Unsupported operand 153"
    assert errors.load_failure_reason(weights_only("WeightsUnpickler error:   Unsupported operand 7  ", "a detail")) == \
        PREFIX + "Unsupported operand 7; a detail"
    assert errors.load_failure_reason(weights_only("no marker here")) == PREFIX + "no marker here"


def test_load_failure_reason_splits_at_the_first_marker_only():
    """The reason is the text after the first marker, a later marker kept in it."""
    exc = weights_only("WeightsUnpickler error: outer WeightsUnpickler error: inner")
    assert errors.load_failure_reason(exc) == PREFIX + "outer WeightsUnpickler error: inner"


def test_load_failure_reason_of_boilerplate_only_is_refused():
    """A reason of boilerplate only (or a bare marker) reads "refused"; a later non-empty reason is given."""
    assert errors.load_failure_reason(weights_only()) == PREFIX + "refused"
    assert errors.load_failure_reason(weights_only("WeightsUnpickler error:")) == PREFIX + "refused"
    assert errors.load_failure_reason(weights_only("WeightsUnpickler error:", "WeightsUnpickler error: x")) == PREFIX + "x"


@pytest.mark.parametrize("limit", [120, 40])
def test_load_failure_reason_truncates_only_past_its_limit(limit):
    """The whole reason, prefix included, is at most ``limit`` (default 120) characters."""
    call = (lambda e: errors.load_failure_reason(e)) if limit == 120 else (lambda e: errors.load_failure_reason(e, limit))
    at = "a" * (limit - len(PREFIX))
    over = "b" * (limit - len(PREFIX) + 1)
    assert call(weights_only(f"WeightsUnpickler error: {at}")) == PREFIX + at
    assert call(weights_only(f"WeightsUnpickler error: {over}")) == cut(PREFIX + over, limit)
    assert len(call(weights_only(f"WeightsUnpickler error: {over}"))) == limit


@pytest.mark.parametrize("limit", [120, 30])
def test_load_failure_reason_of_another_failure_is_its_first_line_at_the_same_limit(limit):
    """Not a weights-only refusal: ``first_line(exc, limit)``."""
    call = (lambda e: errors.load_failure_reason(e)) if limit == 120 else (lambda e: errors.load_failure_reason(e, limit))
    assert call(RuntimeError("invalid load key, 'j'.\nmore")) == "invalid load key, 'j'."
    assert call(RuntimeError("z" * limit)) == "z" * limit
    assert call(RuntimeError("z" * (limit + 1))) == cut("z" * (limit + 1), limit)
    assert call(KeyError()) == "KeyError"


# -- describe_failure: torch.load ------------------------------------------------------------------
UNREADABLE = ("cannot be read as a PyTorch checkpoint ({}); the file is truncated or damaged (an interrupted copy or "
              "save?) or is not a checkpoint: copy it again, or load another step")


def caught(call, *args, **kwargs) -> BaseException:
    try:
        call(*args, **kwargs)
    except BaseException as exc:  # noqa: BLE001
        return exc
    raise AssertionError("no exception")


def test_a_missing_checkpoint_is_not_found(tmp_path):
    """A checkpoint ``torch.load`` cannot find is "checkpoint not found", from a path or a string."""
    path = tmp_path / "none.ckpt"
    exc = caught(torch.load, path)
    assert errors.describe_failure(exc) == f"{path}: checkpoint not found"
    exc = caught(torch.load, str(path), weights_only=True)
    assert errors.describe_failure(exc) == f"{path}: checkpoint not found"


class Unreadable(io.RawIOBase):
    """A checkpoint handle whose reads fail with ``code`` (a disk error, a permission lost mid-read)."""

    def __init__(self, code, name=None):
        self.code, self.name_ = code, name

    def __getattr__(self, attr):
        if attr == "name" and self.name_ is not None:
            return self.name_
        raise AttributeError(attr)

    def readable(self):
        return True

    def seekable(self):
        return True

    def tell(self):
        return 0

    def seek(self, *args):
        return 0

    def read(self, *args):
        raise OSError(self.code, os.strerror(self.code))

    readinto = read


@pytest.mark.parametrize("code", [errno.EPERM, errno.EIO, errno.EISDIR])
def test_another_oserror_inside_torch_load_is_not_called_not_found(code):
    """An ``OSError`` of an errno below and above ``ENOENT`` (2) raised inside ``torch.load``: the file
    cannot be read, it is not missing."""
    exc = caught(torch.load, Unreadable(code, name="/ckpts/step-9.ckpt"))
    assert isinstance(exc, OSError) and exc.errno == code
    assert errors.describe_failure(exc) == "/ckpts/step-9.ckpt: " + UNREADABLE.format(errors.load_failure_reason(exc))


def test_a_damaged_checkpoint_is_named_with_torchs_reason(tmp_path):
    """A damaged checkpoint is named (by path or by its file object's name) with torch's reason."""
    path = tmp_path / "junk.ckpt"
    path.write_bytes(b"junk, not a checkpoint")
    exc = caught(torch.load, path)
    assert errors.describe_failure(exc) == f"{path}: " + UNREADABLE.format(errors.load_failure_reason(exc))
    with open(path, "rb") as handle:  # a file object: its name
        exc = caught(torch.load, handle)
    assert errors.describe_failure(exc) == f"{path}: " + UNREADABLE.format(errors.load_failure_reason(exc))


def test_a_checkpoint_read_from_a_nameless_handle_is_the_checkpoint():
    """A damaged checkpoint read from a nameless handle is called "the checkpoint"."""
    exc = caught(torch.load, io.BytesIO(b"junk, not a checkpoint"))
    assert errors.describe_failure(exc) == "the checkpoint: " + UNREADABLE.format(errors.load_failure_reason(exc))


def test_a_refused_global_is_named_and_nothing_was_run(tmp_path):
    """A checkpoint that pickles ``os.system``, loaded weights-only: torch refuses it."""
    path = tmp_path / "evil.ckpt"
    torch.save({"call": os.system}, path)
    exc = caught(torch.load, path, weights_only=True)
    name = errors.refused_global(exc)
    assert name == f"{os.system.__module__}.system"
    assert errors.describe_failure(exc) == (
        f"{path}: holds a pickled {name}, which torch's weights-only loading refuses (nothing in the file was run); it "
        "was written by another version (e.g. nerfstudio's schedulers stored numpy learning rates) or not by a training "
        "run: retrain with this version, and load checkpoints only from sources you trust")


def test_an_explicit_traceback_is_read_instead_of_the_exceptions_own(tmp_path):
    """The hook passes the traceback it was given; ``exc.__traceback__`` may be gone."""
    path = tmp_path / "junk.ckpt"
    path.write_bytes(b"junk")
    exc = caught(torch.load, path)
    tb = exc.__traceback__
    exc.with_traceback(None)
    assert errors.describe_failure(exc) is None
    assert errors.describe_failure(exc, tb) == f"{path}: " + UNREADABLE.format(errors.load_failure_reason(exc))
    exc.with_traceback(tb)
    assert errors.describe_failure(exc) == f"{path}: " + UNREADABLE.format(errors.load_failure_reason(exc))


def load(path):
    """A function named ``load`` outside torch: not ``torch.load``."""
    raise ValueError(f"cannot parse {path}")


def save(path):
    """A function named ``save`` outside torch: not ``torch.save``."""
    raise RuntimeError(f"cannot write {path}")


def test_a_load_or_save_outside_torch_is_not_torchs(tmp_path):
    """A failure in a function named ``load`` or ``save`` outside torch is not described as torch's."""
    for fn in (load, save):
        exc = caught(fn, tmp_path / "x")
        assert errors.describe_failure(exc) is None


# -- describe_failure: torch.save ------------------------------------------------------------------
WRITE_FAILED = ("writing the checkpoint failed ({}); the disk is probably full or the folder read-only (the partial "
                "file was removed): free space or choose another output folder")
KEPT = WRITE_FAILED.replace(" (the partial file was removed)", "")
"""Nothing was removed (a handle, a folder, a file that cannot be removed): the line does not say it was."""


class Raises:
    """Pickling it raises ``exc`` (inside ``torch.save``, after the file was opened: a partial file)."""

    def __init__(self, exc):
        self.exc = exc

    def __reduce_ex__(self, protocol):
        raise self.exc


def test_a_failed_save_removes_its_partial_file_and_gives_the_strerror(tmp_path):
    """A save that fails while writing removes its partial file and gives the OS's reason."""
    path = tmp_path / "step-5.ckpt"
    exc = caught(torch.save, {"w": torch.zeros(3), "x": Raises(OSError(errno.ENOSPC, "No space left on device"))}, path)
    assert path.is_file()
    assert errors.describe_failure(exc) == f"{path}: " + WRITE_FAILED.format("No space left on device")
    assert not path.exists()


def test_a_failed_save_of_another_error_gives_its_first_line(tmp_path):
    """A non-``OSError`` (no ``strerror`` at all) and an ``OSError`` without one."""
    for exc_in, reason in [(ValueError("cannot pickle this\nmore"), "cannot pickle this"),
                           (OSError("the writer gave up"), "the writer gave up"),
                           (ValueError("v" * 120), "v" * 120),
                           (ValueError("w" * 121), cut("w" * 121, 120))]:
        path = tmp_path / "step-6.ckpt"
        exc = caught(torch.save, {"x": Raises(exc_in)}, path)
        assert errors.describe_failure(exc) == f"{path}: " + WRITE_FAILED.format(reason)
        assert not path.exists()


def test_a_failed_save_to_a_handle_is_the_checkpoint():
    """A failed save to a handle is described as "the checkpoint", its reason kept."""
    exc = caught(torch.save, {"x": Raises(ValueError("nope"))}, io.BytesIO())
    assert errors.describe_failure(exc) == "the checkpoint: " + KEPT.format("nope")


def test_a_failed_save_leaves_what_is_not_a_file(tmp_path):
    """A save to a link to a folder fails; the link is not a file, so it stays."""
    folder = tmp_path / "folder"
    folder.mkdir()
    link = tmp_path / "link"
    link.symlink_to(folder)
    exc = caught(torch.save, {"a": 1}, str(link))
    assert errors.describe_failure(exc) == f"{link}: " + KEPT.format(errors.first_line(exc, 120))
    assert link.is_symlink() and folder.is_dir()


@pytest.mark.skipif(not os.path.isfile("/proc/self/status"), reason="needs Linux's /proc")
def test_a_file_that_cannot_be_removed_still_gets_its_line():
    """``/proc/self/status`` is a file no one (root included) may write or remove: the save fails, the
    removal fails, the line is still given."""
    exc = caught(torch.save, {"a": 1}, "/proc/self/status")
    assert errors.describe_failure(exc) == "/proc/self/status: " + KEPT.format(errors.first_line(exc, 120))
    assert os.path.isfile("/proc/self/status")


# -- describe_failure: the rest --------------------------------------------------------------------
def test_an_input_error_is_its_own_message():
    """An ``InputError`` is described by its own message, whole."""
    assert errors.describe_failure(InputError("data: no images\nsecond")) == "data: no images\nsecond"
    assert errors.describe_failure(InputError("x")) == "x"


@pytest.mark.parametrize("code", sorted(errors.WRITE_ERRNOS))
def test_a_write_errno_with_a_file_name_is_a_write_failure(code):
    """An ``OSError`` with a write errno and a file name is a write failure; without a file name, or another errno,
    it is not."""
    exc = caught(open, "/nonexistent-root-folder/x")  # ENOENT: not a write errno
    assert errors.describe_failure(exc) is None
    exc = OSError(code, os.strerror(code), "/out/a.png")
    assert errors.describe_failure(exc) == errors.write_failure(exc)
    assert errors.describe_failure(exc).startswith(f"/out/a.png: cannot write ({os.strerror(code)}); ")
    assert errors.describe_failure(OSError(code, os.strerror(code))) is None  # no file name


def test_other_exceptions_keep_pythons_report():
    """Any other exception has no description: Python's report stands."""
    for exc in (ValueError("x"), KeyError("k"), ZeroDivisionError(), OSError(errno.ENOENT, "No such file", "/a"),
                OSError("plain")):
        assert errors.describe_failure(exc) is None


def wandb_error(name: str, module: str):
    return type(name, (Exception,), {"__module__": module})


def test_a_wandb_error_says_how_to_log_in():
    """An error of the ``wandb`` package says how to log in or choose another ``--vis``, its message cut at 120
    characters; a module that only contains "wandb" in its name is not wandb's."""
    tail = ("it needs an account: log in with `wandb login` (or set WANDB_MODE=offline), or pass --vis viewer "
            "(nerfstudio's web viewer) or --vis tensorboard")
    comm = wandb_error("CommError", fresh("wandb") + ".errors.errors")
    for message, shown in [("No API key configured\nmore", "No API key configured"), ("m" * 120, "m" * 120),
                           ("n" * 121, cut("n" * 121, 120))]:
        assert errors.describe_failure(comm(message)) == f"--vis wandb: wandb could not start (CommError: {shown}); {tail}"
    top = wandb_error("Error", fresh("wandb"))
    assert errors.describe_failure(top("x")) == f"--vis wandb: wandb could not start (Error: x); {tail}"
    for module in ("wandbx.errors", "my.wandb", "errors.wandb.x"):
        assert errors.describe_failure(wandb_error("CommError", module)("x")) is None


# -- is_network_error ------------------------------------------------------------------------------
def test_network_errors_are_recognised():
    assert errors.is_network_error(urllib.error.URLError("no route"))
    assert errors.is_network_error(socket.gaierror(-2, "Name or service not known"))
    assert errors.is_network_error(socket.herror(1, "Unknown host"))
    assert errors.is_network_error(ConnectionRefusedError(errno.ECONNREFUSED, "Connection refused"))
    assert errors.is_network_error(ConnectionError("reset"))
    assert errors.is_network_error(TimeoutError("timed out"))


@pytest.mark.parametrize("module", [*errors.NETWORK_MODULES, "requests.exceptions", "urllib3.exceptions",
                                    "huggingface_hub.utils._errors"])
def test_an_oserror_of_a_download_library_is_a_network_error(module):
    """An ``OSError`` raised by a download library's module is a network error."""
    cls = type("DownloadError", (OSError,), {"__module__": fresh(module)})
    assert errors.is_network_error(cls("x")) is True


def test_other_errors_are_not_network_errors():
    """A library's error that is not an ``OSError``, a plain ``OSError`` and one of a look-alike module are not
    network errors."""
    not_os = type("HTTPError", (ValueError,), {"__module__": "requests.exceptions"})
    for exc in (not_os("x"), OSError("disk"), FileNotFoundError(errno.ENOENT, "No such file"), ValueError("x"),
                type("E", (OSError,), {"__module__": "requestsx.exceptions"})("x"),
                type("E", (OSError,), {"__module__": "my.requests"})("x")):
        assert errors.is_network_error(exc) is False


# -- provider, build_failure -----------------------------------------------------------------------
def host_class(module: str, name: str = "Field"):
    return type(name, (), {"__module__": module})


def test_the_hosts_own_classes_are_nerfstudios():
    """A class of a ``nerfstudio`` module (its name built at run time) is provided by nerfstudio."""
    assert errors.provider(host_class(fresh("nerfstudio") + ".fields.base_field")) == "nerfstudio"
    assert errors.provider(host_class("nerfstudio")) == "nerfstudio"


def dist_info(root: Path, folder: str, name: str, top: str, release: str = "") -> None:
    """An installed distribution's metadata: ``folder`` (``<name>-<version>.dist-info``), its ``Name``, its
    ``Version`` (none when empty) and the top-level module it declares."""
    info = root / folder
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\n" + (f"Version: {release}\n" if release else ""))
    (info / "top_level.txt").write_text(f"{top}\n")


def test_a_plugin_is_named_by_its_first_distribution_and_version(tmp_path, monkeypatch):
    """A module two distributions declare (of different versions): the first one's name and its version."""
    assert errors.provider(host_class("yaml.nodes")) == f"the plugin PyYAML {version('PyYAML')}"
    dist_info(tmp_path, "verdist_a-1.0.dist-info", "verdist_a", "sp_vermod", "1.0")
    dist_info(tmp_path, "verdist_b-2.0.dist-info", "verdist_b", "sp_vermod", "2.0")
    monkeypatch.syspath_prepend(str(tmp_path))
    dists = packages_distributions()["sp_vermod"]
    assert sorted(dists) == ["verdist_a", "verdist_b"]
    first = dists[0]
    assert errors.provider(host_class("sp_vermod.fields")) == f"the plugin {first} {'1.0' if first == 'verdist_a' else '2.0'}"


def test_a_module_no_distribution_declares_is_named_by_its_top():
    assert errors.provider(host_class("no_such_module_anywhere.sub")) == "the plugin no_such_module_anywhere"


def test_a_distribution_without_metadata_is_named_without_a_version(tmp_path, monkeypatch):
    """Two ``.dist-info`` whose names are not their folders': ``version`` cannot find them."""
    dist_info(tmp_path, "fakedist-1.0.dist-info", "ghostdist", "ghostmod")
    dist_info(tmp_path, "fakedist2-1.0.dist-info", "ghostdist2", "ghostmod")
    monkeypatch.syspath_prepend(str(tmp_path))
    dists = packages_distributions()["ghostmod"]
    assert sorted(dists) == ["ghostdist", "ghostdist2"]
    assert errors.provider(host_class("ghostmod.fields")) == f"the plugin {dists[0]}"


def test_a_distribution_whose_metadata_has_no_version_is_named_without_one(tmp_path, monkeypatch):
    """A found distribution without a ``Version`` line (``version()`` gives None on Python 3.11 where it used to
    say "the plugin nover None": a regression test for that defect, found by the exact tests' review)."""
    dist_info(tmp_path, "nover-0.dist-info", "nover", "sp_novermod")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert errors.provider(host_class("sp_novermod.fields")) == "the plugin nover"


def test_build_failure_of_a_network_error():
    """A host model that cannot reach the network while it is built gets the network hint."""
    cls = host_class("nerfstudio.models.zipnerf", "ZipNerfModel")
    exc = ConnectionRefusedError("Connection refused")
    assert errors.build_failure(exc, cls, "building the model") == (
        "ZipNerfModel of nerfstudio failed while building the model (ConnectionRefusedError: Connection refused); it "
        "downloads files while the model is built and could not reach the network: connect to the network, or fetch "
        "the files it needs beforehand (see its documentation)")


@pytest.mark.parametrize("size", [160, 161, 20])
def test_build_failure_of_a_missing_file(size):
    """A host model missing a file gets the missing-file hint, the exception's message cut at 160 characters."""
    cls = host_class("nerfstudio.models.lerf", "LERFModel")
    message = "f" * size
    shown = message if size <= 160 else cut(message, 160)
    assert errors.build_failure(FileNotFoundError(message), cls, "loading the weights") == (
        f"LERFModel of nerfstudio failed while loading the weights (FileNotFoundError: {shown}); a file or folder it "
        "needs is missing or unreadable: see its documentation for what it needs")


def test_build_failure_of_a_bug_keeps_its_traceback():
    cls = host_class("nerfstudio.models.lerf", "LERFModel")
    for exc in (ValueError("x"), KeyError("k"), RuntimeError("CUDA out of memory"), InputError("y")):
        assert errors.build_failure(exc, cls, "building the model") is None
