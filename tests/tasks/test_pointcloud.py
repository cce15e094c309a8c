import numpy as np
import pytest
import torch

from sp_plugins import SPConfig
from sp_plugins.tasks.pointcloud import PointCloudSDFConfig, siren_sdf_losses


@pytest.fixture
def small_config(tiny_grid):
    def make(**kw):
        return _small_config(tiny_grid, **kw)

    return make


def _small_config(grid, **kw):
    base = dict(steps=120, surface_batch=512, space_batch=512, hidden=(32, 32), encoding=grid,
                mesh_resolution=48, refine=2, metric_points=5000, lr=3e-3)
    base.update(kw)
    return PointCloudSDFConfig(**base)


def test_siren_terms_vanish_on_an_exact_sdf():
    r = 0.5
    xs = torch.nn.functional.normalize(torch.randn(100, 3), dim=-1) * r
    xo = torch.rand(100, 3) * 2 - 1
    x = torch.cat([xs, xo]).requires_grad_(True)
    f = x.norm(dim=-1) - r
    (g,) = torch.autograd.grad(f.sum(), x)
    terms = siren_sdf_losses(f[:100], g[:100], xs / r, f[100:], g[100:])
    assert terms["surface"].item() < 1e-6
    assert terms["normal"].item() < 1e-6
    assert terms["eikonal"].item() < 1e-6
    flipped = siren_sdf_losses(f[:100], g[:100], -xs / r, f[100:], g[100:])
    assert flipped["normal"].item() == pytest.approx(2.0, abs=1e-5)


def test_a_short_fit_lowers_the_loss_and_finds_the_surface(blob_points, blob_mesh, small_config):
    trainer = small_config(geometric_init=True).setup(blob_points)
    trainer.fit()
    loss = trainer.history["loss"]
    assert np.mean(loss[-10:]) < 0.3 * np.mean(loss[:10])
    mesh, metrics = trainer.evaluate(blob_mesh)
    assert len(mesh.faces) > 0
    assert metrics["completeness"] < 0.03  # the true surface is there (relative to the diagonal)
    assert metrics["negative_fraction"] < 0.5  # geometric init: positive outside


def test_sp_follows_its_schedule_and_baseline_has_none(blob_points, small_config):
    sp = small_config(steps=20, sp=SPConfig(alpha0=0.05, schedule="step", end=0.5)).setup(blob_points)
    base = small_config(steps=20, sp=SPConfig(enabled=False)).setup(blob_points)
    for _ in range(20):
        sp.step()
        base.step()
    assert sp.history["alpha"] == [0.05] * 10 + [0.0] * 10
    assert base.history["alpha"] == [0.0] * 20
    # same seed, same batches, same init: only the perturbation differs, and only while it is on
    assert base.history["loss"][0] != sp.history["loss"][0]
    # after the end SP is off: from the SP run's weights, its step is exactly a plain step
    plain = small_config(steps=20, sp=SPConfig(enabled=False)).setup(blob_points)
    plain.field.load_state_dict(sp.field.state_dict())
    plain.optimizer.load_state_dict(sp.optimizer.state_dict())
    plain.scheduler.load_state_dict(sp.scheduler.state_dict())
    plain.generator.set_state(sp.generator.get_state())
    plain.step_index = sp.step_index = 15
    assert sp.step()["loss"] == plain.step()["loss"]


def test_runs_are_reproducible(blob_points, small_config):
    a = small_config(steps=8).setup(blob_points)
    b = small_config(steps=8).setup(blob_points)
    a.fit()
    b.fit()
    assert a.history["loss"] == b.history["loss"]
    x = torch.rand(50, 3) * 2 - 1
    assert torch.equal(a.sdf(x), b.sdf(x))


def test_the_frame_maps_the_object_into_the_box(blob_points, small_config):
    trainer = small_config(steps=1).setup(blob_points)
    lo, hi = trainer.points.min(0).values, trainer.points.max(0).values
    assert float((hi - lo).norm()) == pytest.approx(1.9, rel=1e-3)
    assert float(trainer.points.abs().max()) < 1.0


def test_bad_settings_are_refused(blob_points, small_config):
    with pytest.raises(ValueError, match="eikonal"):
        small_config(eikonal="cubic").setup(blob_points)
    with pytest.raises(ValueError, match="steps"):
        small_config(steps=0).setup(blob_points)
    with pytest.raises(ValueError, match="alpha0"):
        small_config(sp=SPConfig(alpha0=-1.0)).setup(blob_points)
