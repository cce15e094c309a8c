"""Fuzz (Hypothesis) over every file kind a user hands our commands.

Each generated or corrupted file goes to the command a user runs with it (its ``main``, in this
process, the way the console script runs it: ``sys.argv`` set, an uncaught exception handed to
``sys.excepthook``, ``SystemExit`` read as the exit status), and the command must either work
(exit 0) or stop with exit status 2 and one line ``<command>: error: ...`` that names the file:
never a traceback, no file written outside its output folder, no input file changed, nothing a
file names executed (every hostile payload here would create ``sp-fuzz-marker`` in the working
folder).

=================  ==============================================  =================================
kind               command                                         what is generated
=================  ==============================================  =================================
config.yml         sp-export-mesh --load-config                    a real run's config.yml with hostile
                                                                   tags spliced in, truncated, bytes
                                                                   flipped, lines dropped / doubled;
                                                                   YAML node trees with any tag
checkpoint         sp-export-mesh (the run's .ckpt),               truncated, bytes flipped, pickled
                   sp-fit --resume (checkpoint.pt)                 callables, random pickle opcodes,
                                                                   wrong contents
transforms / meta  sp-train sp-neus-hashgrid blender-data /        JSON edits (types, missing keys,
                   sdfstudio-data --data                           file_path outside the scene,
                                                                   invalid JSON), damaged images
mesh / cloud       sp-fit pointcloud | sdf, sp-scene               PLY (ascii, binary, clouds with
                                                                   normals), OBJ, STL, OFF: NaN, huge,
                                                                   bad indices, truncated, random bytes
image              sp-fit image                                    8/16-bit grey and colour, alpha,
                                                                   palette, 32-bit, 1x1, truncated,
                                                                   bytes flipped, random bytes
sweep spec         sp-sweep SPEC --dry-run                         YAML / JSON mappings of any values,
                                                                   python tags, truncated
=================  ==============================================  =================================

Examples per kind: :data:`EXAMPLES` (derandomized: the same files every run, no example database
written). ``SP_FUZZ_REPORT=path.json`` writes the distinct one-line errors seen, per kind.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import re
import shutil
import subprocess
import sys
import zipfile
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
import yaml
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st
from yaml.nodes import MappingNode, ScalarNode, SequenceNode

EXAMPLES = {"config": 40, "checkpoint": 16, "fit-checkpoint": 8, "transforms": 20, "meta": 12, "mesh": 30, "image": 30,
            "sweep": 60}
MARKER = "sp-fuzz-marker"
TOUCH = f"touch {MARKER}"
BIN = Path(sys.executable).parent
COLLECT = os.environ.get("SP_FUZZ_COLLECT") == "1"
SCALE = int(os.environ.get("SP_FUZZ_SCALE", "1"))
"""``SP_FUZZ_SCALE=N``: N times the examples (a longer hunt; the suite runs 1)."""
MEMORY = 12 * 2**30
"""Address space of this process while the fuzz runs (nerfstudio and torch take about 4 GB of it)."""


def _settings(kind: str):
    # no shrinking: a failure is reported as generated (its blob reproduces it), within a bounded time
    return settings(max_examples=EXAMPLES[kind] * SCALE, deadline=None, database=None, derandomize=True, print_blob=True,
                    suppress_health_check=list(HealthCheck), phases=(Phase.explicit, Phase.generate))


# -- running a command the way its console script does ---------------------------------------------------


def _call(fn, argv, prog: str) -> int:
    """The command's exit status; afterwards ``sys.argv`` and what the command installed for its
    process (``registry.install_for_process``) are as they were, as when a process ends."""
    from sp_plugins.patches import registry

    saved_argv = sys.argv
    sys.argv = [str(BIN / prog), *map(str, argv)]
    try:
        rc = fn(list(map(str, argv)))
    except SystemExit as stop:
        return stop.code if isinstance(stop.code, int) else (0 if stop.code is None else 1)
    except Exception as exc:  # noqa: BLE001  (what the interpreter does with it: the installed hook, or a traceback)
        try:
            sys.excepthook(type(exc), exc, exc.__traceback__)
        except SystemExit as stop:
            return stop.code if isinstance(stop.code, int) else 1
        return 1
    finally:
        sys.argv = saved_argv
        registry.end_for_process()
    return 0 if rc is None else rc


def _tree(root: Path, skip: Path) -> dict:
    out = {}
    for p in sorted(root.rglob("*")):
        if p == skip or skip in p.parents or p.name == MARKER:
            continue
        st_ = p.lstat()
        out[str(p.relative_to(root))] = "dir" if p.is_dir() and not p.is_symlink() else (st_.st_mtime_ns, st_.st_size)
    return out


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest() if path.is_file() else "-"


class Harness:
    """Runs one command on one generated input and checks every promise; tallies the error lines."""

    def __init__(self, root: Path):
        self.root = root
        self.count = 0
        self.seen = defaultdict(Counter)
        self.failures = []

    def case(self, name: str) -> Path:
        self.count += 1
        folder = self.root / "cases" / f"{self.count:04d}-{name}"
        folder.mkdir(parents=True)
        return folder

    def input_file(self, name: str, file: tuple) -> tuple:
        """A new case holding one drawn input file ``(suffix, bytes)``: its path and the case's ``out``."""
        suffix, data = file
        case = self.case(name)
        path = case / f"input{suffix}"
        path.write_bytes(data)
        return path, case / "out"

    def run(self, kind: str, prog: str, fn, argv, out: Path, inputs, names) -> tuple:
        if not COLLECT:
            return self._run(kind, prog, fn, argv, out, inputs, names)
        try:
            return self._run(kind, prog, fn, argv, out, inputs, names)
        except AssertionError as failed:  # SP_FUZZ_COLLECT=1: list every failure instead of stopping at the first
            self.failures.append(str(failed)[:3000])
            return None, None

    def _run(self, kind: str, prog: str, fn, argv, out: Path, inputs, names) -> tuple:
        inputs = [Path(p) for p in inputs]
        before, digests = _tree(self.root, out), {p: _digest(p) for p in inputs}
        stdout, stderr = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
            rc = _call(fn, argv, prog)
        err = stderr.getvalue()
        report = f"[{kind}] {prog} {' '.join(map(str, argv))}\nrc={rc}\n--- stderr\n{err[-4000:]}"
        assert "Traceback" not in err, report
        assert rc in (0, 2), report
        assert not (self.root / MARKER).exists(), f"a file's payload ran\n{report}"
        after = _tree(self.root, out)
        assert after == before, f"written outside the output folder: {sorted(set(after) ^ set(before)) or 'changed files'}\n{report}"
        assert {p: _digest(p) for p in inputs} == digests, f"an input file changed\n{report}"
        if rc == 0:
            self.seen[kind]["(works)"] += 1
            return rc, None
        lines = [line for line in err.splitlines() if line.strip()]
        errors = [line for line in lines if ": error: " in line]
        assert len(errors) == 1 and errors[0] == lines[-1] and errors[0].startswith(f"{prog}: error: "), report
        assert any(str(n) in errors[0] for n in names), f"the error names none of {names}\n{report}"
        self.seen[kind][self.normalized(errors[0])] += 1
        return rc, errors[0]

    def normalized(self, line: str) -> str:
        text = line.split(": error: ", 1)[1].replace(str(self.root), "<tmp>")
        text = re.sub(r"<tmp>/cases/\d+-[\w.-]+", "<case>", text)
        text = re.sub(r"(?<![\w!])\d[\d.e+-]*", "N", text)
        return text[:200]


