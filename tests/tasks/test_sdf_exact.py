"""Exact values of the direct SDF-fitting task: in one step the field is queried at the
paper's ``x + alpha * eps`` (K draws averaged) folded into the frame's box ``[-1, 1]^3``, and the
loss is the MAPE of that (mean) prediction against the plain points' distances, computed here
from the raw seeded draws. The mutation of ``sp_plugins/tasks/sdf.py`` each test kills is listed in
``bench/results/mutation_study/kills.json``."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import torch
import trimesh

from sp_plugins import SPConfig
from sp_plugins.geometry import sample_surface
from sp_plugins.tasks import sdf
from sp_plugins.tasks.sdf import SDFFitConfig, mape, signed_distance
from tests.helpers.exact import (
    Recorder, assert_alpha_grid_frozen_once_sp_ends, assert_keyword_only_options, assert_read_folded, sp_draws,
)

SP_SEED = 4


def plain_batch(trainer, seed: int, sizes):
    """The step's plain points and their distances, drawn as the task does from the batch generator
    seeded ``seed``: ``sizes`` points of each group (surface, near, uniform) in turn."""
    g = torch.Generator().manual_seed(seed)
    xs, ds = [], []
    for (pts, dist), n in zip(trainer.groups, sizes):
        idx = torch.randint(len(pts), (n,), generator=g)
        xs.append(pts[idx])
        ds.append(dist[idx])
    return torch.cat(xs), torch.cat(ds)


@pytest.mark.parametrize("k", [1, 3])
def test_one_step_queries_x_plus_alpha_eps_and_fits_the_mean_to_the_plain_distances(k, blob_mesh, tiny_grid):
    """K = 1 and 3: the batch (half surface, a quarter near, a quarter uniform points, drawn from the batch generator) is
    read at ``fold(x + alpha eps_k)`` into [-1, 1]^3 and the loss is MAPE(mean prediction, d(x))."""
    config = SDFFitConfig(steps=4, batch=40, pool=400, hidden=(16,), encoding=tiny_grid,
                          sp=SPConfig(alpha0=0.3, schedule="constant", seed=SP_SEED, num_samples=k))
    trainer = config.setup(blob_mesh)
    field = copy.deepcopy(trainer.field)
    trainer.field = Recorder(trainer.field)
    trainer.step()

    x, d = plain_batch(trainer, config.seed, (20, 10, 10))
    q = assert_read_folded(trainer, x, 0.3, sp_draws(x, k, SP_SEED), -1.0, 1.0)
    with torch.no_grad():
        pred = field(q.float()).squeeze(-1)
        pred = pred.mean(0) if k > 1 else pred
    loss = ((pred - d).abs() / (d.abs() + 0.01)).mean()
    assert trainer.history["loss"][0] == pytest.approx(float(loss), rel=1e-5)


# --- the mutation study's survivors in sdf.py --------------------------------------------

def tiny(grid, **kw) -> SDFFitConfig:
    base = dict(steps=2, batch=9, pool=28, hidden=(16,), encoding=grid, mesh_resolution=8, refine=0, metric_points=100)
    base.update(kw)
    return SDFFitConfig(**base)


def test_the_defaults_are_documented_ones():
    """The README's SP table (``sp-fit sdf``: alpha 0.02, step schedule, end 0.2), Instant-NGP's batch mix
    (8192 per step) from a pool of 100k samples, near-surface offsets of 0.02 in the frame, and the meshed
    tasks' shared settings."""
    c = SDFFitConfig()
    assert (c.steps, c.seed, c.lr, c.hidden) == (2000, 0, 1e-3, (64, 64))
    assert (c.batch, c.pool, c.near_sigma) == (8192, 100_000, 0.02)
    assert (c.frame_diagonal, c.mesh_resolution, c.refine, c.metric_points) == (1.9, 192, 4, 200_000)
    assert (c.sp.enabled, c.sp.alpha0, c.sp.schedule, c.sp.end) == (True, 0.02, "step", 0.2)
    assert (c.sp.noise, c.sp.boundary) == ("gaussian", "reflect")


REQUIRED = "steps >= 1, batch >= 4, pool >= 8, lr > 0 and near_sigma > 0 are required"


@pytest.mark.parametrize("name, refused, accepted", [
    ("steps", 0, 1), ("batch", 3, 4), ("pool", 7, 8), ("lr", 0.0, 1e-12), ("lr", -1e-3, 1e-12),
    ("near_sigma", 0.0, 1e-9), ("near_sigma", -0.02, 1e-9),
])
def test_validation_refuses_exactly_the_documented_values_in_one_line(name, refused, accepted):
    """Each bound at its edge: the first refused value gives the one line ``sp-fit`` prints, the boundary
    value is accepted (batch 4 and pool 8: each of the three groups gets at least one sample)."""
    with pytest.raises(ValueError) as refused_error:
        SDFFitConfig(**{name: refused}).validate()
    assert str(refused_error.value) == REQUIRED
    SDFFitConfig(**{name: accepted}).validate()


