"""What the nerfstudio adapter knows about methods: the one file to edit to support or refuse one.

Tables keyed by a host model class's path (``module.QualName``, a string: no host import here)
apply to that class and its subclasses, the most derived class a table names winning
(:mod:`sp_plugins.adapter.tables`); tables keyed by a method name apply to our registered methods.

- :data:`REFUSED_MODELS`: models SP cannot reach (no field it is handed ``RaySamples``), and why.
  ``sp-train`` and ``with_sp`` refuse them in one line.
- :data:`NEEDS_CUDA`: models that cannot run without CUDA: refused on such a machine only.
- :data:`PRESETS`: the paper's settings for a model; any other model gets ``presets.DEFAULT``.
- :data:`PLAIN_FIELDS`: submodules of a model that stay plain (not perturbed), and why.
- :data:`ALPHA_GRID_UNREACHABLE`: models whose fields detach the positions they read, so a
  learnable alpha grid is refused.
- :data:`CONTRACTED_MODELS`: models whose field contracts space, and the flag that turns that
  off: a box boundary is refused unless it is off.
- :data:`OUR_BASELINES`, :data:`SP_OFF_METHODS`: our methods with SP off, and what ``sp-train``
  says of them.

A model no table names is offered with the default preset; the seam then checks after its first
step that a field read the moved positions. To support a model that fails that check, give its
field a read point (:mod:`sp_plugins.nerfstudio.seam`); to refuse one, add it to
:data:`REFUSED_MODELS`. README's method table is generated from this module
(``python -m sp_plugins.method_table --write``).
"""

from __future__ import annotations

from typing import Dict, Optional, Tuple

from sp_plugins.adapter import presets
from sp_plugins.core import SPConfig

REFUSED_MODELS: Dict[str, str] = {
    "nerfstudio.models.splatfacto.SplatfactoModel": (
        "Gaussian splatting has no field queried with RaySamples (it rasterises Gaussians); SP does not apply"
    ),
}
"""Host model classes SP cannot reach, and why: only what has no field."""

NEEDS_CUDA: Dict[str, str] = {
    "nerfstudio.models.instant_ngp.NGPModel": "it ray-marches with nerfacc's CUDA kernels and no CUDA device is available",
}
"""Host models that cannot run without CUDA: refused on such a machine (on a CPU nerfacc tries to
JIT-compile its CUDA extension, fails after minutes and can leave a lock that hangs later runs)."""

PRESETS: Dict[str, SPConfig] = {
    "nerfstudio.models.base_surface_model.SurfaceModel": presets.NEUS,
    "nerfstudio.models.mipnerf.MipNerfModel": presets.MIPNERF,
}
"""The paper's settings for host model classes; :data:`presets.DEFAULT` otherwise."""

PLAIN_FIELDS: Dict[str, Dict[str, str]] = {
    "nerfstudio.models.base_surface_model.SurfaceModel": {
        "field_background": "the background model outside the SDF's sphere: the paper perturbs the SDF field only",
    },
}
"""Host model classes -> submodules that stay plain, and why (merged over the class's bases)."""

ALPHA_GRID_UNREACHABLE: Dict[str, Tuple[str, str]] = {
    "nerfstudio.models.tensorf.TensoRFModel": (
        "TensoRF", "nerfstudio's TensoRF encoding detaches its sample positions, so no gradient reaches the alpha grid"
    ),
}
"""Host models whose fields detach the positions they read: a learnable alpha grid cannot learn."""

CONTRACTED_MODELS: Dict[str, Optional[str]] = {
    "nerfstudio.models.nerfacto.NerfactoModel": "disable_scene_contraction",
    "nerfstudio.models.instant_ngp.NGPModel": "disable_scene_contraction",
    "nerfstudio.models.semantic_nerfw.SemanticNerfWModel": None,
}
"""Host models whose radiance field contracts space, and the config flag that turns that off
(None: always on). A box boundary cannot apply there; known from the config, so it is refused
before the run writes anything (other fields are checked after their first step)."""

OUR_BASELINES: Dict[str, str] = {
    "neus-hashgrid": "sp-neus-hashgrid",
    "neuralangelo-lite": "sp-neuralangelo-lite",
    "relu-field": "sp-relu-field",
    "relu-field-flat": "sp-relu-field",
}
"""Our baselines (SP off) and the method that is the same with SP on."""

SP_OFF_METHODS: Dict[str, str] = {
    "freenerf-lite": "FreeNeRF is a sparse-view method of its own, not SP's baseline: sp-train puts SP on it (FreeNeRF + SP)",
}
"""Our methods that have SP off by default but are no one's baseline: ``sp-train`` offers them, and why."""