@pytest.fixture(scope="module")
def harness(tmp_path_factory):
    import resource

    root = tmp_path_factory.mktemp("fuzz")
    hook, cwd = sys.excepthook, os.getcwd()
    limit = resource.getrlimit(resource.RLIMIT_AS)
    # a file that asks for gigabytes fails here as a MemoryError (a traceback the harness reports), not as the OOM killer
    resource.setrlimit(resource.RLIMIT_AS, (min(MEMORY, limit[1]) if limit[1] > 0 else MEMORY, limit[1]))
    os.chdir(root)  # the hostile payloads' marker, and any file a command wrote relative to it, land here
    h = Harness(root)
    try:
        yield h
    finally:
        resource.setrlimit(resource.RLIMIT_AS, limit)
        os.chdir(cwd)
        if not hasattr(hook, "sp_plugins_input_errors"):  # (ours, held by a live object of an earlier test, is the
            sys.excepthook = hook                         # registry's to restore when that object goes)
        report = os.environ.get("SP_FUZZ_REPORT")
        if report:
            seen = {k: dict(v) for k, v in h.seen.items()}
            Path(report).write_text(json.dumps({"seen": seen, "failures": h.failures}, indent=1, sort_keys=True))


# -- a real run (sp-train), shared by the config and checkpoint kinds ---------------------------------------

