"""What decides a table row is checked by what the run did.

``nerfacto+sp`` and ``nerfacto+sp-off`` are built as ``nerfbaselines train`` builds them (the spec from
nerfbaselines' registry, its python backend, the tiny scene loaded and the presets applied), in this
process: the first model has SP on and attached to its fields and moves positions in its first step,
the second has SP off. Specs whose ``sp_off`` flags are swapped are refused when the model is built,
a ``--set`` against the id before, and the run's SP state is in the hparams nerfbaselines saves.
"""

from __future__ import annotations

import gc
from contextlib import contextmanager
from types import SimpleNamespace

import pytest

from sp_plugins.nerfbaselines import sp_state

BUDGET = {"machine.device_type": "cpu", "max_num_iterations": "3", "pipeline.datamanager.train_num_rays_per_batch": "32",
          "pipeline.model.num_nerf_samples_per_ray": "8", "pipeline.model.num_proposal_samples_per_ray": "8,8",
          "pipeline.model.log2_hashmap_size": "12", "pipeline.model.max_res": "64", "pipeline.model.hidden_dim": "16"}


@pytest.fixture(scope="module")
def blender(tmp_path_factory) -> str:
    from sp_plugins.data import make_tiny_scene

    return str(make_tiny_scene(tmp_path_factory.mktemp("sp-state") / "scene", mesh="sphere").root / "blender")


@contextmanager
def built(method_id: str, data: str, **overrides: str):
    """``method_id`` as ``nerfbaselines train`` builds it: the registry's spec, the python backend, the
    train split loaded, the presets for it applied, then our ``--set`` values (as strings)."""
    import nerfbaselines
    from nerfbaselines.datasets import load_dataset
    from nerfbaselines.training import get_presets_and_config_overrides

    spec = nerfbaselines.get_method_spec(method_id)
    with nerfbaselines.build_method_class(spec, "python") as cls:
        info = cls.get_method_info()
        dataset = load_dataset(data, split="train", features=info["required_features"],
                               supported_camera_models=info["supported_camera_models"])
        _, config_overrides = get_presets_and_config_overrides(spec, dataset["metadata"], config_overrides={**BUDGET, **overrides})
        method = cls(train_dataset=dataset, config_overrides=config_overrides)
        try:
            yield method
        finally:
            method.close()
            del method
            gc.collect()  # the model holds patches (registry.hold) while it exists


def attached(model) -> list:
    """Names of the model's fields whose seam holds the model's own preconditioner (read off the model)."""
    return [name for name, m in model.named_modules() if getattr(m, "sp_handle", None) is not None and m.sp_handle.sp is model.sp]


def test_sp_and_sp_off_build_what_their_ids_promise(blender):
    with built("nerfacto+sp", blender) as method:
        model = method._trainer.pipeline.model
        assert model.sp.config.enabled is True and attached(model), attached(model)
        assert method.train_iteration(0)["sp_alpha"] > 0  # the first step perturbs
        hparams = method.get_info()["hparams"]
        assert hparams["sp_run.enabled"] is True and hparams["sp_run.fields"] == ",".join(attached(model))
        assert hparams["sp_run.alpha0"] == pytest.approx(model.sp.config.alpha0)
    with built("nerfacto+sp-off", blender) as method:
        model = method._trainer.pipeline.model
        assert model.sp.config.enabled is False
        assert method.train_iteration(0)["sp_alpha"] == 0.0
        hparams = method.get_info()["hparams"]
        assert hparams["sp_run.enabled"] is False and "sp_run.alpha0" not in hparams


def test_swapped_spec_flags_are_refused_when_the_model_is_built(blender, monkeypatch):
    from sp_plugins.nerfbaselines import specs

    on, off = specs.ENTRIES["nerfacto+sp"], specs.ENTRIES["nerfacto+sp-off"]
    monkeypatch.setitem(specs.ENTRIES, "nerfacto+sp", off)
    monkeypatch.setitem(specs.ENTRIES, "nerfacto+sp-off", on)
    for method_id, said, got in (("nerfacto+sp", "on", "off"), ("nerfacto+sp-off", "off", "on")):
        with pytest.raises(sp_state.SPStateError) as err:
            with built(method_id, blender):
                pass
        message = str(err.value)
        assert "\n" not in message and message.startswith(f"{method_id} promises SP {said}, but the model it built has SP {got}")
        assert "specs.ENTRIES" in message


@pytest.mark.parametrize("method_id, value, twin", [("nerfacto+sp", "False", "nerfacto+sp-off"),
                                                     ("nerfacto+sp-off", "True", "nerfacto+sp")])
