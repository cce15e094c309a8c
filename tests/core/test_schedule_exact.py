"""The alpha schedule (sp_plugins.core.schedule), exactly: its defaults, each bound of ``__post_init__`` and
``resolve`` at its edge with its one line, and kinds named by parsed strings. Each test names the mutants it
kills (``bench/mutation_study.py sp_plugins/core/schedule.py``)."""

import math

import pytest

from sp_plugins.core.schedule import AlphaSchedule


def parsed(word: str) -> str:
    """An equal string that is not the literal (as tyro hands over a flag's value)."""
    return "".join(list(word))


def test_the_defaults_are_the_papers_exponential_from_alpha0_one_percent():
    """Kills: ``alpha0: float = 0.01`` -> 1.01 / -0.99, ``final_ratio`` 1e-3 and the kind changed."""
    s = AlphaSchedule(end_step=10)
    assert (s.kind, s.alpha0, s.end_step, s.final_ratio) == ("exponential", 0.01, 10, 1e-3)
    assert s(0) == pytest.approx(0.01, rel=1e-12) and s(10) == 0.0


@pytest.mark.parametrize("kind", ["constant", "step", "exponential", "linear"])
def test_a_kind_named_by_a_parsed_string_gives_the_literals_values(kind):
    """Kills: ``kind == "constant"`` / ``"step"`` / ``"linear"`` -> ``is`` in ``__call__``."""
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
    above 0, a constant schedule without an end). Kills: ``end_step < 1`` -> ``< 0``, ``0.0 < final_ratio`` ->
    ``<=`` / ``!=``."""
    with pytest.raises(ValueError) as e:
        AlphaSchedule(alpha0=0.1, **kwargs)
    assert str(e.value) == message
    assert AlphaSchedule("linear", 0.1, 1)(0) == 0.1
    assert AlphaSchedule("exponential", 0.1, 5, final_ratio=1e-300)(0) == 0.1
    assert AlphaSchedule("constant", 0.1, None)(10**6) == 0.1


@pytest.mark.parametrize("end", [None, math.nan, 0.0, -1.0])
def test_resolve_refuses_a_missing_or_non_positive_end_in_one_line(end):
    """None and NaN get the line too (not a TypeError from ``None <= 0`` or int(NaN)'s message). Kills: either
    ``or`` of ``end is None or not isfinite(end) or end <= 0`` -> ``and``."""
    with pytest.raises(ValueError) as e:
        AlphaSchedule.resolve("exponential", 0.01, end=end, total_steps=100)
    assert str(e.value) == f"end={end!r}: give a fraction of training in (0, 1] or an absolute end step > 1"