TRAIN = [
    "--machine.device-type", "cpu", "--vis", "tensorboard", "--timestamp", "t", "--logging.local-writer.enable", "False",
    "--pipeline.datamanager.train-num-rays-per-batch", "32", "--pipeline.datamanager.eval-num-rays-per-batch", "32",
    "--pipeline.model.num-samples", "8", "--pipeline.model.num-samples-importance", "8",
    "--pipeline.model.num-up-sample-steps", "1", "--pipeline.model.num-samples-outside", "4",
    "--pipeline.model.sdf-field.hidden-dim", "16", "--pipeline.model.sdf-field.hidden-dim-color", "16",
    "--pipeline.model.sdf-field.geo-feat-dim", "7", "--pipeline.model.sdf-field.num-levels", "4",
    "--pipeline.model.sdf-field.log2-hashmap-size", "10", "--pipeline.model.sdf-field.max-res", "32",
    "--pipeline.model.eval-num-rays-per-chunk", "256", "--max-num-iterations", "1", "--steps-per-save", "1",
]
METHOD = "sp-neus-hashgrid"


def sp_train(argv):
    from sp_plugins.cli.train import train

    try:
        return train(argv)
    finally:  # as a new process would start: nerfstudio keeps a run's event writers in module globals
        from nerfstudio.utils import writer

        for w in writer.EVENT_WRITERS:
            getattr(getattr(w, "tb_writer", None), "close", lambda: None)()
        writer.EVENT_WRITERS.clear()
        writer.EVENT_STORAGE.clear()


def export_mesh(argv):
    from sp_plugins.cli.export_mesh import main

    return main(argv)


@pytest.fixture(scope="module")
def scene(harness):
    from sp_plugins.data import make_tiny_scene

    return make_tiny_scene(harness.root / "scene", mesh="sphere", n_train=4, n_val=1, n_test=1, resolution=16).root


@pytest.fixture(scope="module")
def run(harness, scene):
    """config.yml of a 1-step sp-neus-hashgrid run, written by sp-train (in this process)."""
    out = harness.root / "run"
    rc, line = harness.run("setup", "sp-train", sp_train, [METHOD, *TRAIN, "--output-dir", out, "blender-data", "--data",
                                                          scene / "blender"], out, [], [])
    assert rc == 0, line
    (config,) = out.glob("*/*/t/config.yml")
    assert list((config.parent / "nerfstudio_models").glob("*.ckpt"))
    return config


# -- config.yml ---------------------------------------------------------------------------------------------

PY = "tag:yaml.org,2002:python/"
HOSTILE_VALUES = [
    f'!!python/object/apply:os.system ["{TOUCH}"]',
    f'!!python/object/apply:subprocess.call [["touch", "{MARKER}"]]',
    f"!!python/object/apply:builtins.eval [\"__import__('os').system('{TOUCH}')\"]",
    f'!!python/object/new:os.system ["{TOUCH}"]',
    f'!!python/object/apply:nerfstudio.utils.scripts.run_command ["{TOUCH}"]',
    "!!python/name:os.system ''",
    "!!python/module:os ''",
    "!!python/object:builtins.type {a: 1}",
    f'!!python/object/apply:_operator.getitem [!!python/name:os.system "", "{TOUCH}"]',
    f"!local {TOUCH}",
]
TAGS = [None, None, None, "tag:yaml.org,2002:str", "tag:yaml.org,2002:int", "tag:yaml.org,2002:float",
        "tag:yaml.org,2002:bool", "tag:yaml.org,2002:null", "tag:yaml.org,2002:binary", "tag:yaml.org,2002:timestamp",
        "tag:yaml.org,2002:set", "tag:yaml.org,2002:omap", "tag:yaml.org,2002:seq", "tag:yaml.org,2002:map",
        PY + "tuple", PY + "str", PY + "name:nerfstudio.engine.trainer.Trainer", PY + "name:os.system",
        PY + "name:nerfstudio.data.utils.nerfstudio_collate.nerfstudio_collate",
        PY + "object:sp_plugins.core.config.SPConfig", PY + "object:nerfstudio.engine.trainer.TrainerConfig",
        PY + "object:sp_plugins.nerfstudio.retired.Config", PY + "object/apply:pathlib.PosixPath",
        PY + "object/apply:nerfstudio.utils.writer.EventName", PY + "object/apply:os.system",
        PY + "object/apply:_operator.getitem", PY + "object/new:os.system", PY + "module:os", "!local"]


def _scalar(tag, value):
    return ScalarNode(tag or "tag:yaml.org,2002:str", value)


