"""What every host adapter shares, importing no host at module level.

A host adapter (``sp_plugins.nerfstudio``, ``sp_plugins.sdfstudio``) has one shape: a *seam*
(``seam.py``: where a model hands its samples to a field, the positions move), a *model*
(``model.py``: the preconditioner, optimizer group, callbacks) and *registration*
(``registration.py``: how methods reach the host's commands, ``with_sp``, the refusal table).
The pieces both hosts need live here, one idea per module:

- :mod:`.model`: :class:`~sp_plugins.adapter.model.SPModelBase` and ``SPModelConfig``, what each
  host's ``SPModel`` adds to a host model;
- :mod:`.field`: the preconditioner handle a seam holds, and the K-draw average;
- :mod:`.variants`: SP subclasses of host classes made on demand, importable by the path a saved
  ``config.yml`` names; the refusal-table lookup;
- :mod:`.callbacks`: the schedule's training callbacks. Both hosts are a package named
  ``nerfstudio`` (1.x, and sdfstudio's 0.1 fork) with the same ``nerfstudio.engine.callbacks``, so
  this one module imports it, lazily: the only place here that touches a host;
- :mod:`.shrink`: a trainer config of either host made CPU-sized (tests, benchmarks);
- :mod:`.presets`, :mod:`.checks`, :mod:`.errors`, :mod:`.safe_config`, :mod:`.lpips`: presets,
  input checks with one-line errors, the restricted config loader, LPIPS without downloads.

A new host gets a folder of its own (``seam.py``, ``model.py``, ``registration.py``) built on
these; a new method of an existing host usually needs no code at all (the host's ``with_sp``).
"""

from sp_plugins.adapter.field import PreconditionerHandle, SPFieldMixin
from sp_plugins.adapter.variants import VariantFactory

__all__ = ["PreconditionerHandle", "SPFieldMixin", "VariantFactory"]
