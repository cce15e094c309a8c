"""What every host adapter shares, importing no host at module level.

A host adapter (``sp_plugins.nerfstudio``, ``sp_plugins.sdfstudio``) has one shape: *fields*
(where positions are perturbed), *models* (the preconditioner, optimizer group, callbacks) and
*registration* (how methods reach the host's commands). The pieces both hosts need live here:

- :mod:`~sp_plugins.adapter.field`: the field mixin that holds the preconditioner handle and
  averages ``num_samples`` draws;
- :mod:`~sp_plugins.adapter.variants`: SP subclasses of host classes made on demand (for SP on
  any method) and importable by the path a saved ``config.yml`` names.

A new host gets a folder of its own with ``fields``, ``models`` and ``registration`` built on
these; a new method of an existing host usually needs no code at all (the host's ``with_sp``).
"""

from sp_plugins.adapter.field import PreconditionerHandle, SPFieldMixin
from sp_plugins.adapter.variants import VariantFactory

__all__ = ["PreconditionerHandle", "SPFieldMixin", "VariantFactory"]
