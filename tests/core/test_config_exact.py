"""SP's one configuration (sp_plugins.core.config), exactly: every default as the README's table of SP
settings documents it, and each validation bound at its edge with its one-line message, so a flag typed on
any method is refused the same way when the config is made. Each test names the mutants it kills
(``bench/mutation_study.py`` ``sp_plugins/core/config.py``)."""

from __future__ import annotations

import dataclasses

import pytest

from sp_plugins.core import SPConfig, StochasticPreconditioner

NAN, INF = float("nan"), float("inf")


def test_the_defaults():
    """Kills: every default's literal changed (+1 / -1 / flipped)."""
    c = SPConfig()
    assert c._target is StochasticPreconditioner
    assert (c.enabled, c.alpha0, c.relative_to_diagonal, c.schedule, c.end, c.final_ratio) == (True, 0.01, False, "exponential", 0.2, 1e-3)
    assert (c.noise, c.boundary, c.num_samples, c.alpha_grid, c.alpha_grid_mode) == ("gaussian", "reflect", 1, False, "replace")
    assert (c.alpha_grid_resolution, c.alpha_grid_init, c.alpha_grid_lr, c.alpha_grid_parameterization, c.seed) == (32, None, 1e-3, "log", None)
    assert [f.name for f in dataclasses.fields(SPConfig)][:3] == ["_target", "enabled", "alpha0"]


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
    """Kills: each comparison moved across its edge (``>=`` -> ``>``, ``< 1`` -> ``<= 1``, ``< 2`` -> ``<= 2`` ...),
    ``isfinite and`` -> ``or``, the ``is not None`` guard, a check dropped."""
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
    """Kills: ``not in`` -> ``in`` for the schedule and the grid mode, a kind's check dropped."""
    with pytest.raises(ValueError, match=f"^{message}".replace("(", r"\(").replace(")", r"\)")):
        SPConfig(**{name: value})


def test_validation_runs_when_the_config_is_made_and_again_on_demand():
    """Kills: ``__post_init__`` not validating (a bad flag accepted until the schedule is built, mid-setup)."""
    config = SPConfig()
    config.alpha0 = -1.0  # set after construction (a config file): validate() still finds it
    with pytest.raises(ValueError, match=r"^alpha0=-1\.0"):
        config.validate()


def test_setup_builds_the_target_with_the_config_and_the_keywords():
    sp = SPConfig(alpha0=0.25, boundary="none").setup(dim=2)
    assert type(sp) is StochasticPreconditioner and sp.config.alpha0 == 0.25
