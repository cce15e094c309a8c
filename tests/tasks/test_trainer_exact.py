"""The task trainers' base (sp_plugins.tasks.trainer), exactly: when a fit's per-step numbers are read
from the device (every LOG_EVERY = 25 steps, at a read of ``history`` or a record, at the end of
``run_to_end``) and what they read back, the non-finite stop and its step, ``done``, the seeds of the
field / the SP noise / the batches, the optimizer groups, the checkpoint state, and the plain field's
mesh (grid box, sign count, resolution / refinement arguments) and metrics. A scripted trainer (the
real base class, losses chosen by the test) and a tiny 2-D trainer; an analytic sphere for the mesh.
The mutants each test kills are listed in ``bench/results/mutation_study/kills.json``."""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np
import pytest
import torch
import trimesh
from torch import nn

from sp_plugins.core import SPConfig
from sp_plugins.geometry import largest_component
from sp_plugins.geometry import mesh_metrics as geometry_mesh_metrics
from sp_plugins.tasks import trainer as tr
from sp_plugins.tasks.common import StepTimer
from sp_plugins.tasks.fields import EncodingConfig, NeuralField
from sp_plugins.tasks.settings import MeshedFitSettings
from tests.helpers.exact import gaussian_draws


# --- a trainer whose per-step numbers the test chooses ----------------------------------------------

class Scripted(tr.ResumableTrainer):
    """The real base class; ``step`` reports ``loss(i)`` (a device tensor), ``alpha(i)`` (a float) and
    ``count`` (an int) for step ``i``."""

    def __init__(self, steps=100, loss=lambda i: 0.25 * i, alpha=lambda i: 0.5 ** i, lr=1e-3):
        self.config = SimpleNamespace(steps=steps, lr=lr)
        self.loss, self.alpha = loss, alpha
        self.step_index = 0
        self.history = {}
        self.timer = StepTimer("cpu")

    def step(self):
        i = self.step_index
        return self._finish_step({"loss": torch.tensor(self.loss(i)), "alpha": self.alpha(i), "count": i})


def pending_reads(trainer) -> int:
    """Steps whose numbers have not been read yet (the trainer's own bookkeeping)."""
    return len(trainer.__dict__["_pending"])


def test_each_record_reads_its_own_steps_numbers_as_floats_across_reads():
    """60 steps (two reads at 25 and 50, ten pending): every record gives its own step's loss / alpha /
    count, as Python floats, in order; a key not reported is a KeyError; ``history`` holds all 60."""
    t = Scripted()
    records = [t.step() for _ in range(60)]
    assert pending_reads(t) == 10
    for i, r in enumerate(records):
        assert (r["loss"], r["alpha"], r["count"]) == (0.25 * i, 0.5 ** i, float(i))
        assert type(r["loss"]) is float and type(r["count"]) is float
        assert list(r) == ["loss", "alpha", "count"] and len(r) == 3
        with pytest.raises(KeyError):
            r["lr"]
    assert repr(records[2]) == "StepRecord({'loss': 0.5, 'alpha': 0.25, 'count': 2.0})"
    assert t.history["loss"] == [0.25 * i for i in range(60)] and t.history["count"] == [float(i) for i in range(60)]
    assert all(type(v) is float for v in t.history["loss"] + t.history["alpha"])


def test_numbers_with_no_tensor_are_kept_without_a_device_read():
    """A step that reports only Python numbers is read without stacking anything."""
    t = Scripted(steps=3)
    records = [t._finish_step({"loss": 1.5, "alpha": 2}) for _ in range(3)]
    assert records[1]["loss"] == 1.5 and t.history == {"loss": [1.5] * 3, "alpha": [2.0] * 3}


@pytest.mark.parametrize("bad, raised_at", [(3, 25), (30, 50), (49, 50)])
def test_a_non_finite_loss_stops_at_the_next_read_every_25_steps_naming_its_step(bad, raised_at):
    """The numbers are read after steps 25, 50, ... (not before: a step never waits for its own
    numbers), and a NaN at step ``bad`` stops the fit at the read after it with one line naming that
    step and the lr."""
    t = Scripted(loss=lambda i: float("nan") if i == bad else 1.0, lr=3e-4)
    for n in range(1, raised_at):
        t.step()
        assert pending_reads(t) == n % 25, n
    with pytest.raises(FloatingPointError) as e:
        t.step()
    assert str(e.value) == f"step {bad}: the loss became nan; the fit diverged: lower --lr (now 0.0003, e.g. 10x smaller)"