def test_a_mesh_resolution_below_8_is_refused_before_training():
    """``sp-fit sdf --mesh-resolution 1`` trained every step and only then failed with a message naming
    no flag (``resolution=1: need at least 2 grid points per axis``); it is refused before anything runs,
    with ``sp-fit pointcloud``'s line, and 8 is accepted."""
    with pytest.raises(ValueError) as refused_error:
        SDFFitConfig(mesh_resolution=7).validate()
    assert str(refused_error.value) == "mesh_resolution=7: use at least 8"
    SDFFitConfig(mesh_resolution=8).validate()


def test_a_mesh_without_faces_is_refused_and_one_face_is_enough(tiny_grid):
    """A mesh without faces is refused in one line; one face is enough."""
    triangle = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]], process=False)
    with pytest.raises(ValueError) as refused:
        tiny(tiny_grid).setup(trimesh.Trimesh(triangle.vertices, np.zeros((0, 3), dtype=int), process=False))
    assert str(refused.value) == "sdf fitting needs a mesh with faces"
    assert len(tiny(tiny_grid).setup(triangle).groups[0][0]) == 14


def test_the_pool_is_half_surface_a_quarter_near_and_the_rest_uniform_with_their_distances(blob_mesh, tiny_grid):
    """pool 28 -> 14 surface points (distance 0), 7 near ones (surface samples 14..20 moved by
    N(0, near_sigma^2), from ``default_rng(seed)``), 7 uniform in [-1, 1]^3 (the same generator, next), with the
    signed distances to the mesh in the frame. (28: no single operator or number change of the split's
    arithmetic gives the same three sizes, e.g. 30 would let ``(pool - n_surface) ^ n_near`` pass.)"""
    config = tiny(tiny_grid, pool=28, near_sigma=0.05, seed=3)
    trainer = config.setup(blob_mesh)
    rng = np.random.default_rng(3)
    surface, _ = sample_surface(trainer.mesh_in_frame, 21, seed=3)
    near = surface[14:] + rng.normal(0.0, 0.05, (7, 3))
    uniform = rng.uniform(-1.0, 1.0, (7, 3))
    d = signed_distance(trainer.mesh_in_frame, np.concatenate([near, uniform]))
    expected = [(surface[:14], np.zeros(14)), (near, d[:7]), (uniform, d[7:])]
    assert [len(pts) for pts, _ in trainer.groups] == [14, 7, 7]
    for (pts, dist), (want_pts, want_dist) in zip(trainer.groups, expected):
        assert torch.equal(pts, torch.as_tensor(want_pts, dtype=torch.float32))
        assert torch.equal(dist, torch.as_tensor(want_dist, dtype=torch.float32))
    assert (d[:7] < 0).any() and (d[:7] > 0).any()  # near points on both sides


def test_signed_distance_in_chunks_and_the_sign_of_an_open_mesh():
    """Any chunk size gives the same distances (here 7 points at a time for 50 points, against the exact
    distances to a sphere); on an open mesh the sign is the side of the closest face's normal (``(p -
    closest) . n < 0`` is inside), and a point in the face's plane is outside."""
    sphere = trimesh.creation.icosphere(3, radius=1.0)
    pts = np.random.default_rng(1).uniform(-1.5, 1.5, (50, 3))
    chunked = signed_distance(sphere, pts, chunk=7)  # first: no freed array of the same size to reuse
    np.testing.assert_allclose(chunked, np.linalg.norm(pts, axis=1) - 1.0, atol=2e-2)
    np.testing.assert_array_equal(signed_distance(sphere, pts), chunked)
    triangle = trimesh.Trimesh([[0, 0, 1], [1, 0, 1], [0, 1, 1]], [[0, 1, 2]], process=False)  # z = 1, normal +z
    np.testing.assert_allclose(signed_distance(triangle, np.array([[0.2, 0.2, 1.5], [0.2, 0.2, 0.5], [2.0, 0.0, 1.0]])),
                               [0.5, -0.5, 1.0], atol=1e-12)