scalars = st.builds(_scalar, st.sampled_from(TAGS),
                    st.one_of(st.text(max_size=10), st.sampled_from(["", "1", "-3.5", "x", TOUCH, "2020-01-01", "AAAA", "true"])))
keys = st.builds(_scalar, st.sampled_from([None, None, "tag:yaml.org,2002:int", PY + "tuple"]),
                 st.one_of(st.sampled_from(["pipeline", "__class__", "_target", "output_dir", "x"]), st.text(max_size=6)))
nodes = st.recursive(scalars, lambda kids: st.one_of(
    st.builds(lambda tag, items: SequenceNode(tag or "tag:yaml.org,2002:seq", items), st.sampled_from(TAGS),
              st.lists(kids, max_size=4)),
    st.builds(lambda tag, pairs: MappingNode(tag or "tag:yaml.org,2002:map", pairs), st.sampled_from(TAGS),
              st.lists(st.tuples(keys, kids), max_size=4))), max_leaves=10)

NOT_DIGITS = st.characters(blacklist_categories=("Nd", "Cs"))  # a flipped digit could ask for a 2^90 hash table


@st.composite
def mutated_text(draw, text: str, hostile=HOSTILE_VALUES):
    lines = text.splitlines()
    how = draw(st.sampled_from(["hostile", "hostile", "truncate", "flip", "drop", "double", "insert"]))
    if how == "hostile":  # a value somewhere replaced by a payload
        i = draw(st.integers(0, len(lines) - 1))
        key, sep, _ = lines[i].partition(":")
        lines[i] = f"{key}: {draw(st.sampled_from(hostile))}" if sep else draw(st.sampled_from(hostile))
        return "\n".join(lines) + "\n"
    if how == "truncate":
        return text[: draw(st.integers(0, len(text)))]
    if how == "flip":
        chars = list(text)
        for _ in range(draw(st.integers(1, 4))):
            at = draw(st.integers(0, len(chars) - 1))
            if not chars[at].isdigit():
                chars[at] = draw(NOT_DIGITS)
        return "".join(chars)
    i = draw(st.integers(0, len(lines) - 1))
    if how == "drop":
        del lines[i: i + draw(st.integers(1, 3))]
    elif how == "double":
        lines.insert(i, lines[i])
    else:
        lines.insert(i, draw(st.text(NOT_DIGITS, max_size=20)))
    return "\n".join(lines) + "\n"


def test_config_yml(harness, run):
    real = run.read_text()

    @_settings("config")
    @given(text=st.one_of(mutated_text(real), nodes.map(yaml.serialize)))
    def check(text):
        case = harness.case("config")
        path = case / "config.yml"
        path.write_text(text)
        out = case / "mesh"
        harness.run("config", "sp-export-mesh", export_mesh, ["--load-config", path, "--output-dir", out, "--resolution", "8",
                                                               "--coarse", "4"], out, [path], [path])

    check()


# -- checkpoints ---------------------------------------------------------------------------------------------


class Call:
    """Pickles as ``fn(*args)``: what a hostile checkpoint carries."""

    def __init__(self, fn, *args):
        self.fn, self.args = fn, args

    def __reduce__(self):
        return (self.fn, self.args)


def _payloads():
    import builtins

    code = f"__import__('os').system('{TOUCH}')"
    return [Call(os.system, TOUCH), Call(subprocess.call, ["touch", MARKER]), Call(builtins.eval, code),
            Call(builtins.exec, code), Call(builtins.print, "x"), Call(builtins.__import__, "os"), print, os.system,
            np.array([TOUCH], dtype=object), np.str_("x"), {1, 2}, slice(1, 2), Counter(a=1), complex(1, 2)]


def _with_pickle(original: bytes, data: bytes) -> bytes:
    """The checkpoint zip with its data.pkl replaced by ``data`` (every other member kept)."""
    src, dst = io.BytesIO(original), io.BytesIO()
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w", zipfile.ZIP_STORED) as zout:
        for item in zin.infolist():
            zout.writestr(item, data if item.filename.endswith("/data.pkl") else zin.read(item.filename))
    return dst.getvalue()