def test_an_infinite_loss_is_named_at_a_read_of_the_history():
    """Reading ``history`` reads the pending steps at once, +inf included."""
    t = Scripted(loss=lambda i: math.inf if i == 2 else 0.5)
    t.step(), t.step()
    assert t.history["loss"] == [0.5, 0.5] and pending_reads(t) == 0
    t.step()
    with pytest.raises(FloatingPointError, match=r"^step 2: the loss became inf; "):
        t.history


def test_done_exactly_from_the_last_step_on():
    """``done`` is ``step_index >= steps``: not at 0 or steps - 1, at steps and past it (a checkpoint of
    a longer run)."""
    t = Scripted(steps=3)
    seen = []
    for _ in range(3):
        seen.append(t.done)
        t.step()
    assert seen == [False, False, False] and t.done is True
    t.step_index = 1000
    assert t.done is True
    t.step_index, t.config.steps = 2000, 1000  # ints above CPython's small-int cache: ``is`` differs from ==
    assert t.done is True


# --- run_to_end with a stand-in trainer that logs which step's numbers were read --------------------

class Logged(Mapping):
    def __init__(self, log, step):
        self.log, self.step = log, step

    def __getitem__(self, key):
        self.log.append((self.step, key))
        return {"loss": 1234.5678 + self.step, "alpha": 0.0123456}[key]

    def __iter__(self):
        return iter(("loss", "alpha"))

    def __len__(self):
        return 2


class StandIn:
    """What ``run_to_end`` needs: ``step()``, ``done``, ``step_index``, ``config.steps`` (and ``flush``)."""

    def __init__(self, steps, start):
        self.config = SimpleNamespace(steps=steps)
        self.step_index, self.reads, self.flushed_at = start, [], []

    @property
    def done(self):
        return self.step_index >= self.config.steps

    def step(self):
        self.step_index += 1
        return Logged(self.reads, self.step_index)


class Flushing(StandIn):
    def flush(self):
        self.flushed_at.append(self.step_index)


def test_run_to_end_without_progress_reads_nothing_prints_nothing_and_flushes_once(capsys):
    """Resumed at step 4 of 52, with no progress asked: 48 steps, each handed to the callback, none of
    their numbers read, nothing on stderr, ``flush`` once after the last step (a trainer without one
    also runs)."""
    t = Flushing(52, 4)
    got = []
    tr.run_to_end(t, "fitting", callback=lambda trainer, record: got.append((trainer, record.step)))
    assert got == [(t, s) for s in range(5, 53)]
    assert t.reads == [] and t.flushed_at == [52]
    plain = StandIn(3, 0)
    tr.run_to_end(plain, "fitting")
    assert plain.step_index == 3 and plain.reads == []
    assert capsys.readouterr().err == ""


def test_run_to_end_with_progress_shows_loss_and_alpha_every_25_steps_and_at_the_end(capsys):
    """With progress, the numbers are read at steps 25 and 50 and at the last step (52), nowhere else,
    and the bar ends at 52/52 (from 4) with the last step's loss (4 significant digits) and alpha (3)."""
    t = Flushing(52, 4)
    tr.run_to_end(t, "fitting", progress=True)
    assert t.reads == [(25, "loss"), (25, "alpha"), (50, "loss"), (50, "alpha"), (52, "loss"), (52, "alpha")]
    err = capsys.readouterr().err
    last = err.replace("\r", "\n").strip().splitlines()[-1]
    assert last.startswith("fitting: 100%") and "52/52" in last, last
    assert last.endswith("alpha=0.0123, loss=1287]"), last


# --- the set-up every task shares --------------------------------------------------------------------

@dataclass
class TinyConfig(MeshedFitSettings):
    encoding: EncodingConfig = field(default_factory=lambda: EncodingConfig(kind="fourier", frequencies=2))
    sp: SPConfig = field(default_factory=lambda: SPConfig(alpha0=0.25, schedule="constant", boundary="none"))


class Tiny(tr.SDFTrainer):
    """A 2-D fit through the shared set-up, in the order the tasks call it."""

    def __init__(self, config: TinyConfig, scheduler: bool = False) -> None:
        self.config, self.device = config, torch.device("cpu")
        self.field = self._build_field(dim=2, out_dim=1, hidden=config.hidden)
        self.sp_config = self._setup_sp(bounds=(-1.0, 1.0), dim=2)
        self.optimizer = torch.optim.Adam(self._param_groups(self.sp_config))
        if scheduler:
            self.scheduler = torch.optim.lr_scheduler.StepLR(self.optimizer, step_size=1, gamma=0.5)
        self._start_steps()

    def step(self):
        with self.timer:
            alpha = self.sp.step_pre(self.step_index)
            x = torch.rand(4, 2, generator=self.generator) * 2.0 - 1.0
            loss = self.sp.blurred(self.field, x).square().mean()
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            self.optimizer.step()
            if getattr(self, "scheduler", None) is not None:
                self.scheduler.step()
        return self._finish_step({"loss": loss, "alpha": alpha})


