"""SP through Frustums.offsets: sp-vanilla-nerf, sp-nerfacto, sp-tensorf."""

from __future__ import annotations

import math

import pytest
import torch
from nerfstudio.cameras.rays import Frustums, RaySamples
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.engine.callbacks import TrainingCallbackLocation
from radiance_tiny import run_recording, tiny_radiance_config  # type: ignore[import-not-found]
from torch import nn

from sp_plugins.core import AlphaSchedule, SPConfig, StochasticPreconditioner
from sp_plugins.nerfstudio.frustum_sp import FrustumSPField, set_perturbed_offsets

POSITION_METHODS = ("sp-vanilla-nerf", "sp-nerfacto", "sp-tensorf")
BOX = SceneBox(aabb=torch.tensor([[-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]]))


def samples(n_rays=8, n=16, origin=(0.0, 0.0, 4.0), far=8.0, offsets=None):
    o = torch.tensor(origin).expand(n_rays, n, 3)
    d = nn.functional.normalize(torch.tensor([0.0, 0.0, -1.0]) + 0.05 * torch.randn(n_rays, 1, 3), dim=-1).expand(n_rays, n, 3)
    t = torch.linspace(0.5, far, n + 1)
    starts, ends = t[:-1].expand(n_rays, n)[..., None], t[1:].expand(n_rays, n)[..., None]
    return RaySamples(Frustums(origins=o, directions=d, starts=starts, ends=ends, pixel_area=torch.full((n_rays, n, 1), 1e-4),
                               offsets=offsets), camera_indices=torch.zeros(n_rays, n, 1, dtype=torch.long))


def preconditioner(alpha=0.3, boundary="reflect", seed=0):
    sp = StochasticPreconditioner(SPConfig(alpha0=alpha, schedule="constant", boundary=boundary, seed=seed), bounds=BOX.aabb)
    sp.set_step(0, 10)
    return sp.train()


def test_offsets_make_get_positions_the_perturbed_positions():
    rs = samples()
    x = rs.frustums.get_positions().clone()
    sp = preconditioner(alpha=0.3)
    previous = set_perturbed_offsets(rs, sp)
    assert previous is None
    q = rs.frustums.get_positions()
    expected = preconditioner(alpha=0.3)(x.reshape(-1, 3)).view(x.shape)  # same seed, same draw
    assert torch.allclose(q, expected, atol=1e-6)
    inside = ((x.abs() <= 1.5).all(-1))
    assert inside.any() and (~inside).any()
    # samples inside the box stay inside (reflection); samples the host placed outside stay where SP put them
    assert (q[inside].abs() <= 1.5 + 1e-6).all()
    assert (q - x).abs().mean() == pytest.approx(0.3 * math.sqrt(2 / math.pi), rel=0.2)


def test_existing_offsets_are_kept_and_restored_after_the_field_runs():
    base = torch.full((8, 16, 3), 0.1)
    rs = samples(offsets=base.clone())
    seen = {}

    class Probe(nn.Module):
        def forward(self, ray_samples, compute_normals=False):
            seen["positions"] = ray_samples.frustums.get_positions().clone()
            return {}

    class SPProbe(FrustumSPField, Probe):
        pass

    field = SPProbe()
    sp = preconditioner(alpha=1e-3, boundary="none")
    field.use_preconditioner(sp)
    x = rs.frustums.get_positions().clone()
    field.forward(rs)  # models call .forward directly
    assert torch.allclose(seen["positions"], x, atol=0.01) and not torch.allclose(seen["positions"], x)
    assert torch.equal(rs.frustums.offsets, base)  # restored
    field(ray_samples=rs)  # and through __call__ with a keyword
    assert torch.equal(rs.frustums.offsets, base)
    field.eval()
    field.forward(rs)
    assert torch.equal(seen["positions"], x)  # eval: the plain positions
    assert "_sp" not in field.state_dict() and list(field.state_dict()) == list(Probe().state_dict())


def test_gradients_reach_positions_through_the_offsets():
    rs = samples(n_rays=2, n=4, origin=(0.0, 0.0, 1.0), far=1.5)
    origins = rs.frustums.origins.clone().requires_grad_(True)
    rs.frustums.origins = origins
    sp = preconditioner(alpha=0.01, boundary="none")
    set_perturbed_offsets(rs, sp)
    rs.frustums.get_positions().sum().backward()
    assert torch.allclose(origins.grad, torch.ones_like(origins))


@pytest.mark.parametrize("name", POSITION_METHODS)
def test_method_trains_a_few_iterations(name, tiny_scene, tmp_path):
    trainer, record = run_recording(tiny_radiance_config(name, tiny_scene, tmp_path, steps=3))
    assert len(record) == 3
    for loss, parts, metrics in record:
        assert math.isfinite(loss) and all(math.isfinite(v) for v in parts.values())
        assert metrics["sp_alpha"] > 0
    model = trainer.pipeline.model
    assert int(model.sp.step) == 2 and int(model.sp.total_steps) == 3
    state = torch.load(sorted(trainer.checkpoint_dir.glob("*.ckpt"))[-1], map_location="cpu", weights_only=False)
    assert "_model.sp.step" in state["pipeline"] and not any("lpips" in k for k in state["pipeline"])


