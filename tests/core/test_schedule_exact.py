"""The alpha schedule (sp_plugins.core.schedule), exactly: its defaults, each bound of ``__post_init__`` and
``resolve`` at its edge with its one line, and kinds named by parsed strings. The mutants each test kills are listed in
``bench/results/mutation_study/kills.json``."""

import dataclasses
import math

import pytest

from sp_plugins.core.schedule import AlphaSchedule


def parsed(word: str) -> str:
    """An equal string that is not the literal (as tyro hands over a flag's value)."""
    return "".join(list(word))


def test_the_defaults_are_the_papers_exponential_from_alpha0_one_percent():
    """The defaults are the paper's: exponential from alpha0 0.01 with a final ratio of 1e-3, zero at the end."""
    s = AlphaSchedule(end_step=10)
    assert (s.kind, s.alpha0, s.end_step, s.final_ratio) == ("exponential", 0.01, 10, 1e-3)
    assert s(0) == pytest.approx(0.01, rel=1e-12) and s(10) == 0.0


@pytest.mark.parametrize("kind", ["constant", "step", "exponential", "linear"])
def test_a_kind_named_by_a_parsed_string_gives_the_literals_values(kind):
    """A kind named by a parsed (equal, not identical) string gives the literal's values."""
    literal, parsed_kind = AlphaSchedule(kind, 0.5, 8), AlphaSchedule(parsed(kind), 0.5, 8)
    values = [literal(t) for t in range(10)]
    assert [parsed_kind(t) for t in range(10)] == values
    assert values[4] == {"constant": 0.5, "step": 0.5, "linear": 0.25, "exponential": 0.5 * (1e-3 ** 0.5 - 1e-3) / (1 - 1e-3)}[kind]


@pytest.mark.parametrize("kwargs, message", [
    (dict(kind="linear", end_step=0), "end_step=0: schedule 'linear' needs an end step >= 1"),
    (dict(kind="step", end_step=None), "end_step=None: schedule 'step' needs an end step >= 1"),
    (dict(kind="exponential", end_step=5, final_ratio=0.0), "final_ratio=0.0: must lie in (0, 1)"),
    (dict(kind="exponential", end_step=5, final_ratio=-0.5), "final_ratio=-0.5: must lie in (0, 1)"),
    (dict(kind="exponential", end_step=5, final_ratio=1.0), "final_ratio=1.0: must lie in (0, 1)"),
])
def test_each_bound_is_refused_at_its_edge_in_one_line(kwargs, message):
    """The first refused value gives its line; the edge beside it is accepted (end step 1, a final ratio just
    above 0, a constant schedule without an end)."""
    with pytest.raises(ValueError) as e:
        AlphaSchedule(alpha0=0.1, **kwargs)
    assert str(e.value) == message
    assert AlphaSchedule("linear", 0.1, 1)(0) == 0.1
    assert AlphaSchedule("exponential", 0.1, 5, final_ratio=1e-300)(0) == 0.1
    assert AlphaSchedule("constant", 0.1, None)(10**6) == 0.1


@pytest.mark.parametrize("end", [None, math.nan, 0.0, -1.0])
def test_resolve_refuses_a_missing_or_non_positive_end_in_one_line(end):
    """None and NaN get the line too (not a TypeError from ``None <= 0`` or int(NaN)'s message)."""
    with pytest.raises(ValueError) as e:
        AlphaSchedule.resolve("exponential", 0.01, end=end, total_steps=100)
    assert str(e.value) == f"end={end!r}: give a fraction of training in (0, 1] or an absolute end step > 1"


def test_resolve_ends_fractions_and_steps_and_refuses_a_bad_diagonal_or_kind():
    """Fractions 0.5 / 1.0 of 10 steps end at 5 / 9 (the last step), a tiny one at step 1; the kind and alpha0 by
    keyword; a constant schedule named by a parsed string needs no end; a diagonal of 0 or below is refused in
    one line and 0.5 scales alpha0; an unknown kind (one sorting before "constant") gets the unknown-kind line."""
    assert [AlphaSchedule.resolve("linear", 0.1, end=e, total_steps=10).end_step for e in (0.5, 1.0, 1e-9)] == [5, 9, 1]
    assert AlphaSchedule.resolve(kind="linear", alpha0=0.1, end=4, total_steps=10).end_step == 4
    assert AlphaSchedule.resolve(parsed("constant"), 0.1, end=None, total_steps=None)(10**6) == 0.1
    assert AlphaSchedule(parsed("constant"), 0.1, None).end_step is None
    for diagonal in (0.0, -2.0):
        with pytest.raises(ValueError) as e:
            AlphaSchedule.resolve("linear", 0.1, end=0.5, total_steps=10, scene_diagonal=diagonal)
        assert str(e.value) == f"scene_diagonal={diagonal!r}: must be a finite number > 0"
    assert AlphaSchedule.resolve("linear", 0.1, end=0.5, total_steps=10, scene_diagonal=0.5).alpha0 == 0.05
    with pytest.raises(ValueError) as e:
        AlphaSchedule.resolve("bogus", 0.1, end=0.5, total_steps=10)
    assert str(e.value) == "schedule='bogus' is not a schedule; allowed values: constant, step, exponential, linear"


def test_before_step_0_alpha_is_alpha0_and_a_schedule_is_frozen():
    """A negative step (a host asking before training) reads step 0; a schedule is a frozen value (hosts share it)."""
    for kind in ("linear", "exponential"):
        s = AlphaSchedule(kind, 0.5, 8)
        assert s(-1) == s(0) == pytest.approx(0.5, rel=1e-12) and s(0) == 0.5
    with pytest.raises(dataclasses.FrozenInstanceError):
        AlphaSchedule("linear", 0.5, 8).alpha0 = 1.0
    with pytest.raises(ValueError, match=r"^final_ratio=1.5: must lie in \(0, 1\)$"):
        AlphaSchedule("exponential", 0.5, 8, final_ratio=1.5)