def test_set_up_seeds_the_field_the_batches_and_the_noise_from_the_config_seed():
    """seed 7: the field is NeuralField's initialisation after ``manual_seed(7)`` whatever ran before (the
    caller's global stream left as it was), step 0 with empty history, the batches from a generator seeded
    7, and the SP noise, with ``sp.seed`` unset, from seed 7 + 1 = 8 (set: its own)."""
    config = TinyConfig(steps=3, seed=7, hidden=(8,))
    torch.manual_seed(123)
    before = torch.random.get_rng_state()
    t = Tiny(config)
    assert torch.equal(torch.random.get_rng_state(), before)
    torch.manual_seed(7)
    reference = NeuralField(config.encoding, dim=2, out_dim=1, hidden=(8,))
    for (name, p), (_, q) in zip(t.field.named_parameters(), reference.named_parameters()):
        assert torch.equal(p, q), name
    assert t.step_index == 0 and t.done is False and dict(t.history) == {}
    assert torch.equal(torch.rand(4, 2, generator=t.generator), torch.rand(4, 2, generator=torch.Generator().manual_seed(7)))
    assert t.sp_config.seed == 8 and config.sp.seed is None and t.sp.training
    x = torch.zeros(5, 2)
    torch.testing.assert_close((t.sp(x) - x).double(), 0.25 * gaussian_draws((5, 2), 8), rtol=0, atol=1e-6)

    own = Tiny(TinyConfig(steps=3, seed=7, hidden=(8,), sp=SPConfig(alpha0=0.25, schedule="constant", boundary="none", seed=5)))
    assert own.sp_config.seed == 5
    torch.testing.assert_close((own.sp(x) - x).double(), 0.25 * gaussian_draws((5, 2), 5), rtol=0, atol=1e-6)


def test_the_optimizer_groups_are_the_field_at_lr_and_the_alpha_grid_at_its_own_lr():
    """Without an alpha grid one group (every field parameter at ``lr``); with one, a second group with
    the grid's parameters at ``sp.alpha_grid_lr``."""
    plain = Tiny(TinyConfig(steps=3, lr=0.02, hidden=(8,)))
    (group,) = plain.optimizer.param_groups
    assert group["lr"] == 0.02 and [id(p) for p in group["params"]] == [id(p) for p in plain.field.parameters()]
    sp = SPConfig(alpha0=0.25, schedule="constant", boundary="none", alpha_grid=True, alpha_grid_resolution=4, alpha_grid_lr=0.125)
    gridded = Tiny(TinyConfig(steps=3, lr=0.02, hidden=(8,), sp=sp))
    first, second = gridded.optimizer.param_groups
    assert first["lr"] == 0.02 and second["lr"] == 0.125
    assert [id(p) for p in second["params"]] == [id(p) for p in gridded.sp.alpha_grid.parameters()] != []


@pytest.mark.parametrize("scheduler", [False, True])
def test_the_checkpoint_state_holds_the_trajectory_and_a_resume_continues_it_exactly(scheduler):
    """After 2 of 4 steps the state holds the step, the history read so far, the step times, the batch
    generator and, only where there is one, the scheduler; a fresh trainer loaded from it makes steps 3
    and 4 exactly as the uninterrupted one (loss, alpha, field, lr)."""
    config = TinyConfig(steps=4, hidden=(8,), sp=SPConfig(alpha0=0.25, schedule="linear", end=4, boundary="none"))
    a = Tiny(config, scheduler)
    a.step(), a.step()
    state = copy.deepcopy(a.state_dict())  # as written to disk: not the live tensors
    assert state["step"] == 2 and state["history"] == a.history and len(state["history"]["loss"]) == 2
    assert state["step_times"] == a.timer.times and len(state["step_times"]) == 2
    assert torch.equal(state["generator"], a.generator.get_state())
    assert ("scheduler" in state) is scheduler
    if scheduler:
        assert state["scheduler"]["last_epoch"] == 2
    a.step(), a.step()

    b = Tiny(config, scheduler)
    b.load_state_dict(state)
    assert b.step_index == 2 and b.history == state["history"] and b.timer.times == state["step_times"]
    b.step(), b.step()
    assert b.history == a.history and b.done
    for p, q in zip(a.field.parameters(), b.field.parameters()):
        assert torch.equal(p, q)
    assert b.optimizer.param_groups[0]["lr"] == a.optimizer.param_groups[0]["lr"] == (0.001 * 0.5 ** 4 if scheduler else 0.001)


