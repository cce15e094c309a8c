"""The README's NeuS recipe went NaN at step 93: a training ray that misses the scene box almost
parallel to a face gets a near plane beyond the background's far plane from nerfstudio's box collider, its
background bins run backwards and the rendered colour is NaN. These tests pin that cause on the host, and
that our surface models render such a ray finitely and leave every other ray as nerfstudio meets it."""

from __future__ import annotations

import pytest
import torch

from nerfstudio.cameras.rays import RayBundle
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.model_components.scene_colliders import AABBBoxCollider

from sp_plugins.nerfstudio.components.colliders import SurfaceBoxCollider, bound_surface_rays, closest_approach

BOX = SceneBox(aabb=torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))
FAR_BG = 1000.0


def _bundle(origins, directions) -> RayBundle:
    origins, directions = torch.as_tensor(origins, dtype=torch.float32), torch.as_tensor(directions, dtype=torch.float32)
    directions = directions / directions.norm(dim=-1, keepdim=True)
    n = origins.shape[0]
    return RayBundle(origins=origins, directions=directions, pixel_area=torch.full((n, 1), 1e-4),
                     camera_indices=torch.zeros(n, 1, dtype=torch.long),
                     metadata={"directions_norm": torch.ones(n, 1)})


# 3 units above the box, running along x and descending 1 unit per 10,000: it reaches the top face's plane
# 20,000 units on, long after it passed beside the box (one such ray in every 50,000 of sp-scene spot's)
GRAZING = ([[0.0, 3.0, 0.0]], [[1.0, -1e-4, 0.0]])


def test_nerfstudio_s_box_collider_starts_a_ray_that_misses_the_box_beyond_the_background_s_far_plane():
    """The host's behaviour that caused the NaN (fails when nerfstudio changes it: then the collider can go)."""
    collider = AABBBoxCollider(BOX, near_plane=0.05)
    bundle = collider(_bundle(*GRAZING))
    assert bundle.nears.item() > FAR_BG and bundle.fars.item() > FAR_BG


def test_our_collider_starts_that_ray_at_its_closest_approach_and_leaves_every_other_ray_as_nerfstudio_does():
    g = torch.Generator().manual_seed(0)
    origins = torch.randn(4000, 3, generator=g) * 3
    directions = torch.randn(4000, 3, generator=g)
    origins = torch.cat([origins, torch.tensor(GRAZING[0])])
    directions = torch.cat([directions, torch.tensor(GRAZING[1])])
    host = AABBBoxCollider(BOX, near_plane=0.05)(_bundle(origins, directions))
    ours = SurfaceBoxCollider(BOX, near_plane=0.05, far_plane_bg=FAR_BG)(_bundle(origins, directions))
    beyond = (host.nears > FAR_BG).squeeze(-1)
    assert beyond[-1] and 1 < beyond.sum() < 100  # random rays that leave the box behind them meet it too
    assert torch.equal(ours.nears[~beyond], host.nears[~beyond]) and torch.equal(ours.fars[~beyond], host.fars[~beyond])
    expected = closest_approach(ours.origins, ours.directions, torch.zeros(3)).clamp(0.05, FAR_BG)
    assert expected[-1].item() == pytest.approx(0.05)  # 3e-4 along the grazing ray, clamped to the near plane
    assert torch.allclose(ours.nears[beyond], expected[beyond])
    assert ((ours.fars - ours.nears)[beyond] > 0).all() and ((ours.fars - ours.nears)[beyond] < 1e-3).all()
    assert (ours.nears <= FAR_BG).all() and (ours.fars >= ours.nears).all()