def test_mape_is_instant_ngps_relative_error():
    """``mean(|pred - d| / (|d| + 0.01))``."""
    pred, target = torch.tensor([0.5, -1.0, 0.3], dtype=torch.float64), torch.tensor([0.0, -2.0, 0.1], dtype=torch.float64)
    assert float(mape(pred, target)) == pytest.approx((0.5 / 0.01 + 1.0 / 2.01 + 0.2 / 0.11) / 3, rel=1e-12)
    assert float(mape(pred, target, eps=1.0)) == pytest.approx((0.5 / 1.0 + 1.0 / 3.0 + 0.2 / 1.1) / 3, rel=1e-12)


def test_an_odd_batch_is_split_half_quarter_rest_and_the_field_reads_the_encoding_only(blob_mesh, tiny_grid):
    """batch 9 -> 4 surface, 2 near, 3 uniform samples, drawn in that order from the batch generator; with
    SP off the field reads exactly them, and the loss is MAPE(f(x), d). The MLP reads the hash grid's features
    alone (no coordinates: Instant-NGP's SDF network); Adam has Instant-NGP's betas (0.9, 0.99) and eps
    1e-15."""
    config = tiny(tiny_grid, batch=9, sp=SPConfig(enabled=False))
    trainer = config.setup(blob_mesh)
    assert trainer.field.mlp[0].in_features == tiny_grid.levels * tiny_grid.features_per_level
    group = trainer.optimizer.param_groups[0]
    assert (group["betas"], group["eps"], group["lr"]) == ((0.9, 0.99), 1e-15, config.lr)
    field = copy.deepcopy(trainer.field)
    trainer.field = Recorder(trainer.field)
    trainer.step()
    x, d = plain_batch(trainer, config.seed, (4, 2, 3))
    (read,) = trainer.field.inputs
    assert torch.equal(read, x)
    with torch.no_grad():
        expected = ((field(x).squeeze(-1) - d).abs() / (d.abs() + 0.01)).mean()
    assert trainer.history["loss"][0] == pytest.approx(float(expected), rel=1e-6)


def test_the_learned_alpha_grid_is_left_alone_once_sp_has_ended(blob_mesh, tiny_grid):
    """After the schedule's end SP no longer reads the alpha grid, so Adam must not move it (a parameter
    without a gradient is skipped)."""
    sp = SPConfig(alpha0=0.05, schedule="step", end=0.5, alpha_grid=True, alpha_grid_resolution=4)
    trainer = tiny(tiny_grid, steps=4, sp=sp).setup(blob_mesh)
    assert_alpha_grid_frozen_once_sp_ends(trainer)


def test_evaluate_measures_against_the_input_mesh_and_the_near_samples_quietly(blob_mesh, tiny_grid, capfd):
    """``evaluate()`` compares with the input mesh (in the frame): the same metrics as passing it; a
    mesh given is moved into the frame. ``near_mae`` is the mean |f - d| over the first 20,000 near samples.
    ``evaluate`` and ``fit`` show no progress unless asked."""
    trainer = tiny(tiny_grid, steps=20, batch=64, pool=400, lr=1e-2, sp=SPConfig(enabled=False)).setup(blob_mesh)
    trainer.fit()  # 20 steps: a mesh with faces, so the metrics depend on the ground truth
    mesh, own = trainer.evaluate(resolution=12, metric_points=200)
    _, given = trainer.evaluate(blob_mesh, resolution=12, metric_points=200)
    assert len(mesh.faces) > 0 and math.isfinite(own["chamfer"])
    assert own == given and own["step"] == 20
    _, moved_twice = trainer.evaluate(trainer.mesh_in_frame, resolution=12, metric_points=200)
    assert moved_twice["chamfer"] != own["chamfer"]
    pts = torch.rand(20_001, 3, generator=torch.Generator().manual_seed(0)) * 2 - 1
    with torch.no_grad():
        f = trainer.sdf(pts)
    dist = f + 0.1  # |f - d| = 0.1 for the first 20,000
    dist[-1] = f[-1] + 1e3  # and far off for the one past the cap
    assert abs(float((f[:20_000] + dist[:20_000]).abs().mean()) - 0.1) > 1e-3  # the sum would not give 0.1 (f is near 0: a sign pattern could)
    trainer.groups[1] = (pts, dist)
    _, metrics = trainer.evaluate(resolution=8, metric_points=100)
    assert metrics["near_mae"] == pytest.approx(0.1, rel=1e-4)
    out, err = capfd.readouterr()
    assert (out, err) == ("", "")


def test_device_and_the_evaluation_options_are_keyword_only(blob_mesh, tiny_grid):
    """``SDFFitTrainer(config, mesh, *, device)`` and ``evaluate(gt_mesh, *, resolution, ...)``."""
    assert_keyword_only_options(sdf.SDFFitTrainer, tiny(tiny_grid), blob_mesh, blob_mesh)