# --- the plain field's mesh and metrics ---------------------------------------------------------------

class Sphere(nn.Module):
    """The SDF of a sphere of radius 0.5 at the origin, ``[*batch, 3] -> [*batch, 1]``."""

    def forward(self, x):
        return x.norm(dim=-1, keepdim=True) - 0.5


class Meshed(tr.SDFTrainer):
    def __init__(self, **kw):
        self.config = MeshedFitSettings(**kw)
        self.device = torch.device("cpu")
        self.field = Sphere()


def test_sdf_is_the_plain_field_with_its_last_axis_squeezed():
    """``sdf`` returns the field's values without the output axis, for any leading shape."""
    x = torch.tensor([[[0.5, 0.0, 0.0], [0.0, 0.0, 0.0], [0.6, 0.8, 0.0]]] * 2)
    assert torch.equal(Meshed().sdf(x), torch.tensor([[0.0, -0.5, 0.5]] * 2))
    assert Meshed().sdf(x[0]).shape == (3,)


def test_the_mesh_is_the_zero_set_on_the_frames_grid_with_its_sign_count(capsys):
    """9^3 points on [-1, 1]^3 (spacing 1/4): the grid points strictly inside the sphere are the integer
    points with i^2 + j^2 + k^2 < 4 (those with = 4 lie on it: SDF exactly 0, not negative); the mesh's
    vertices, bisected 4 times, lie on the sphere. Resolution and refinement from the config unless
    given."""
    t = Meshed(mesh_resolution=9, refine=4)
    mesh, info = t.mesh()
    i = np.arange(-4, 5)
    r2 = i[:, None, None] ** 2 + i[None, :, None] ** 2 + i[None, None, :] ** 2
    assert info == {"negative_fraction": float((r2 < 4).sum()) / 9**3, "resolution": 9, "refine": 4}
    assert (r2 < 4).sum() == 27  # the 3x3x3 block around the centre (i^2 + j^2 + k^2 <= 3)
    radii = np.linalg.norm(mesh.vertices, axis=1)
    assert len(radii) > 20 and np.abs(radii - 0.5).max() < 2e-3
    assert np.allclose(mesh.bounds, [[-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]], atol=0.03)
    _, info = t.mesh(resolution=11, refine=0)
    assert (info["resolution"], info["refine"]) == (11, 0)
    assert capsys.readouterr().err == ""


def test_meshing_with_progress_counts_every_grid_point(capsys):
    """With progress the grid's bar counts ``res^3`` = 729 points and each stage is named."""
    Meshed(mesh_resolution=9, refine=0).mesh(progress=True)
    err = capsys.readouterr().err
    assert "/729 [" in err and "sp-fit: meshing: the field on a 9^3 grid ..." in err
    assert "sp-fit: meshing: marching cubes, 0 bisection steps per vertex: done in" in err


def test_mesh_metrics_are_the_geometry_metrics_raw_and_of_the_largest_component(capsys):
    """A sphere mesh plus a small far box against the sphere: the raw metrics with the config's threshold
    and seed, the ``clean_*`` ones of the sphere alone, ``metric_points`` given or the config's."""
    gt = trimesh.creation.icosphere(2, radius=0.5)
    extra = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    extra.apply_translation((0.9, 0.9, 0.9))
    pred = trimesh.util.concatenate([trimesh.creation.icosphere(1, radius=0.52), extra])
    t = Meshed(metric_points=300, fscore_threshold=0.05, seed=3)
    got = t.mesh_metrics(pred, gt)
    raw = geometry_mesh_metrics(pred, gt, n_points=300, fscore_threshold=0.05, seed=3)
    clean = geometry_mesh_metrics(largest_component(pred), gt, n_points=300, fscore_threshold=0.05, seed=3)
    assert got == dict(raw, **{f"clean_{k}": v for k, v in clean.items() if k not in ("unit", "n_points", "fscore_threshold")})
    assert got["n_points"] == 300 and got["clean_chamfer"] < got["chamfer"]
    assert t.mesh_metrics(pred, gt, metric_points=200)["n_points"] == 200
    assert capsys.readouterr().err == ""