@st.composite
def damaged_checkpoint(draw, original: bytes, state: dict):
    how = draw(st.sampled_from(["truncate", "flip", "payload", "payload", "opcodes", "contents"]))
    if how == "truncate":
        return original[: draw(st.integers(0, len(original) - 1))]
    if how == "flip":
        data = bytearray(original)
        for _ in range(draw(st.integers(1, 6))):
            data[draw(st.integers(0, len(data) - 1))] = draw(st.integers(0, 255))
        return bytes(data)
    buf = io.BytesIO()
    if how == "payload":  # a real checkpoint carrying one object weights-only unpickling must refuse or keep inert
        changed = dict(state)
        changed[draw(st.sampled_from(["x", "pipeline", "optimizers", "step"]))] = draw(st.sampled_from(_payloads()))
        torch.save(changed, buf)
        return buf.getvalue()
    if how == "opcodes":
        return _with_pickle(original, b"\x80\x02" + draw(st.binary(max_size=48)) + b".")
    contents = draw(st.sampled_from([{}, [], "text", {"pipeline": {}}, {"pipeline": {"_model.field.x": torch.zeros(3)}},
                                     {"step": "one", "pipeline": state["pipeline"]}, {"pipeline": [1, 2]}]))
    torch.save(contents, buf)
    return buf.getvalue()


def test_checkpoint_of_a_run(harness, run):
    (ckpt,) = (run.parent / "nerfstudio_models").glob("*.ckpt")
    original = ckpt.read_bytes()
    state = torch.load(ckpt, map_location="cpu", weights_only=True)
    folder = run.parents[3]  # a copy of the run: sp-export-mesh reads its checkpoint from there
    copy_root = harness.root / "run-copy"
    shutil.copytree(folder, copy_root)
    config = copy_root / run.relative_to(folder)
    from sp_plugins.adapter.safe_config import load_run_config

    loaded = load_run_config(config)
    loaded.output_dir = copy_root
    config.write_text(yaml.dump(loaded))
    target = config.parent / "nerfstudio_models" / ckpt.name

    @_settings("checkpoint")
    @given(data=damaged_checkpoint(original, state))
    def check(data):
        target.write_bytes(data)
        case = harness.case("ckpt")
        out = case / "mesh"
        harness.run("checkpoint", "sp-export-mesh", export_mesh, ["--load-config", config, "--output-dir", out,
                                                                   "--resolution", "8", "--coarse", "4"], out,
                    [target, config], [target, config])

    check()


FIT = ["--encoding.levels", "2", "--encoding.log2-table-size", "8", "--encoding.base-resolution", "4",
       "--encoding.max-resolution", "16", "--hidden", "8", "--steps", "2", "--quiet"]
MESH_FIT = ["--mesh-resolution", "12", "--refine", "0", "--metric-points", "500"]
CLOUD = ["--n-points", "600", "--surface-batch", "64", "--space-batch", "64"]


def sp_fit(argv):
    from sp_plugins.cli.fit import main

    return main(argv)


def test_checkpoint_of_sp_fit(harness):
    sphere = harness.root / "fit-sphere.ply"
    trimesh.creation.icosphere(1).export(sphere)
    base = harness.root / "fit-run"
    args = ["pointcloud", sphere, *CLOUD, *FIT, *MESH_FIT]
    rc, line = harness.run("setup", "sp-fit", sp_fit, [*args, "--out", base, "--checkpoint-every", "1"], base, [sphere], [])
    assert rc == 0, line
    original = (base / "checkpoint.pt").read_bytes()
    state = torch.load(base / "checkpoint.pt", map_location="cpu", weights_only=True)
    state.setdefault("pipeline", {})

    @_settings("fit-checkpoint")
    @given(data=damaged_checkpoint(original, state))
    def check(data):
        out = harness.case("fit-resume") / "out"
        shutil.copytree(base, out)
        (out / "checkpoint.pt").write_bytes(data)
        harness.run("fit-checkpoint", "sp-fit", sp_fit, [*args, "--out", out, "--resume"], out, [sphere],
                    [out / "checkpoint.pt"])

    check()


# -- transforms_*.json and meta_data.json ---------------------------------------------------------------------

JSON = st.recursive(st.one_of(st.none(), st.booleans(), st.integers(-3, 10**6), st.floats(allow_nan=True),
                              st.text(max_size=8)),
                    lambda kids: st.one_of(st.lists(kids, max_size=3), st.dictionaries(st.text(max_size=6), kids, max_size=3)),
                    max_leaves=6)
OUTSIDE = ["../outside/r_0", "../../../../../../etc/passwd", "/etc/hostname", "train/../../outside/r_0", "", ".",
           "train", "train/r_0.png", "train/\u0000r_0"]


