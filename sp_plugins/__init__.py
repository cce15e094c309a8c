"""sp-plugins: stochastic preconditioning for neural fields.

The public API is deliberately small::

    from sp_plugins import perturb, AlphaSchedule, AlphaGrid, StochasticPreconditioner, SPConfig
"""

from sp_plugins.core import AlphaGrid, AlphaSchedule, SPConfig, StochasticPreconditioner, perturb

__version__ = "0.2.0"
__all__ = ["AlphaGrid", "AlphaSchedule", "SPConfig", "StochasticPreconditioner", "perturb", "__version__"]
