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
- :data:`READ_POINTS`: host field classes that query their samples elsewhere than
  ``get_positions()``, and where (the seam computes SP's offset there).
- :data:`BOX_FIELDS`: host field classes that live in the scene box even where the model contracts
  space, so a box boundary applies to them.
- :data:`OUR_BASELINES`, :data:`SP_OFF_METHODS`: our methods with SP off, and what ``sp-train``
  says of them; :data:`OUR_METHODS`, :data:`OUR_SDF_METHODS`, :data:`HOST_BASELINES`: our
  registered method names, for the front ends that list methods (nerfbaselines, ``sp-gpu-check``).

:func:`preset_for` and :func:`refusal` read these tables; everything else asks them.

A model no table names is offered with the default preset; the seam then checks after its first
step that a field read the moved positions. To support a model that fails that check, give its
field a read point (:mod:`sp_plugins.nerfstudio.seam`); to refuse one, add it to
:data:`REFUSED_MODELS`. README's method table is generated from this module
(``python -m sp_plugins.method_table --write``).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Dict, Optional, Tuple

from sp_plugins.adapter import presets
from sp_plugins.adapter.tables import lookup
from sp_plugins.adapter.variants import table_refusal, target_class
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
    "sp_plugins.nerfstudio.neus.NeuralangeloLiteModel": presets.NEURALANGELO,
    "nerfstudio.models.mipnerf.MipNerfModel": presets.MIPNERF,
    "nerfstudio.models.tensorf.TensoRFModel": presets.BOX_FIELD,
    "sp_plugins.nerfstudio.relu_field.model.ReLUFieldModel": presets.RELU_FIELD,
}
"""The settings for model classes (the paper's where it ran them); :data:`presets.DEFAULT` otherwise.
TensoRF's grid lives in the scene box (its collider is the box), so its samples reflect into it."""

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

READ_POINTS: Dict[str, str] = {
    "nerfstudio.fields.sdf_field.SDFField": "get_start_positions",
}
"""Host field classes (and subclasses) that do not query at ``get_positions()``, the default, and
the ``Frustums`` accessor they query at: nerfstudio's SDF fields query the bins' starts. (MipNeRF's
Gaussian blob needs no entry: its mean moves with the midpoint's offset.) A field class of your own
declares ``sp_read_positions`` instead (:class:`sp_plugins.adapter.field.ReadPointField`)."""

BOX_FIELDS: Dict[str, str] = {
    "nerfstudio.fields.sdf_field.SDFField": "an SDF lives in the scene box (its contraction is the identity there)",
}
"""Host field classes that a box boundary applies to even with scene contraction on, and why."""

OUR_METHODS: Tuple[str, ...] = ("sp-nerfacto", "sp-mipnerf", "sp-vanilla-nerf", "sp-tensorf", "sp-relu-field", "relu-field",
                                "relu-field-flat", "freenerf-lite")
"""Our registered radiance-field methods (``ns-train`` names)."""

OUR_SDF_METHODS: Tuple[str, ...] = ("sp-neus", "sp-neus-hashgrid", "neus-hashgrid", "sp-neuralangelo-lite", "neuralangelo-lite")
"""Our registered SDF methods (``ns-train`` names)."""

HOST_BASELINES: Tuple[str, ...] = ("nerfacto", "mipnerf", "vanilla-nerf", "tensorf")
"""nerfstudio's own methods that an SP method of ours is the SP variant of (``sp-<name>``)."""

HASH_GRID_SDF = "neus-hashgrid"
"""Our hash-grid NeuS without SP: the SDF baseline the README's recipe and the GPU check train (its SP method:
:data:`OUR_BASELINES`)."""
NERFACTO = "nerfacto"
"""nerfstudio's own nerfacto: the baseline of ``sp-nerfacto`` and of ``sp-train nerfacto`` (the recipes, the GPU check)."""
SP_NERFACTO = "sp-nerfacto"
"""Our nerfacto with SP (nerfacto on our hash grid where tiny-cuda-nn cannot run, then ``with_sp``)."""

OUR_BASELINES: Dict[str, str] = {
    HASH_GRID_SDF: "sp-neus-hashgrid",
    "neuralangelo-lite": "sp-neuralangelo-lite",
    "relu-field": "sp-relu-field",
    "relu-field-flat": "sp-relu-field",
}
"""Our baselines (SP off) and the method that is the same with SP on."""

SP_OFF_METHODS: Dict[str, str] = {
    "freenerf-lite": "FreeNeRF is a sparse-view method of its own, not SP's baseline: sp-train puts SP on it (FreeNeRF + SP)",
}
"""Our methods that have SP off by default but are no one's baseline: ``sp-train`` offers them, and why."""


def _cuda_available() -> bool:
    import torch

    return torch.cuda.is_available()


def preset_for(model_config: Any) -> SPConfig:
    """A copy of the SP settings for a model config's host model class (:data:`PRESETS`)."""
    found = lookup(PRESETS, target_class(model_config))
    return dataclasses.replace(found[1] if found else presets.DEFAULT)


def refusal(config: Any) -> Optional[str]:
    """Why SP cannot be put on the method of trainer config ``config`` (None when it can).

    Decided from classes only (nothing is built): a method that passes can still be refused when
    its model is built or after its first step (see :class:`sp_plugins.nerfstudio.model.SPModel`)."""
    if type(config).__name__ == "ExternalMethodDummyTrainerConfig":
        return "it is an external method that is not installed; install it, then it is listed here"
    cuda = {path: (lambda why=why: None if _cuda_available() else why) for path, why in NEEDS_CUDA.items()}
    return table_refusal(getattr(getattr(config, "pipeline", None), "model", None), REFUSED_MODELS, cuda)[1]
