"""The nerfstudio 1.x adapter: SP on any nerfstudio method (``with_sp``, ``sp-train``) and our methods.

One shape, as in ``sp_plugins.sdfstudio``: fields (where positions are perturbed:
:mod:`~sp_plugins.nerfstudio.frustum_sp`, :mod:`~sp_plugins.nerfstudio.mipnerf`,
:mod:`~sp_plugins.nerfstudio.sdf_field`), models (:mod:`~sp_plugins.nerfstudio.model`, the
preconditioner, optimizer group and callbacks) and registration
(:mod:`~sp_plugins.nerfstudio.registration`: ``with_sp`` and ``sp-train``). Importing this
package imports no host module.
"""

from sp_plugins.nerfstudio.registration import with_sp

__all__ = ["with_sp"]
