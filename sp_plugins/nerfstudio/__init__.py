"""The nerfstudio 1.x adapter: SP on any nerfstudio method (``with_sp``, ``sp-train``) and our methods.

One shape, as in ``sp_plugins.sdfstudio``, on the host-neutral base ``sp_plugins.adapter``:

- fields, where positions are perturbed: :mod:`~sp_plugins.nerfstudio.seam`, the one seam: every
  field a model calls with ``RaySamples`` is handed a copy whose origins carry the SP offset, so
  ``get_positions()``, ``get_start_positions()`` and Gaussian means all move;
  :mod:`~sp_plugins.nerfstudio.sdf_field` is our SDF field (masked levels, numerical gradients);
- models: :mod:`~sp_plugins.nerfstudio.model` (``SPModel``: attaches the seam, refuses where it
  cannot act), :mod:`~sp_plugins.nerfstudio.neus`, :mod:`~sp_plugins.nerfstudio.mipnerf`;
- registration: :mod:`~sp_plugins.nerfstudio.registration` (``with_sp``, what ``sp-train`` offers,
  the refusals; the command itself is :mod:`sp_plugins.cli.train`), :mod:`~sp_plugins.nerfstudio.variants` (SP subclasses of any host class, by path), and the
  trainer configs of our registered methods (:mod:`~sp_plugins.nerfstudio.sdf_configs`,
  :mod:`~sp_plugins.nerfstudio.radiance_configs`; ``runs`` runs them from Python).

Not SP, in their own sub-packages: :mod:`~sp_plugins.nerfstudio.relu_field` (a method of ours) and
:mod:`~sp_plugins.nerfstudio.components` (data checks, the tcnn fallback, float schedulers, offline
LPIPS). Importing this package imports no host module.
"""

from sp_plugins.nerfstudio.registration import with_sp

__all__ = ["with_sp"]
