"""One SP configuration shared by every method and task."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Type

from sp_plugins.core.preconditioner import StochasticPreconditioner
from sp_plugins.core.settings import ALPHA_GRID_MODES, AlphaGridMode, SPSettings

__all__ = ["ALPHA_GRID_MODES", "AlphaGridMode", "SPConfig"]


@dataclass
class SPConfig(SPSettings):
    """Stochastic preconditioning settings. Nested as ``sp`` in every model config, so
    ``--pipeline.model.sp.alpha0 0.01`` means the same on every method."""

    _target: Type = field(default_factory=lambda: StochasticPreconditioner)
    """What :meth:`setup` builds (nerfstudio's config pattern)."""

    def setup(self, **kwargs):
        """Build the :class:`StochasticPreconditioner` (nerfstudio's config pattern)."""
        return self._target(self, **kwargs)
