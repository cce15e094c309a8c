"""Every registered method trains through the real ``ns-train`` (and ``sp-train nerfacto`` through
``sp-train``) under nerfstudio's default ``--vis viewer`` on the tiny synthetic scene, and its
checkpoint loads in the real ``ns-eval`` (subprocesses); ``ns-render`` and the mesh export for one SDF
method. (sp-nerfacto and sp-neus-hashgrid run the whole command line on a real capture in
test_real_capture.py.)

The runs use the command line a user types plus budget flags (tiny sizes, 2 steps) and the one flag
a test adds under the viewer, ``--viewer.quit-on-train-completion True`` (every SP method
stopped in ``Trainer.setup`` under the default viewer, and these runs used to pass ``--vis
tensorboard`` or train in-process).

torch >= 2.6 loads checkpoints weights-only; nerfstudio's schedulers stored numpy learning rates,
which it refuses. The SDF runs here go past the warm-up so the cosine factor is a numpy scalar.
"""

from __future__ import annotations

import subprocess
import sys
from types import SimpleNamespace

import numpy as np
import pytest
import trimesh

from tests.helpers.errors import refused
from tests.helpers.ns_commands import ENV, NERFACTO_FLAGS, RUN_FLAGS, SDF_FLAGS, _report, check_eval, command, ns_eval_args
from tests.helpers.ns_configs import SDF_METHODS
from tests.helpers.viewer import PORT_LINE

from sp_plugins.nerfstudio.runs import our_methods
from sp_plugins.nerfstudio.components.schedulers import FloatCosineDecaySchedulerConfig, FloatExponentialDecaySchedulerConfig

ON_THE_FOX = ("sp-nerfacto", "sp-neus-hashgrid")
OTHERS = sorted(set(our_methods()) - set(ON_THE_FOX))
SP_TRAIN = "sp-train nerfacto"
"""nerfstudio's own nerfacto under ``sp-train``, as the README runs it (its parallel data manager included)."""

TINY_FLAGS = {
    "relu-field": ["--pipeline.model.resolution", "17", "--pipeline.model.num-samples", "16"],
    "nerf": ["--pipeline.model.num-coarse-samples", "8", "--pipeline.model.num-importance-samples", "8"],
    "sp-tensorf": ["--pipeline.model.init-resolution", "16", "--pipeline.model.final-resolution", "24",
                   "--pipeline.model.upsampling-iters", "2", "--pipeline.model.num-samples", "8",
                   "--pipeline.model.num-uniform-samples", "16", "--pipeline.model.num-den-components", "4",
                   "--pipeline.model.num-color-components", "8"],
}
"""Budget flags per family (what tests/helpers/ns_configs.py shrinks in Python), as command-line flags."""


def train_args(name: str, out, scene) -> list:
    """``[script, args...]`` of a 2-step CPU run of ``name`` (``SP_TRAIN`` or one of ours) under the default viewer."""
    if name == SP_TRAIN:
        script, method, flags = "sp-train", "nerfacto", NERFACTO_FLAGS
    elif name in SDF_METHODS:  # (sp-neus: an MLP of hidden-dim 32 takes at most 2 layers)
        script, method, flags = "ns-train", name, [*SDF_FLAGS, "--pipeline.model.sdf-field.num-layers", "2"]
    else:
        family = "relu-field" if "relu-field" in name else "nerf" if name != "sp-tensorf" else name
        script, method, flags = "ns-train", name, [*TINY_FLAGS[family], "--pipeline.model.eval-num-rays-per-chunk", "512"]
    parser, layout = ("sdfstudio-data", "sdfstudio") if name in SDF_METHODS else ("blender-data", "blender")
    return [script, method, *RUN_FLAGS, "--max-num-iterations", "2", "--steps-per-save", "2", "--output-dir", str(out),
            *flags, parser, "--data", str(scene / layout)]


@pytest.fixture(scope="module")
def checkpoints(tiny_scene, ns_server, tmp_path_factory):
    """``name -> config.yml`` of a 2-step run of each method here and of ``sp-train nerfacto`` under
    nerfstudio's default viewer, forked two at a time from the test fork server (which stops the data
    worker nerfacto's parallel data manager leaves when its command ends)."""
    folders = {name: tmp_path_factory.mktemp(name.replace(" ", "-")) for name in [SP_TRAIN, *OTHERS]}
    cases = []
    for name, folder in folders.items():
        script, *args = train_args(name, folder, tiny_scene)
        cases.append({"name": name, "script": script, "args": args, "timeout": 600})
    results = ns_server.run(cases, parallel=2)
    failed = [f"[{name}] rc {r['rc']}\n{r['stdout'][-1500:]}\n{r['stderr'][-3000:]}" for name, r in results.items() if r["rc"] != 0]
    assert not failed, "\n\n".join(failed)
    out = {}
    for name, result in results.items():
        assert PORT_LINE.search(result["stdout"]), f"{name} did not start nerfstudio's viewer:\n{result['stdout'][-2000:]}"
        (config,) = folders[name].glob("**/config.yml")
        assert list(config.parent.glob("nerfstudio_models/step-*.ckpt")), f"{name}: no checkpoint"
        out[name] = config
    return out


