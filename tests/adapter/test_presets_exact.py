"""The paper's SP settings per method family (sp_plugins.adapter.presets), exactly as their docstrings state
them (Ling et al. 2025's values; the position-field default is ours). ``tests/test_defaults_table.py`` checks
the README's table against the same presets; this pins the presets themselves, the alpha-grid variant's
settings included (``bench/mutation_study.py sp_plugins/adapter/presets.py``: ``alpha_grid_init`` 0.03 ->
1.03 and ``alpha_grid_lr`` 1e-3 -> 1.001 survived the table's test)."""

from __future__ import annotations

import pytest

from sp_plugins.adapter import presets


@pytest.mark.parametrize("name, alpha0, end, boundary", [
    ("NEUS", 0.013, 0.2, "reflect"),
    ("NEURALANGELO", 0.03, 0.3, "reflect"),
    ("MIPNERF", 0.04, 1 / 3, "none"),
    ("RELU_FIELD", 0.003, 8000 / 28000, "reflect"),
    ("POSITION_FIELD", 0.02, 0.2, "none"),
])
def test_each_family_anneals_its_alpha0_exponentially_to_0_by_its_end(name, alpha0, end, boundary):
    sp = getattr(presets, name)
    assert (sp.alpha0, sp.end, sp.schedule, sp.boundary, sp.enabled) == (alpha0, pytest.approx(end, rel=1e-12), "exponential",
                                                                         boundary, True)


def test_neuralangelos_alpha_grid_variant_starts_at_003_with_lr_1e3_in_place_of_the_scalar():
    """The paper's adaptive variant: a grid initialised to alpha0, Adam lr 1e-3 on log-alpha, replacing (not
    scaling) the annealed scalar."""
    sp = presets.NEURALANGELO
    assert (sp.alpha_grid_init, sp.alpha_grid_lr, sp.alpha_grid_mode, sp.alpha_grid_parameterization) == (0.03, 1e-3, "replace", "log")
    assert sp.alpha_grid_init == sp.alpha0


def test_relu_fields_run_28000_steps_and_the_default_is_the_position_field_preset():
    assert presets.RELU_FIELD_STEPS == 28_000 and presets.DEFAULT is presets.POSITION_FIELD
