"""sp-plugins: stochastic preconditioning for neural fields.

The public API is deliberately small::

    from sp_plugins import perturb, AlphaSchedule, AlphaGrid, StochasticPreconditioner, SPConfig, SPRun, SPNotReached

The names are loaded on first use (PEP 562), so that ``import sp_plugins.<module>`` of a module
that does not need torch (the sweep's trial runner in each Ray worker, the spec, the report) does
not import torch: 2-5 s and some hundred MB per process.
"""

from sp_plugins._lazy import lazy_attribute

__version__ = "0.2.0"
__all__ = ["AlphaGrid", "AlphaSchedule", "SPConfig", "SPNotReached", "SPRun", "StochasticPreconditioner", "perturb",
           "__version__"]
_WHERE = {name: "core" for name in __all__ if name != "__version__"}


def __getattr__(name: str):
    return lazy_attribute(__name__, _WHERE, name)


def __dir__():
    return sorted(set(globals()) | set(__all__))
