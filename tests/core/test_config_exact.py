"""SP's one configuration (sp_plugins.core.config), exactly: every default as the README's table of SP
settings documents it, and each validation bound at its edge with its one-line message, so a flag typed on
any method is refused the same way when the config is made. The mutants each test kills are listed in
``bench/results/mutation_study/kills.json``."""

from __future__ import annotations

import dataclasses

import pytest

from sp_plugins.core import SPConfig, StochasticPreconditioner
from sp_plugins.core.settings import SPSettings

NAN, INF = float("nan"), float("inf")


def test_the_defaults():
    """Each setting of ``SPConfig`` has its documented default (SP on, alpha0 0.01 on an exponential schedule with
    final ratio 1e-3 ending at 0.2 of training, Gaussian noise reflected at the box, one sample, no grid), and
    the settings come first (``enabled``, ``alpha0``), ``_target`` last (``SPConfig`` adds it to ``SPSettings``)."""
    c = SPConfig()
    assert c._target is StochasticPreconditioner
    assert (c.enabled, c.alpha0, c.relative_to_diagonal, c.schedule, c.end, c.final_ratio) == (True, 0.01, False, "exponential", 0.2, 1e-3)
    assert (c.noise, c.boundary, c.num_samples, c.alpha_grid, c.alpha_grid_mode) == ("gaussian", "reflect", 1, False, "replace")
    assert (c.alpha_grid_resolution, c.alpha_grid_init, c.alpha_grid_lr, c.alpha_grid_parameterization, c.seed) == (32, None, 1e-3, "log", None)
    names = [f.name for f in dataclasses.fields(SPConfig)]
    assert names[:2] == ["enabled", "alpha0"] and names[-1] == "_target"
    assert names[:-1] == [f.name for f in dataclasses.fields(SPSettings)]


@pytest.mark.parametrize("name, accepted, refused, message", [
    ("alpha0", [0.0, 1e-9, 5.0], [-1e-9, NAN, INF], "alpha0={!r}: must be a finite number >= 0"),
    ("end", [1e-9, 1.0, 5000.0], [0.0, -0.5, NAN, INF], "end={!r}: give a fraction of training in (0, 1] or an absolute end step > 1"),
    ("final_ratio", [1e-12, 0.5, 0.999], [0.0, 1.0, -0.1, 2.0, NAN], "final_ratio={!r}: must lie in (0, 1)"),
    ("num_samples", [1, 2, 16], [0, -1], "num_samples={}: must be >= 1"),
    ("alpha_grid_init", [None, 1e-9, 0.5], [0.0, -0.1, NAN, INF], "alpha_grid_init={!r}: must be a finite number > 0"),
    ("alpha_grid_lr", [0.0, 1e-3], [-1e-9, NAN, INF], "alpha_grid_lr={!r}: must be a finite number >= 0"),
    ("alpha_grid_resolution", [2, 3, 128], [1, 0, -4], "alpha_grid_resolution={}: must be >= 2"),
])
def test_each_bound_at_its_edge(name, accepted, refused, message):
    """Each numeric setting accepts the values at its edge and refuses those just past it, in its one line."""
    for value in accepted:
        assert getattr(SPConfig(**{name: value}), name) == value or value is None
    for value in refused:
        with pytest.raises(ValueError) as err:
            SPConfig(**{name: value})
        expected = message.format(value)
        assert str(err.value) == expected, (str(err.value), expected)


@pytest.mark.parametrize("name, value, message", [
    ("schedule", "cosine", "schedule='cosine' is not a schedule; allowed values: constant, step, exponential, linear"),
    ("alpha_grid_mode", "multiply", "alpha_grid_mode='multiply': allowed values: replace, scaled"),
    ("noise", "cauchy", "noise='cauchy' is not a noise kind"),
    ("boundary", "wrap", "boundary='wrap'"),
    ("alpha_grid_parameterization", "exp", "alpha_grid_parameterization='exp'"),
])
def test_each_named_choice_is_checked(name, value, message):
    """Each named choice outside its list is refused in its one line."""
    with pytest.raises(ValueError, match=f"^{message}".replace("(", r"\(").replace(")", r"\)")):
        SPConfig(**{name: value})


def test_validation_runs_when_the_config_is_made_and_again_on_demand():
    """A bad value is refused when the config is made, and one set afterwards by ``validate()``."""
    config = SPConfig()
    config.alpha0 = -1.0  # set after construction (a config file): validate() still finds it
    with pytest.raises(ValueError, match=r"^alpha0=-1\.0"):
        config.validate()


def test_setup_builds_the_target_with_the_config_and_the_keywords():
    sp = SPConfig(alpha0=0.25, boundary="none").setup(dim=2)
    assert type(sp) is StochasticPreconditioner and sp.config.alpha0 == 0.25