def _fields(model):
    return [model.field_fine] if hasattr(model, "field_fine") else [model.field]


@pytest.mark.parametrize("name", POSITION_METHODS)
def test_training_queries_are_perturbed_and_eval_queries_are_not(name, tiny_scene, tmp_path):
    config = tiny_radiance_config(name, tiny_scene, tmp_path, steps=100, end=0.5, alpha0=0.1)
    model = config.pipeline.model.setup(scene_box=BOX, num_train_data=8, metadata={}, device="cpu", grad_scaler=None)
    for callback in model.get_training_callbacks(_attributes()):
        callback.run_callback_at_location(0, TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)
    assert model.sp.alpha == pytest.approx(0.1)
    rs = samples(origin=(0.0, 0.0, 1.2), far=2.0)
    (field,) = _fields(model)

    # TensoRF's fine pass goes through forward with its ray mask (its coarse pass only places samples)
    kwargs = {"mask": torch.ones(rs.shape[0], dtype=torch.bool), "bg_color": torch.ones(3)} if name == "sp-tensorf" else {}
    model.train()
    a, b = field.forward(rs, **kwargs), field.forward(rs, **kwargs)
    for key in a:  # an untrained field is nearly constant: any difference is the perturbation
        assert not torch.equal(a[key], b[key]), key
    assert rs.frustums.offsets is None
    model.eval()
    c, d = field.forward(rs, **kwargs), field.forward(rs, **kwargs)
    for key in c:
        assert torch.equal(c[key], d[key]), key
    # the schedule callback drives alpha to 0 at the end step: training is then the plain field
    for callback in model.get_training_callbacks(_attributes()):
        callback.run_callback_at_location(50, TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)
    assert model.sp.alpha == 0.0 and AlphaSchedule("exponential", 0.1, end_step=50)(49) > 0
    model.train()  # (nerfacto's training appearance embedding differs from eval's: compare train with train)
    e, f = field.forward(rs, **kwargs), field.forward(rs, **kwargs)
    for key in e:
        assert torch.equal(e[key], f[key]), key


def _attributes():
    from types import SimpleNamespace

    from nerfstudio.engine.callbacks import TrainingCallbackAttributes

    trainer = SimpleNamespace(config=SimpleNamespace(max_num_iterations=100), _start_step=0)
    return TrainingCallbackAttributes(optimizers=None, grad_scaler=None, pipeline=None, trainer=trainer)  # type: ignore[arg-type]


def test_nerfacto_box_boundary_must_match_contraction(tiny_scene, tmp_path):
    config = tiny_radiance_config("sp-nerfacto", tiny_scene, tmp_path, steps=10, boundary="reflect")
    with pytest.raises(ValueError, match="scene contraction is on"):
        config.pipeline.model.setup(scene_box=BOX, num_train_data=8, metadata={}, device="cpu", grad_scaler=None)
    config.pipeline.model.disable_scene_contraction = True  # a bounded nerfacto: reflecting is right
    model = config.pipeline.model.setup(scene_box=BOX, num_train_data=8, metadata={}, device="cpu", grad_scaler=None)
    assert model.sp.config.boundary == "reflect"


def test_resume_restores_the_sp_state(tiny_scene, tmp_path):
    config = tiny_radiance_config("sp-vanilla-nerf", tiny_scene, tmp_path / "first", steps=10)
    first, _ = run_recording(config, stop_after=3)
    ckpt = sorted(config.get_checkpoint_dir().glob("*.ckpt"))[-1]
    loaded = torch.load(ckpt, map_location="cpu", weights_only=False)
    resumed = tiny_radiance_config("sp-vanilla-nerf", tiny_scene, tmp_path / "resumed", steps=10)
    resumed.load_dir = config.get_checkpoint_dir()
    second = resumed.setup(local_rank=0, world_size=1)
    second.setup()
    sp = second.pipeline.model.sp
    assert int(sp.step) == loaded["step"] + 1 and int(sp.total_steps) == 10
    assert sp.alpha == pytest.approx(AlphaSchedule("exponential", 0.05, end_step=10)(loaded["step"] + 1))
    # the host built our field subclass; its checkpoint keys are the host's own
    from nerfstudio.fields.vanilla_nerf_field import NeRFField

    field = second.pipeline.model.field_fine
    assert isinstance(field, FrustumSPField) and isinstance(field, NeRFField) and field.sp is sp
    assert not any("_sp" in k for k in loaded["pipeline"] if "field_fine" in k)