@st.composite
def edited_json(draw, meta: dict, path_key: str, outside: str):
    """``meta`` (a layout's JSON) edited: a value anywhere replaced, a key dropped, a frame's image path
    pointed elsewhere (outside the scene too); or its text broken."""
    import copy

    meta = copy.deepcopy(meta)
    how = draw(st.sampled_from(["keep", "path", "path", "value", "value", "drop", "root", "text"]))
    if how == "path":
        frame = draw(st.integers(0, len(meta["frames"]) - 1))
        meta["frames"][frame][path_key] = draw(st.sampled_from([*OUTSIDE, outside]))
    elif how in ("value", "drop"):
        where, container = [], meta
        while isinstance(container, (dict, list)) and container and draw(st.booleans()):
            key = draw(st.sampled_from(sorted(container) if isinstance(container, dict) else range(len(container))))
            where.append(key)
            if not isinstance(container[key], (dict, list)) or not container[key]:
                break
            container = container[key]
        parent = meta
        for key in where[:-1]:
            parent = parent[key]
        if not where:
            where = [draw(st.sampled_from(sorted(meta)))]
        if how == "drop" and isinstance(parent, dict):
            del parent[where[-1]]
        else:
            parent[where[-1]] = draw(JSON)
    elif how == "root":
        return json.dumps(draw(JSON))
    text = json.dumps(meta, indent=1)
    return text[: draw(st.integers(0, len(text) - 1))] if how == "text" else text


def _damage_image(draw, folder: Path) -> None:
    images = sorted(p for p in folder.rglob("*.png"))
    image = images[draw(st.integers(0, len(images) - 1))]
    data = image.read_bytes()
    image.write_bytes(data[: draw(st.integers(0, len(data) - 1))])


def _scene_case(harness, scene: Path, layout: str, kind: str, draw, edit_name: str, path_key: str) -> None:
    case = harness.case(kind)
    data = case / layout
    shutil.copytree(scene / layout, data)
    outside = harness.root / "outside"
    if not outside.exists():
        outside.mkdir()
        shutil.copy(next((scene / layout).rglob("*.png")), outside / "r_0.png")
    if draw(st.integers(0, 5)) == 0:
        _damage_image(draw, data)
    else:
        meta = json.loads((data / edit_name).read_text())
        absolute = str((outside / "r_0").resolve()) + ("" if layout == "blender" else ".png")
        (data / edit_name).write_text(draw(edited_json(meta, path_key, absolute)))
    out = case / "out"
    parser = "blender-data" if layout == "blender" else "sdfstudio-data"
    inputs = [p for p in data.rglob("*") if p.is_file()] + [harness.root / "outside" / "r_0.png"]
    harness.run(kind, "sp-train", sp_train, [METHOD, *TRAIN, "--output-dir", out, parser, "--data", data], out, inputs, [data])


@pytest.mark.parametrize("layout, kind, edit_name, path_key", [
    ("blender", "transforms", "transforms_train.json", "file_path"),  # nerfstudio's Blender parser
    ("sdfstudio", "meta", "meta_data.json", "rgb_path"),  # the sdfstudio-data parser
])
def test_scene_json(harness, run, scene, layout, kind, edit_name, path_key):
    @_settings(kind)
    @given(data=st.data())
    def check(data):
        _scene_case(harness, scene, layout, kind, data.draw, edit_name, path_key)

    check()


# -- meshes and point clouds ----------------------------------------------------------------------------------


def _cloud_ply(points: np.ndarray, normals: np.ndarray) -> bytes:
    head = (f"ply\nformat ascii 1.0\nelement vertex {len(points)}\n"
            + "".join(f"property float {k}\n" for k in ("x", "y", "z", "nx", "ny", "nz")) + "end_header\n")
    return (head + "".join(" ".join(f"{v:g}" for v in (*p, *n)) + "\n" for p, n in zip(points, normals))).encode()


