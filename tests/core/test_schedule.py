import math

import pytest

from sp_plugins import AlphaSchedule


def test_step_schedule_is_alpha0_then_exactly_zero():
    s = AlphaSchedule("step", 0.02, end_step=100)
    assert s(0) == 0.02 and s(50) == 0.02 and s(99) == 0.02
    assert s(100) == 0.0 and s(10_000) == 0.0


def test_exponential_schedule_decays_geometrically_to_exactly_zero():
    s = AlphaSchedule("exponential", 0.013, end_step=1000, final_ratio=1e-3)
    assert s(0) == pytest.approx(0.013)
    # midway: about sqrt(1e-3) of alpha0, shifted
    expected_mid = 0.013 * (math.sqrt(1e-3) - 1e-3) / (1 - 1e-3)
    assert s(500) == pytest.approx(expected_mid, rel=1e-9)
    assert 0.0 < s(999) < 0.013 * 1e-4
    assert s(1000) == 0.0
    values = [s(t) for t in range(0, 1001, 50)]
    assert all(a > b for a, b in zip(values, values[1:]))
    # geometric: equal steps early on shrink alpha by a near-constant factor
    assert s(100) / s(0) == pytest.approx(s(200) / s(100), rel=0.01)


def test_linear_and_constant():
    lin = AlphaSchedule("linear", 0.04, end_step=200)
    assert lin(0) == 0.04 and lin(100) == pytest.approx(0.02) and lin(200) == 0.0
    const = AlphaSchedule("constant", 0.03)
    assert const(0) == const(10**7) == 0.03


def test_resolve_fraction_of_training_and_diagonal():
    s = AlphaSchedule.resolve("exponential", 0.01, end=0.2, total_steps=5000, scene_diagonal=2 * math.sqrt(3))
    assert s.end_step == 1000
    assert s.alpha0 == pytest.approx(0.02 * math.sqrt(3))
    assert AlphaSchedule.resolve("step", 0.02, end=2000, total_steps=100_000).end_step == 2000
    assert AlphaSchedule.resolve("step", 0.02, end=1.0, total_steps=300).end_step == 299


@pytest.mark.parametrize(
    "kwargs, word",
    [
        (dict(kind="step", alpha0=0.1, end=2000, total_steps=1000), "after the end of training"),
        (dict(kind="step", alpha0=-0.1, end=0.5, total_steps=1000), "alpha0"),
        (dict(kind="step", alpha0=float("nan"), end=0.5, total_steps=1000), "alpha0"),
        (dict(kind="cosine", alpha0=0.1, end=0.5, total_steps=1000), "schedule"),
        (dict(kind="step", alpha0=0.1, end=0.5, total_steps=None), "total_steps"),
        (dict(kind="step", alpha0=0.1, end=-3, total_steps=1000), "end"),
        (dict(kind="step", alpha0=0.1, end=12.5, total_steps=1000), "whole number"),
        (dict(kind="step", alpha0=0.1, end=0.5, total_steps=1000, scene_diagonal=0.0), "scene_diagonal"),
    ],
)
def test_bad_schedules_raise_value_errors(kwargs, word):
    kind = kwargs.pop("kind")
    alpha0 = kwargs.pop("alpha0")
    with pytest.raises(ValueError, match=word):
        AlphaSchedule.resolve(kind, alpha0, **kwargs)


@pytest.mark.parametrize("kind", ["step", "exponential", "linear"])
@pytest.mark.parametrize("total", [2, 7, 300, 100_000])
def test_end_of_training_reaches_exactly_zero_at_the_last_step(kind, total):
    """Steps run 0 .. total - 1: ``end=1.0`` (and an absolute end at the total) must switch SP off
    at the last step, so the last update trains the plain field (defect 3)."""
    for end in (1.0, total) if total > 1 else (1.0,):
        s = AlphaSchedule.resolve(kind, 0.1, end=end, total_steps=total)
        assert s.end_step == total - 1
        assert s(total - 1) == 0.0 and s(total) == 0.0 and s(10 * total) == 0.0
        assert s(0) == pytest.approx(0.1) and s(total - 2) > 0.0


def test_other_fractions_end_where_they_did():
    assert AlphaSchedule.resolve("step", 0.1, end=0.2, total_steps=5000).end_step == 1000
    assert AlphaSchedule.resolve("step", 0.1, end=0.5, total_steps=200).end_step == 100
    assert AlphaSchedule.resolve("step", 0.1, end=1 / 3, total_steps=7500).end_step == 2500
    assert AlphaSchedule.resolve("step", 0.1, end=0.999, total_steps=100).end_step == 99  # capped at the last step
    assert AlphaSchedule.resolve("linear", 0.1, end=2000, total_steps=100_000).end_step == 2000
