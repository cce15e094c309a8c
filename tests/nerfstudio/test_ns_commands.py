"""Every registered method's checkpoint loads in the real ``ns-eval`` (subprocesses), as written by
nerfstudio's trainer on the tiny synthetic scene; ``ns-render`` and the mesh export for one SDF
method. (sp-nerfacto and sp-neus-hashgrid run the whole command line, ``ns-train`` included, on
a real capture in test_real_capture.py.)

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
from tests.helpers.ns_commands import ENV, _report, check_eval, command, ns_eval_args
from tests.helpers.ns_configs import SDF_METHODS, tiny_sdf_config, run_recording
from tests.helpers.ns_configs import tiny_radiance_config

from sp_plugins.nerfstudio.runs import our_methods
from sp_plugins.nerfstudio.components.schedulers import FloatCosineDecaySchedulerConfig, FloatExponentialDecaySchedulerConfig

ON_THE_FOX = ("sp-nerfacto", "sp-neus-hashgrid")
OTHERS = sorted(set(our_methods()) - set(ON_THE_FOX))


@pytest.fixture(scope="module")
def checkpoints(tiny_scene, tmp_path_factory):
    """``name -> config.yml`` of a 2-step run of each method (the real trainer, in this process)."""
    out = {}
    for name in OTHERS:
        folder = tmp_path_factory.mktemp(name)
        if name in SDF_METHODS:
            config = tiny_sdf_config(name, tiny_scene, folder, steps=2)
            for group in config.optimizers.values():
                if group["scheduler"] is not None:
                    group["scheduler"].warm_up_end = 1
        else:
            config = tiny_radiance_config(name, tiny_scene, folder, steps=2)
        run_recording(config)
        out[name] = config.get_base_dir() / "config.yml"
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
    outs = {name: tmp_path / name for name in checkpoints}
    first, *rest = sorted(checkpoints)
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
    assert sorted(procs) == sorted(checkpoints)
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