def test_every_method_keeps_its_learning_rates_python_floats():
    for name, spec in our_methods().items():
        for group, entry in spec.config.optimizers.items():
            scheduler = entry.get("scheduler")
            assert scheduler is None or isinstance(
                scheduler, (FloatCosineDecaySchedulerConfig, FloatExponentialDecaySchedulerConfig)
            ), f"{name}: optimizer group {group!r} uses {type(scheduler).__name__}, whose numpy learning rates ns-eval cannot load"


@pytest.fixture
def server(ns_server):
    """The session's fork server (tests/nerfstudio/conftest.py): ``ns-eval`` and ``sp-export-mesh`` run
    in processes forked from one import of them, not paying nerfstudio's imports per command."""
    return ns_server


def test_ns_eval_loads_every_method_checkpoint(checkpoints, server, tmp_path):
    """The real ``ns-eval`` script on one checkpoint; the others through the test fork server, which
    runs the same entry point in a forked process without paying nerfstudio's imports per method
    (they were most of this test's three minutes)."""
    outs = {name: tmp_path / name for name in OTHERS}  # (sp-train nerfacto's eval has no per-image lines of ours)
    first, *rest = OTHERS
    real = subprocess.Popen(ns_eval_args(checkpoints[first], outs[first]), env=ENV, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        results = server.run([{"name": name, "script": "ns-eval", "args": ns_eval_args(checkpoints[name], outs[name])[1:]}
                              for name in rest], parallel=2)
        out, err = real.communicate(timeout=900)
    finally:
        if real.poll() is None:
            real.kill()
    procs = {first: SimpleNamespace(returncode=real.returncode, stdout=out, stderr=err)}
    procs.update({name: SimpleNamespace(returncode=r["rc"], stdout=r["stdout"], stderr=r["stderr"]) for name, r in results.items()})
    assert sorted(procs) == OTHERS
    failed = [f"[{name}] rc {proc.returncode}\n{proc.stderr[-3000:]}" for name, proc in procs.items() if proc.returncode != 0]
    assert not failed, "\n\n".join(failed)
    for name, proc in procs.items():
        check_eval(proc, outs[name])


def test_ns_render_and_sp_export_mesh_on_an_sdf_checkpoint(checkpoints, server, tmp_path):
    """The real ``ns-render`` script; ``sp-export-mesh`` forked from the server meanwhile (the real
    script runs in the refusal test below)."""
    config = checkpoints["neuralangelo-lite"]
    render = [command("ns-render"), "dataset", "--load-config", str(config), "--split", "test",
              "--output-path", str(tmp_path / "renders"), "--rendered-output-names", "rgb", "--image-format", "png"]
    real = subprocess.Popen(render, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        mesh_proc = server.call([command("sp-export-mesh"), "--load-config", str(config), "--output-dir", str(tmp_path / "mesh"),
                                 "--resolution", "96"])
        out, err = real.communicate(timeout=900)
    finally:
        if real.poll() is None:
            real.kill()
    assert real.returncode == 0, _report(render, subprocess.CompletedProcess(render, real.returncode, out, err))
    assert list((tmp_path / "renders").glob("**/*.png"))
    mesh = trimesh.load(tmp_path / "mesh" / "mesh.ply")
    assert len(mesh.faces) > 0 and "96^3" in mesh_proc.stdout and np.isfinite(mesh.vertices).all()


def test_sp_export_mesh_refuses_a_density_field_in_one_line(checkpoints, tmp_path):
    proc = subprocess.run([sys.executable, "-m", "sp_plugins.cli.export_mesh", "--load-config", str(checkpoints["sp-tensorf"]),
                           "--output-dir", str(tmp_path / "mesh")], capture_output=True, text=True, timeout=600)
    refused(proc, "sp-export-mesh", "has no SDF field", others=True)


VIEWER_FAMILIES = {"SDF": "sp-neus", "radiance": "sp-mipnerf", "ReLU field": "sp-relu-field", "sp-train": SP_TRAIN}
"""A finished run of each method family that ``ns-viewer`` loads."""


def test_ns_viewer_serves_every_method_familys_finished_run(checkpoints, ns_server, tmp_path):
    """``ns-viewer --load-config`` (forked together from the test fork server; the browser test runs the
    real script) serves the viser client page on the port viser bound, one port each, and its websocket
    sends the viewer's controls (the render panel's "Output type"); then each is stopped. A frame of the
    model is the browser test's part."""
    import msgspec
    from websockets.sync.client import connect

    from tests.helpers.viewer import CLIENT_MARKER, forked_viewers

    commands = {family: [command("ns-viewer"), "--load-config", checkpoints[name]] for family, name in VIEWER_FAMILIES.items()}
    with forked_viewers(ns_server, commands, tmp_path) as viewers:
        for family, viewer in viewers.items():
            assert CLIENT_MARKER in viewer.page(), family
            labels = set()
            with connect(f"ws://127.0.0.1:{viewer.port}", open_timeout=30, max_size=None) as ws:
                while "Output type" not in labels:
                    labels |= {m.get("label") for m in msgspec.msgpack.decode(ws.recv(timeout=30))}
            assert viewer.proc.poll() is None, f"{family}: ns-viewer exited\n{viewer.output()[-3000:]}"
        assert len({viewer.port for viewer in viewers.values()}) == len(viewers)  # each picked its own port