def test_a_surface_model_renders_the_grazing_ray_finitely_where_the_host_s_collider_renders_nan(tiny_scene, tmp_path, tiny_config):
    """Our NeuS model with nerfstudio's background MLP: a finite colour and finite gradients for the ray that
    made the recipe diverge; with the host's collider put back, the same ray renders NaN."""
    config = tiny_config("sp-neus-hashgrid", tiny_scene, tmp_path)
    model_config = config.pipeline.model
    model_config.background_model = "mlp"
    model_config.background_mlp_layers, model_config.background_mlp_width = 2, 16
    torch.manual_seed(0)
    model = model_config.setup(scene_box=BOX, num_train_data=1, metadata={}, device="cpu")
    model.train()
    assert type(model.collider) is SurfaceBoxCollider
    rgb = model(_bundle(*GRAZING))["rgb"]
    assert torch.isfinite(rgb).all()
    rgb.sum().backward()
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)

    model.collider = AABBBoxCollider(BOX, near_plane=0.05)  # nerfstudio's own, as before the fix
    assert not torch.isfinite(model(_bundle(*GRAZING))["rgb"]).all()


def test_a_model_with_its_own_near_far_planes_keeps_its_collider():
    from types import SimpleNamespace

    from nerfstudio.model_components.scene_colliders import NearFarCollider

    model = SimpleNamespace(collider=NearFarCollider(2.0, 6.0), config=SimpleNamespace(far_plane_bg=FAR_BG))
    bound_surface_rays(model)
    assert type(model.collider) is NearFarCollider


def test_a_surface_model_on_nerfstudio_s_collider_names_it_when_its_loss_goes_nan(tiny_scene, tmp_path, tiny_config):
    """``sp-train neus`` keeps the host's collider (SP changes nothing else): a NaN there names the collider
    before the learning rate; our surface models, which bound those rays, give no such hint."""
    from sp_plugins.adapter.errors import InputError

    config = tiny_config("sp-neus-hashgrid", tiny_scene, tmp_path)
    model = config.pipeline.model.setup(scene_box=BOX, num_train_data=1, metadata={}, device="cpu")
    assert model._divergence_hint() is None
    model.collider = AABBBoxCollider(BOX, near_plane=0.05)
    hint = model._divergence_hint()
    assert "nerfstudio's box collider" in hint
    watch = model._sp_watch
    watch.update({"rgb_loss": torch.tensor(float("nan"))}, 7)
    with pytest.raises(InputError, match=r"^training step 7: .*: likely cause: this surface model keeps nerfstudio's box "
                                         r"collider.*; otherwise lower the learning rate \(--optimizers\.fields"):
        watch.raise_if_diverged(7, model._lr_groups, model._divergence_hint)


def test_closest_approach_exactly():
    """``t`` of the point nearest the centre: the projection of centre - origin on the direction over its squared length."""
    origins = torch.tensor([[-5.0, 0.0, 0.0], [-5.0, 0.0, 0.0], [0.0, 3.0, 0.0], [1.0, 1.0, 1.0], [4.0, 0.0, 0.0]])
    directions = torch.tensor([[1.0, 0.0, 0.0], [2.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    t = closest_approach(origins, directions, torch.tensor([0.0, 0.0, 1.0]))
    assert t.shape == (5, 1)
    assert t.squeeze(-1).tolist() == [5.0, 2.5, 0.0, 0.0, -4.0]  # a longer direction halves t; behind the origin: negative


@pytest.mark.parametrize("training, start", [(True, 0.05), (False, 3e-4)])
def test_the_grazing_ray_starts_at_the_near_plane_in_training_and_at_0_in_evaluation(training, start):
    """The closest approach (3e-4 along this ray) is clamped to ``[near_plane, far_plane_bg]`` while training and
    to ``[0, far_plane_bg]`` in evaluation (nerfstudio's colliders use near 0 there), the interval 1e-6 long; a ray whose closest approach
    lies beyond the background's far plane starts at that far plane."""
    collider = SurfaceBoxCollider(BOX, near_plane=0.05, far_plane_bg=FAR_BG)
    collider.train(training)
    behind = ([[0.0, 3.0, 0.0], [-2e5, 3.0, 0.0]], [[1.0, -1e-4, 0.0], [1.0, -1e-4, 0.0]])  # the second passes the box at t 2e5
    bundle = collider(_bundle(*behind))
    assert bundle.nears[0].item() == pytest.approx(start, rel=1e-6) and bundle.nears[1].item() == FAR_BG
    assert torch.equal(bundle.fars, bundle.nears + 1e-6)