@st.composite
def mesh_files(draw):
    """(suffix, bytes) of a mesh or point cloud, plausible or not."""
    base = trimesh.creation.icosphere(draw(st.integers(0, 1)))
    vertices, faces = np.array(base.vertices), np.array(base.faces)
    for change in draw(st.lists(st.sampled_from(["nan", "inf", "huge", "tiny", "faces", "drop", "flat", "same"]), max_size=2)):
        i = draw(st.integers(0, len(vertices) - 1))
        if change == "nan":
            vertices[i, draw(st.integers(0, 2))] = np.nan
        elif change == "inf":
            vertices[i] = np.inf
        elif change == "huge":
            vertices *= 1e30
        elif change == "tiny":
            vertices *= 1e-30
        elif change == "faces":
            faces[draw(st.integers(0, len(faces) - 1))] = draw(st.sampled_from([[0, 0, 0], [0, 1, 10**6], [-1, 2, 3]]))
        elif change == "drop":
            faces = faces[: draw(st.integers(0, len(faces)))]
        elif change == "flat":
            vertices[:, 2] = 0
        else:
            vertices[:] = vertices[0]
    suffix = draw(st.sampled_from([".ply", ".ply", ".obj", ".stl", ".off", "cloud"]))
    if suffix == "cloud":
        normals = np.array(base.vertex_normals)
        if draw(st.booleans()):
            normals[draw(st.integers(0, len(normals) - 1))] = draw(st.sampled_from([0.0, np.nan]))
        data, suffix = _cloud_ply(vertices, normals), ".ply"
    else:
        lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in vertices] + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
        valid = faces[(faces >= 0).all(1) & (faces < len(vertices)).all(1)]
        if suffix == ".obj" or len(valid) == 0:
            data, suffix = ("\n".join(lines) + "\n").encode(), ".obj"
        else:
            mesh = trimesh.Trimesh(np.nan_to_num(vertices, nan=0.0, posinf=1e30), valid, process=False)
            kind = {".ply": draw(st.sampled_from(["ply", "ply-ascii"])), ".stl": "stl", ".off": "off"}[suffix]
            if kind == "ply-ascii":
                data = trimesh.exchange.ply.export_ply(mesh, encoding="ascii")
            else:
                data = mesh.export(file_type=kind)
            data = data.encode() if isinstance(data, str) else data
    how = draw(st.sampled_from(["keep", "keep", "keep", "truncate", "flip", "random"]))
    if how == "truncate":
        data = data[: draw(st.integers(0, len(data) - 1))]
    elif how == "flip":
        buf = bytearray(data)
        for _ in range(draw(st.integers(1, 4))):
            buf[draw(st.integers(0, len(buf) - 1))] = draw(st.integers(0, 255))
        data = bytes(buf)
    elif how == "random":
        data = draw(st.binary(max_size=200))
    return suffix, data


def sp_scene(argv):
    from sp_plugins.cli.scene import main

    return main(argv)


@_settings("mesh")
@given(file=mesh_files(), command=st.sampled_from(["pointcloud", "sdf", "scene"]))
def test_meshes_and_point_clouds(harness, file, command):
    path, out = harness.input_file("mesh", file)
    if command == "scene":
        argv = [path, out, "--views", "2", "--val-views", "1", "--test-views", "1", "--resolution", "8", "--quiet"]
        harness.run("mesh", "sp-scene", sp_scene, argv, out, [path], [path])
    else:
        extra = CLOUD if command == "pointcloud" else ["--batch", "32", "--pool", "500"]
        harness.run("mesh", "sp-fit", sp_fit, [command, path, *extra, *FIT, *MESH_FIT, "--out", out], out, [path], [path])


# -- images ---------------------------------------------------------------------------------------------------


@st.composite
def image_files(draw):
    from PIL import Image

    w, h = draw(st.integers(1, 12)), draw(st.integers(1, 12))
    kind = draw(st.sampled_from(["L", "LA", "RGB", "RGBA", "P", "P-transparency", "1", "I;16", "I", "rgb16", "rgba16",
                                 "jpeg", "tiff-float", "bmp", "random"]))
    rng = np.random.default_rng(draw(st.integers(0, 2**16)))
    buf = io.BytesIO()
    if kind in ("rgb16", "rgba16"):
        import cv2

        pixels = rng.integers(0, 65535, size=(h, w, 3 if kind == "rgb16" else 4), dtype=np.uint16)
        ok, encoded = cv2.imencode(".png", pixels)
        assert ok
        data, suffix = encoded.tobytes(), ".png"
    elif kind == "random":
        data, suffix = draw(st.binary(max_size=120)), draw(st.sampled_from([".png", ".jpg"]))
    else:
        if kind in ("I;16", "I"):
            im = Image.fromarray(rng.integers(0, 65535, size=(h, w)).astype(np.uint16 if kind == "I;16" else np.int32))
        elif kind == "tiff-float":
            im = Image.fromarray(rng.random((h, w)).astype(np.float32))
        else:
            im = Image.fromarray(rng.integers(0, 255, size=(h, w, 4), dtype=np.uint8), "RGBA")
            im = {"L": lambda: im.convert("L"), "LA": lambda: im.convert("LA"), "RGB": lambda: im.convert("RGB"),
                  "RGBA": lambda: im, "P": lambda: im.convert("P"), "P-transparency": lambda: im.convert("P"),
                  "1": lambda: im.convert("1"), "jpeg": lambda: im.convert("RGB"), "bmp": lambda: im.convert("RGB")}[kind]()
        fmt = {"jpeg": "JPEG", "tiff-float": "TIFF", "I": "TIFF", "bmp": "BMP"}.get(kind, "PNG")  # PIL writes no 32-bit PNG
        extra = {"transparency": 0} if kind == "P-transparency" else {}
        im.save(buf, format=fmt, **extra)
        data, suffix = buf.getvalue(), {"JPEG": ".jpg", "TIFF": ".tif", "BMP": ".bmp"}.get(fmt, ".png")
    how = draw(st.sampled_from(["keep", "keep", "truncate", "flip"]))
    if how == "truncate" and data:
        data = data[: draw(st.integers(0, len(data) - 1))]
    elif how == "flip" and data:
        b = bytearray(data)
        for _ in range(draw(st.integers(1, 3))):
            b[draw(st.integers(0, len(b) - 1))] = draw(st.integers(0, 255))
        data = bytes(b)
    return suffix, data


