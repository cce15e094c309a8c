"""The box collider of our surface models: rays that miss the box stay in front of the background's far plane.

nerfstudio 1.1.5's ``SurfaceModel`` (NeuS, neus-facto and ours) meets rays with the scene box through
``AABBBoxCollider`` and then samples its background model from each ray's box exit (``fars``) to
``far_plane_bg`` (1000). For a ray that misses the box, the collider's near is where the ray enters the last
slab of the box, ``(face - origin) / (direction + 1e-6)`` along an axis the ray nearly runs parallel to: it
can lie anywhere up to about 1e6 scene units. Where it lies beyond ``far_plane_bg``, the background's bins run
backwards (negative lengths), ``exp(+density * length)`` overflows, the background weights become infinite
and the rendered colour NaN: the whole model is NaN one optimizer step later. On ``sp-scene spot`` (64x64,
24 views) 2 of the 98,304 training rays are such rays, so a run at 256 rays per step meets one after about
200 steps on average (the README's NeuS recipe: step 93 with SP, step 149 without; the step depends only on
which rays are drawn). sdfstudio is not affected: its surface models use the scene's near/far planes.

:class:`SurfaceBoxCollider` is nerfstudio's collider, except that such a ray (near beyond the background's far
plane) starts at its closest approach to the box's centre, clamped to ``[near_plane, far_plane_bg]``, as an
empty foreground interval there: its background is sampled from that point on, as for every other ray that
misses. Every other ray keeps nerfstudio's near and far exactly.
"""

from __future__ import annotations

import torch
from jaxtyping import Float
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.model_components.scene_colliders import AABBBoxCollider
from torch import Tensor


def closest_approach(
    origins: Float[Tensor, "n 3"], directions: Float[Tensor, "n 3"], centre: Float[Tensor, "3"]
) -> Float[Tensor, "n 1"]:
    """The ray parameter ``t`` at which each ray passes closest to ``centre``."""
    return ((centre - origins) * directions).sum(-1, keepdim=True) / directions.square().sum(-1, keepdim=True)


class SurfaceBoxCollider(AABBBoxCollider):
    """nerfstudio's ``AABBBoxCollider`` whose rays never start beyond ``far_plane_bg`` (see the module)."""

    def __init__(self, scene_box: SceneBox, near_plane: float, far_plane_bg: float, **kwargs) -> None:
        super().__init__(scene_box, near_plane=near_plane, **kwargs)
        self.far_plane_bg = float(far_plane_bg)

    def set_nears_and_fars(self, ray_bundle: RayBundle) -> RayBundle:
        ray_bundle = super().set_nears_and_fars(ray_bundle)
        nears, fars = ray_bundle.nears, ray_bundle.fars
        assert nears is not None and fars is not None
        beyond = nears > self.far_plane_bg  # no device sync: a masked select, whatever the count
        near_plane = self.near_plane if self.training else 0.0
        centre = self.scene_box.aabb.to(nears).mean(0)
        t = closest_approach(ray_bundle.origins, ray_bundle.directions, centre).clamp(near_plane, self.far_plane_bg)
        ray_bundle.nears = torch.where(beyond, t, nears)
        ray_bundle.fars = torch.where(beyond, t + 1e-6, fars)
        return ray_bundle


GRAZING_RAYS_HINT = ("this surface model keeps nerfstudio's box collider, which starts a ray that grazes the box beyond "
                     "the background's far plane (a NaN background colour); sp-neus, sp-neus-hashgrid and neus-hashgrid "
                     "bound such rays (docs/troubleshooting.md)")
"""What a divergence of a model with :func:`unbounded_surface_rays` names as its likely cause."""


def unbounded_surface_rays(model) -> bool:
    """``model`` is a surface model (it samples a background to ``far_plane_bg``) on nerfstudio's own box
    collider, whose grazing rays can start beyond that far plane (a model with ``overwrite_near_far_plane``
    has a near/far collider, which has no such rays)."""
    return type(getattr(model, "collider", None)) is AABBBoxCollider and hasattr(getattr(model, "config", None), "far_plane_bg")


def bound_surface_rays(model) -> None:
    """Give a nerfstudio ``SurfaceModel`` with :func:`unbounded_surface_rays` :class:`SurfaceBoxCollider`."""
    if unbounded_surface_rays(model):
        collider = model.collider
        model.collider = SurfaceBoxCollider(collider.scene_box, collider.near_plane, model.config.far_plane_bg)
