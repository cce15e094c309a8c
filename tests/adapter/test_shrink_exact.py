"""Shrinking a trainer config to a CPU size (sp_plugins.adapter.shrink), exactly, on stand-in configs of
both hosts' shape: which object each setting lands on, the SDF methods' ``sdf_field``, learning rates and
scheduler settings per group, and a misspelt setting or group refused naming it."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from sp_plugins.adapter.shrink import shrink


def config(sdf: bool):
    field = SimpleNamespace(hidden_dim=256, max_res=2048)
    model = SimpleNamespace(num_samples=64, **({"sdf_field": field} if sdf else {"field": field}))
    scheduler = SimpleNamespace(warm_up_end=500, max_steps=300000)
    optimizers = {"fields": {"optimizer": SimpleNamespace(lr=1e-3), "scheduler": scheduler},
                  "field_grid": {"optimizer": SimpleNamespace(lr=1e-2), "scheduler": SimpleNamespace(warm_up_end=500, max_steps=300000)}}
    return SimpleNamespace(pipeline=SimpleNamespace(model=model), optimizers=optimizers)


@pytest.mark.parametrize("sdf", [False, True])
def test_each_setting_lands_where_it_belongs(sdf):
    """Each setting passed by name lands on its place in the config; an optimizer group not named keeps its
    settings."""
    c = config(sdf)
    assert shrink(config=c, num_samples=16, field=dict(hidden_dim=32, max_res=64), lr={"fields": 5e-3}, warm_up_end=10, max_steps=200) is c
    m = c.pipeline.model
    f = m.sdf_field if sdf else m.field
    assert m.num_samples == 16 and (f.hidden_dim, f.max_res) == (32, 64)
    fields, grid = c.optimizers["fields"], c.optimizers["field_grid"]
    assert fields["optimizer"].lr == 5e-3 and (fields["scheduler"].warm_up_end, fields["scheduler"].max_steps) == (10, 200)
    assert grid["optimizer"].lr == 1e-2 and (grid["scheduler"].warm_up_end, grid["scheduler"].max_steps) == (500, 300000)  # not named


def test_scheduler_settings_left_out_are_left_alone():
    c = config(False)
    shrink(c, lr={"fields": 5e-3}, max_steps=200)
    assert (c.optimizers["fields"]["scheduler"].warm_up_end, c.optimizers["fields"]["scheduler"].max_steps) == (500, 200)
    c = config(False)
    shrink(c, lr={"fields": 5e-3})
    assert (c.optimizers["fields"]["scheduler"].warm_up_end, c.optimizers["fields"]["scheduler"].max_steps) == (500, 300000)
    c.optimizers["fields"]["scheduler"] = None  # a group without a scheduler: only its lr
    shrink(c, lr={"fields": 1e-4})
    assert c.optimizers["fields"]["optimizer"].lr == 1e-4


def test_a_misspelt_setting_or_group_is_refused_naming_it():
    with pytest.raises(AttributeError, match=r"^pipeline\.model has no setting 'num_sample' \(SimpleNamespace\)$"):
        shrink(config(False), num_sample=16)
    with pytest.raises(AttributeError, match=r"^pipeline\.model\.sdf_field has no setting 'hidden' "):
        shrink(config(True), field=dict(hidden=32))
    with pytest.raises(KeyError, match=r"no optimizer group 'proposal'; the config has fields, field_grid"):
        shrink(config(False), lr={"proposal": 1e-3})
    with pytest.raises(AttributeError, match=r"^optimizers\['fields'\]\.scheduler has no setting 'max_steps' "):
        c = config(False)
        c.optimizers["fields"]["scheduler"] = SimpleNamespace(warm_up_end=1)
        shrink(c, lr={"fields": 1e-3}, max_steps=5)
    c = config(False)
    shrink(c, field={})  # nothing to set: the field is not looked up
    assert c.pipeline.model.field.hidden_dim == 256