def test_a_set_against_the_id_is_one_line_naming_the_id_that_trains_so(blender, capsys, method_id, value, twin):
    with pytest.raises(SystemExit) as exit_:
        with built(method_id, blender, **{"pipeline.model.sp.enabled": value}):
            pass
    assert exit_.value.code == 2
    (line,) = [line for line in capsys.readouterr().err.splitlines() if "error" in line]
    assert f"--set pipeline.model.sp.enabled={value}: {method_id} trains with SP" in line and f"train {twin}" in line, line


def test_the_promise_is_read_from_the_id_not_the_spec_flags():
    on, off, no_sp = (SimpleNamespace(pipeline=SimpleNamespace(model=m)) for m in (
        SimpleNamespace(sp=SimpleNamespace(enabled=True)), SimpleNamespace(sp=SimpleNamespace(enabled=False)), SimpleNamespace()))
    assert sp_state.promised("nerfacto+sp", off) is True and sp_state.promised("mipnerf+sp-off", on) is False
    # a plain id trains as its config says (sp-nerfacto with --set pipeline.model.sp.enabled=False is a baseline)
    assert sp_state.promised("sp-nerfacto", on) is True and sp_state.promised("sp-nerfacto", off) is False
    assert sp_state.promised("mipnerf", no_sp) is False
    assert sp_state.twin("vanilla-nerf+sp") == "vanilla-nerf+sp-off" and sp_state.twin("vanilla-nerf+sp-off") == "vanilla-nerf+sp"
    sp_state.check("sp-nerfacto", True, {"enabled": True, "alpha0": 0.02, "fields": ["field"]})
    with pytest.raises(sp_state.SPStateError, match="promises SP on, but SP is attached to no field"):
        sp_state.check("nerfacto+sp", True, {"enabled": True, "alpha0": 0.02, "fields": []})


# -- the run record, exactly (a model of our own: no nerfbaselines needed) ------------------------------
def _model(enabled=True, alpha0=0.01, relative=True, attach=("a",)):
    import torch

    from sp_plugins.adapter.field import SPFieldMixin
    from sp_plugins.core import SPConfig

    class Field(SPFieldMixin, torch.nn.Module):
        pass

    model = torch.nn.Module()
    model.sp = SPConfig(enabled=enabled, alpha0=alpha0, relative_to_diagonal=relative).setup(
        scene_diagonal=4.0 if relative else None, bounds=(-1.0, 1.0))
    for name in ("a", "b"):
        field = Field()
        if name in attach:
            field.use_preconditioner(model.sp)
        setattr(model, name, field)
    return model


def test_the_model_state_names_alpha0_in_scene_units_and_the_attached_fields():
    assert sp_state.model_state(_model()) == {"enabled": True, "alpha0": 0.04, "fields": ["a"]}  # 0.01 of a diagonal of 4
    assert sp_state.model_state(_model(relative=False, attach=("a", "b"))) == {"enabled": True, "alpha0": 0.01, "fields": ["a", "b"]}
    assert sp_state.model_state(_model(enabled=False)) == {"enabled": False, "alpha0": None, "fields": ["a"]}
    import torch

    assert sp_state.model_state(torch.nn.Linear(2, 2)) == {"enabled": False, "alpha0": None, "fields": []}


def test_the_run_record_as_hparams():
    assert sp_state.as_hparams({"enabled": True, "alpha0": 0.04, "fields": ["a", "b"]}) == {
        "sp_run.enabled": True, "sp_run.fields": "a,b", "sp_run.alpha0": 0.04}
    assert sp_state.as_hparams({"enabled": False, "alpha0": None, "fields": []}) == {"sp_run.enabled": False, "sp_run.fields": ""}


def test_a_broken_promise_is_one_line_naming_the_id_and_what_the_model_does():
    with pytest.raises(sp_state.SPStateError) as on:
        sp_state.check("nerfacto+sp", True, {"enabled": False, "alpha0": None, "fields": []})
    assert str(on.value) == ("nerfacto+sp promises SP on, but the model it built has SP off: its spec "
                             "(sp_plugins.nerfbaselines.specs.ENTRIES) builds another run than its id names; its results would "
                             "fill the wrong table row")
    with pytest.raises(sp_state.SPStateError, match=r"^mipnerf\+sp-off promises SP off, but the model it built has SP on: "):
        sp_state.check("mipnerf+sp-off", False, {"enabled": True, "alpha0": 0.04, "fields": ["a"]})
    sp_state.check("mipnerf+sp-off", False, {"enabled": False, "alpha0": None, "fields": ["a"]})  # off: the inert seam may stay
