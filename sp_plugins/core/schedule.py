"""Alpha schedules: how the perturbation scale anneals to 0 over training."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, Optional

ScheduleKind = Literal["constant", "step", "exponential", "linear"]
SCHEDULE_KINDS: tuple[str, ...] = ("constant", "step", "exponential", "linear")


@dataclass(frozen=True)
class AlphaSchedule:
    """``alpha(step)`` for one training run.

    Kinds (T = ``end_step``):

    - ``constant``: ``alpha0`` forever (for an alpha grid that learns its own decay, or ablations).
    - ``step``: ``alpha0`` until T, then exactly 0 (the official code's choice).
    - ``exponential``: ``alpha0 * (r**(t/T) - r) / (1 - r)`` with ``r = final_ratio``: a geometric
      decay over ``log10(1/r)`` decades, shifted so that it reaches exactly 0 at T (the paper's
      default). With ``r = 1e-3`` the value at ``t = T/2`` is about 3% of ``alpha0``.
    - ``linear``: ``alpha0 * (1 - t/T)``.

    At and after T every kind but ``constant`` is exactly 0, so the trained field is an ordinary
    field; :meth:`resolve` puts T at the last training step at the latest.
    """

    kind: ScheduleKind = "exponential"
    alpha0: float = 0.01
    end_step: Optional[int] = None
    final_ratio: float = 1e-3

    def __post_init__(self) -> None:
        if self.kind not in SCHEDULE_KINDS:
            raise ValueError(f"schedule={self.kind!r} is not a schedule; allowed values: {', '.join(SCHEDULE_KINDS)}")
        if not (math.isfinite(self.alpha0) and self.alpha0 >= 0):
            raise ValueError(f"alpha0={self.alpha0!r}: must be a finite number >= 0")
        if self.kind != "constant" and (self.end_step is None or self.end_step < 1):
            raise ValueError(f"end_step={self.end_step!r}: schedule {self.kind!r} needs an end step >= 1")
        if not 0.0 < self.final_ratio < 1.0:
            raise ValueError(f"final_ratio={self.final_ratio!r}: must lie in (0, 1)")

    @staticmethod
    def resolve(
        kind: ScheduleKind,
        alpha0: float,
        *,
        end: Optional[float],
        total_steps: Optional[int],
        scene_diagonal: Optional[float] = None,
        final_ratio: float = 1e-3,
    ) -> "AlphaSchedule":
        """Build a schedule from user-facing settings.

        Args:
            alpha0: absolute when ``scene_diagonal`` is None, else a fraction of the diagonal.
            end: a fraction of ``total_steps`` when in (0, 1], an absolute step when > 1. The end
                step is ``round(end * total_steps)`` (0.2 of 5000: step 1000, the first at alpha
                0), capped at the last step ``total_steps - 1``: ``end=1.0`` (or ``end=total``)
                keeps SP on for every step but the last, which trains the plain field.
            total_steps: length of training (steps ``0 .. total_steps - 1``); the end must not lie
                after it.
        """
        if scene_diagonal is not None:
            if not (math.isfinite(scene_diagonal) and scene_diagonal > 0):
                raise ValueError(f"scene_diagonal={scene_diagonal!r}: must be a finite number > 0")
            alpha0 = alpha0 * scene_diagonal
        if kind == "constant":
            return AlphaSchedule("constant", alpha0, None, final_ratio)
        if end is None or not math.isfinite(end) or end <= 0:
            raise ValueError(f"end={end!r}: give a fraction of training in (0, 1] or an absolute end step > 1")
        if end <= 1:
            if total_steps is None:
                raise ValueError(f"end={end} is a fraction of training: total_steps is needed to resolve it")
            end_step = round(end * total_steps)
        else:
            if end != int(end):
                raise ValueError(f"end={end}: an absolute end step must be a whole number")
            end_step = int(end)
        if total_steps is not None:
            if end_step > total_steps:
                raise ValueError(
                    f"end={end}: the schedule ends at step {end_step}, after the end of training "
                    f"({total_steps} steps); give an end <= {total_steps} or a fraction in (0, 1]"
                )
            # steps run 0 .. total - 1: an end at the total would never switch SP off
            end_step = min(end_step, total_steps - 1)
        return AlphaSchedule(kind, alpha0, max(1, end_step), final_ratio)

    def __call__(self, step: int) -> float:
        if self.kind == "constant":
            return self.alpha0
        T = self.end_step
        assert T is not None
        if step >= T:
            return 0.0
        t = max(step, 0) / T
        if self.kind == "step":
            return self.alpha0
        if self.kind == "linear":
            return self.alpha0 * (1.0 - t)
        r = self.final_ratio
        return self.alpha0 * (r**t - r) / (1.0 - r)