@_settings("image")
@given(file=image_files(), adaptive=st.booleans())
def test_images(harness, file, adaptive):
    path, out = harness.input_file("image", file)
    argv = ["image", path, *FIT, "--batch", "64", "--out", out, *(["--adaptive-alpha", "--alpha-map-downscale", "4"] if adaptive else [])]
    harness.run("image", "sp-fit", sp_fit, argv, out, [path], [path])


# -- sweep specs ----------------------------------------------------------------------------------------------

FIELDS = ["command", "data", "grid", "sp", "sp_methods", "seeds", "sample", "sample_seed", "success", "metric", "eval",
          "sp_only", "unknown"]
GOOD = {"command": "sp-fit pointcloud s.ply --steps 3", "grid": {"lr": [1e-3, 1e-2]}, "seeds": [0, 1],
        "success": ["chamfer <= 0.01"], "sp": "both"}
SPEC_VALUES = st.one_of(JSON, st.sampled_from(["sp-fit pointcloud s.ply", "ns-train neus-hashgrid", f"sh -c '{TOUCH}'",
                                               "psnr >= 24", "on", "off", "both", ["neus", "sp-neus"], {"lr": "1e-3,1e-2"}]))


@st.composite
def sweep_specs(draw):
    spec = dict(GOOD) if draw(st.booleans()) else {}
    for key in draw(st.lists(st.sampled_from(FIELDS), max_size=4)):
        spec[key] = draw(SPEC_VALUES)
    for key in draw(st.lists(st.sampled_from(sorted(spec) or ["command"]), max_size=1)):
        spec.pop(key, None)
    text = yaml.safe_dump(spec) if draw(st.booleans()) else json.dumps(spec)
    how = draw(st.sampled_from(["keep", "keep", "keep", "hostile", "truncate", "raw"]))
    if how == "hostile":
        text = draw(mutated_text(text or "x: 1"))
    elif how == "truncate":
        text = text[: draw(st.integers(0, max(len(text) - 1, 0)))]
    elif how == "raw":
        text = yaml.serialize(draw(nodes))
    return text


def sp_sweep(argv):
    from sp_plugins.cli.sweep import main

    return main(argv)


@_settings("sweep")
@given(text=sweep_specs())
def test_sweep_specs(harness, text):
    case = harness.case("sweep")
    path = case / "spec.yaml"
    path.write_text(text)
    out = case / "out"
    harness.run("sweep", "sp-sweep", sp_sweep, [path, "--out", out, "--dry-run"], out, [path], [path])


def test_sweep_spec_naming_os_system_runs_nothing_under_the_real_console_script(tmp_path):
    spec = tmp_path / "spec.yaml"
    spec.write_text(f'command: !!python/object/apply:os.system ["{TOUCH}"]\n')
    proc = subprocess.run([str(BIN / "sp-sweep"), str(spec), "--out", str(tmp_path / "out"), "--dry-run"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=300, env=dict(os.environ, OMP_NUM_THREADS="1"))
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 2 and "Traceback" not in proc.stderr and len(lines) == 1, proc.stderr
    assert lines[0].startswith(f"sp-sweep: error: {spec}: not valid YAML/JSON") and "os.system" in lines[0], lines[0]
    assert not (tmp_path / MARKER).exists() and not (tmp_path / "out").exists()
