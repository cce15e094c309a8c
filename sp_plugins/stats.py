"""Paired differences over seeds: is an effect larger than run-to-run noise?

A claim that SP helps is a paired difference: the same scene, settings and seed with SP and
without, over several seeds. :func:`paired_difference` gives the mean difference with a 95%
Student-t interval over the pairs (t with n - 1 degrees of freedom: the honest interval for the
3-10 seeds a neural-field study can afford; a bootstrap needs more pairs than that) and a verdict
in words. Used by ``sp-compare`` and the benchmarks.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Optional, Sequence

__all__ = ["PairedDifference", "paired_difference", "spread"]

BETTER, WORSE, NOISE, ONE_PAIR = "better", "worse", "within the noise", "one pair: cannot tell"


@dataclass(frozen=True)
class PairedDifference:
    """``b - a`` over ``n`` pairs: mean, sample standard deviation, the interval and the verdict for b."""

    n: int
    mean: float
    sd: Optional[float]
    low: Optional[float]
    high: Optional[float]
    verdict: str
    confidence: float = 0.95

    def as_dict(self) -> dict:
        return asdict(self)

    def text(self, digits: int) -> str:
        """``+mean [+low, +high]`` at ``digits`` decimals (the mean alone for one pair), as tables quote it."""
        mean = f"{self.mean:+.{digits}f}"
        return mean if self.low is None or self.high is None else f"{mean} [{self.low:+.{digits}f}, {self.high:+.{digits}f}]"


def spread(values: Sequence[float]) -> tuple:
    """``(mean, sample sd)`` of ``values`` (sd None for one value)."""
    n = len(values)
    if n == 0:
        raise ValueError("no values")
    mean = sum(values) / n
    sd = math.sqrt(sum((v - mean) ** 2 for v in values) / (n - 1)) if n > 1 else None
    return mean, sd


def paired_difference(a: Sequence[float], b: Sequence[float], higher_is_better: bool = True,
                      confidence: float = 0.95) -> PairedDifference:
    """``b - a`` pair by pair (``a[i]`` and ``b[i]`` share a seed): mean, t interval, verdict.

    The verdict is ``better`` / ``worse`` (for ``b``) when the interval excludes 0, ``within the
    noise`` when it contains 0, and ``one pair: cannot tell`` with a single pair."""
    if len(a) != len(b) or not a:
        raise ValueError(f"paired values need the same, non-zero count (got {len(a)} and {len(b)})")
    diffs = [y - x for x, y in zip(a, b)]
    mean, sd = spread(diffs)
    if sd is None:
        return PairedDifference(1, mean, None, None, None, ONE_PAIR, confidence)
    from scipy.stats import t

    half = float(t.ppf(0.5 + confidence / 2, len(diffs) - 1)) * sd / math.sqrt(len(diffs))
    low, high = mean - half, mean + half
    if low > 0 or high < 0:
        verdict = BETTER if (low > 0) == higher_is_better else WORSE
    else:
        verdict = NOISE
    return PairedDifference(len(diffs), mean, sd, low, high, verdict, confidence)
