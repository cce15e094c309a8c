"""Our sdfstudio methods: found through our entry-point group, added to ns-train's union, and
equal to sdfstudio's own method configs except for the SP classes and settings."""

from __future__ import annotations

import dataclasses
import math

import pytest



pytestmark = pytest.mark.usefixtures("patched")

BASES = {"neus": (0.013, 0.2), "neus-facto": (0.013, 0.2), "neuralangelo": (0.03, 0.3), "bakedangelo": (0.03, 0.3)}
SP_ONLY = {"_target", "sp", "sdf_field", "enable_progressive_hash_encoding", "enable_numerical_gradients_schedule"}


def test_entry_point_group_lists_the_four_methods():
    from sp_plugins.sdfstudio.registration import discover

    assert sorted(discover()) == sorted(f"sp-{base}" for base in BASES)


@pytest.mark.parametrize("base", sorted(BASES))
def test_sp_config_is_the_host_config_plus_sp(base):
    import nerfstudio.configs.method_configs as host

    ours, theirs = host.method_configs[f"sp-{base}"], host.method_configs[base]
    assert ours.trainer == theirs.trainer and ours.pipeline.datamanager == theirs.pipeline.datamanager
    assert set(theirs.optimizers) <= set(ours.optimizers) and "sp_alpha_grid" in ours.optimizers
    model, host_model = ours.pipeline.model, theirs.pipeline.model
    assert isinstance(model, type(host_model)) and type(model) is not type(host_model)
    for f in dataclasses.fields(host_model):
        if f.name not in SP_ONLY:
            assert getattr(model, f.name) == getattr(host_model, f.name), f.name
    for f in dataclasses.fields(host_model.sdf_field):
        if f.name not in ("_target",):
            assert getattr(model.sdf_field, f.name) == getattr(host_model.sdf_field, f.name), f.name
    alpha0, end = BASES[base]
    assert (model.sp.enabled, model.sp.alpha0, model.sp.end, model.sp.schedule) == (True, alpha0, end, "exponential")


@pytest.mark.parametrize("base, fd", [("neuralangelo", 2.0), ("bakedangelo", 1.0)])
def test_sp_replaces_neuralangelo_coarse_to_fine(base, fd):
    import nerfstudio.configs.method_configs as host

    model, host_model = host.method_configs[f"sp-{base}"].pipeline.model, host.method_configs[base].pipeline.model
    assert host_model.enable_progressive_hash_encoding and host_model.enable_numerical_gradients_schedule
    assert not model.enable_progressive_hash_encoding and not model.enable_numerical_gradients_schedule
    assert math.isclose(model.sdf_field.fd_step, fd / host_model.sdf_field.max_res)
    assert model.sp.alpha_grid_init == 0.03 and model.sp.alpha_grid_lr == 1e-3


@pytest.mark.parametrize("base", sorted(BASES))
def test_the_named_methods_are_the_generic_conversion(base):
    """One mechanism: sp-neus ... sp-bakedangelo (entry points, fixed names and presets) are what
    the generic route makes of sdfstudio's config (only the description is their own)."""
    import nerfstudio.configs.method_configs as host

    from sp_plugins.sdfstudio.registration import discover
    from sp_plugins.sdfstudio.sdf_methods import with_sp

    named = discover()[f"sp-{base}"]
    assert named.config == with_sp(host.method_configs[base]).config
    assert host.method_configs[f"sp-{base}"] is named.config


def test_a_schedule_that_does_not_fit_is_one_clear_line(sdf_scene, tmp_path):
    import subprocess

    from sdf_tiny import BIN, env, train_args

    args = train_args("sp-neus-facto", "neus-facto", sdf_scene, tmp_path, 3, "--pipeline.model.sp.end", "50")
    proc = subprocess.run([str(BIN / "sp-sdfstudio-train"), *map(str, args)], env=env(), capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2, proc.stderr[-1000:]
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("sp-sdfstudio-train: error: --pipeline.model.sp.end 50 does not fit --trainer.max-num-iterations 3")
    assert "Traceback" not in proc.stderr


def test_the_sdfstudio_adapter_never_loads_the_nerfstudio_adapter():
    import sys

    import sp_plugins.sdfstudio.cli  # noqa: F401
    import sp_plugins.sdfstudio.neus  # noqa: F401

    assert not any(name.startswith("sp_plugins.nerfstudio") for name in sys.modules)
