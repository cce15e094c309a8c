"""Our sdfstudio methods: found through our entry-point group, added to ns-train's union, and
equal to sdfstudio's own method configs except for the SP classes and settings."""

from __future__ import annotations

import copy
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
    from sp_plugins.sdfstudio.registration import with_sp

    named = discover()[f"sp-{base}"]
    assert named.config == with_sp(host.method_configs[base]).config
    assert host.method_configs[f"sp-{base}"] is named.config


def test_with_sp_on_a_method_that_is_ours_switches_sp_on():
    """As nerfstudio's ``with_sp``: ours comes back with SP enabled, an explicit ``sp`` wins, the
    name, classes and alpha-grid optimizer entry follow."""
    import nerfstudio.configs.method_configs as host

    from sp_plugins.adapter import presets
    from sp_plugins.sdfstudio.registration import MethodSpecification, discover, with_sp

    named = discover()["sp-neus"]
    config = copy.deepcopy(named.config)
    config.pipeline.model.sp = dataclasses.replace(config.pipeline.model.sp, enabled=False, alpha0=0.02)
    off = MethodSpecification(config=config, description=named.description)
    on = with_sp(off)
    assert on.config.method_name == "sp-neus" and on.description == named.description
    assert type(on.config.pipeline.model) is type(named.config.pipeline.model)
    assert on.config.pipeline.model.sp == dataclasses.replace(off.config.pipeline.model.sp, enabled=True)
    assert not off.config.pipeline.model.sp.enabled  # the argument is not modified
    mine = dataclasses.replace(presets.NEURALANGELO, alpha_grid=True, alpha_grid_lr=0.5)
    explicit = with_sp(host.method_configs["sp-neus"], mine, name="sp-neus-grid")
    assert explicit.config.pipeline.model.sp == mine and explicit.config.method_name == "sp-neus-grid"
    assert explicit.config.optimizers["sp_alpha_grid"]["optimizer"].lr == 0.5


def test_with_sp_refuses_in_one_line_naming_the_method_and_why():
    import nerfstudio.configs.method_configs as host

    from sp_plugins.sdfstudio.registration import refusal, with_sp
    from sp_plugins.sdfstudio.table import REFUSED_MODELS

    assert all(path.count(".") >= 2 and reason for path, reason in REFUSED_MODELS.items())  # class path -> reason
    for method in ("dto", "nerfacto"):
        reason = refusal(host.method_configs[method])
        assert reason
        with pytest.raises(ValueError) as err:
            with_sp(host.method_configs[method])
        assert str(err.value) == f"SP cannot be put on {method}: {reason}"
    assert refusal(host.method_configs["dto"]) == REFUSED_MODELS["nerfstudio.models.dto.DtoOModel"]
    assert refusal(host.method_configs["neus"]) is None and refusal(host.method_configs["sp-neus"]) is None


def test_both_hosts_have_the_same_adapter_names():
    """The adapter shape (ARCHITECTURE.md): a reader of one host's adapter finds the other's by the
    same module and function names (read from the sources: the two hosts never share a process)."""
    import ast
    from pathlib import Path

    import sp_plugins

    root = Path(sp_plugins.__file__).parent

    def names(host: str, module: str) -> set:
        tree = ast.parse((root / host / f"{module}.py").read_text())
        found = {n.name for n in tree.body if isinstance(n, (ast.FunctionDef, ast.ClassDef))}
        for n in tree.body:
            targets = n.targets if isinstance(n, ast.Assign) else [n.target] if isinstance(n, ast.AnnAssign) else []
            found |= {t.id for t in targets if isinstance(t, ast.Name)}
        return found

    for host in ("nerfstudio", "sdfstudio"):
        assert {"with_sp", "sp_methods"} <= names(host, "registration"), host
        # the method knowledge, rules included, is the table's; registration only re-exports it
        assert {"refusal", "preset_for", "REFUSED_MODELS"} <= names(host, "table"), host
        assert not {"refusal", "preset_for", "REFUSED_MODELS"} & names(host, "registration"), host
        assert "HOST" in names(host, "host"), host
        assert "SPModel" in names(host, "model") and (root / host / "seam.py").is_file(), host
    assert not (root / "sdfstudio" / "sdf_field.py").exists()


def test_a_schedule_that_does_not_fit_is_one_clear_line(sdf_scene, tmp_path):
    from tests.helpers.errors import refused
    from tests.helpers.sdf_configs import run, train_args

    args = train_args("sp-neus-facto", "neus-facto", sdf_scene, tmp_path, 3, "--pipeline.model.sp.end", "50")
    proc = run(["sp-sdfstudio-train", *args], cwd=tmp_path, expect=2)
    last = refused(proc, "sp-sdfstudio-train", others=True)
    assert last.startswith("sp-sdfstudio-train: error: --pipeline.model.sp.end 50 does not fit --trainer.max-num-iterations 3")


def test_the_sdfstudio_adapter_never_loads_the_nerfstudio_adapter():
    """In a fresh interpreter: this process's other tests (benchmarks, helpers) may have loaded it."""
    import subprocess
    import sys

    from tests.helpers.sdf_configs import env

    code = ("import sys, sp_plugins.sdfstudio.cli, sp_plugins.sdfstudio.registration, sp_plugins.adapter.shrink; "
            "print(sorted(n for n in sys.modules if n.startswith('sp_plugins.')))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env())
    assert proc.returncode == 0, proc.stderr[-2000:]
    loaded = eval(proc.stdout.strip().splitlines()[-1])
    assert "sp_plugins.sdfstudio.cli" in loaded and "sp_plugins.sdfstudio.registration" in loaded
    assert not [name for name in loaded if name.startswith("sp_plugins.nerfstudio")], loaded
