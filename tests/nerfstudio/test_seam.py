"""The one seam (sp_plugins.nerfstudio.seam): moved RaySamples for every field a model calls with them."""

from __future__ import annotations

import math

import pytest
import torch
from nerfstudio.cameras.rays import Frustums, RaySamples
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.engine.callbacks import TrainingCallbackLocation
from tests.helpers.ns_configs import run_recording, tiny_radiance_config
from torch import nn

from sp_plugins.adapter.errors import InputError
from sp_plugins.core import AlphaSchedule, SPConfig, StochasticPreconditioner
from sp_plugins.nerfstudio.seam import SeamField, SeamFrustums, attach_seam, check_reached, perturbed_samples

POSITION_METHODS = ("sp-vanilla-nerf", "sp-nerfacto", "sp-tensorf")
BOX = SceneBox(aabb=torch.tensor([[-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]]))


def samples(n_rays=8, n=16, origin=(0.0, 0.0, 4.0), far=8.0, offsets=None):
    o = torch.tensor(origin).expand(n_rays, n, 3)
    d = nn.functional.normalize(torch.tensor([0.0, 0.0, -1.0]) + 0.05 * torch.randn(n_rays, 1, 3), dim=-1).expand(n_rays, n, 3)
    t = torch.linspace(0.5, far, n + 1)
    starts, ends = t[:-1].expand(n_rays, n)[..., None], t[1:].expand(n_rays, n)[..., None]
    return RaySamples(Frustums(origins=o, directions=d, starts=starts, ends=ends, pixel_area=torch.full((n_rays, n, 1), 1e-4),
                               offsets=offsets), camera_indices=torch.zeros(n_rays, n, 1, dtype=torch.long))


def preconditioner(alpha=0.3, boundary="reflect", seed=0, **config):
    sp = StochasticPreconditioner(SPConfig(alpha0=alpha, schedule="constant", boundary=boundary, seed=seed, **config), bounds=BOX.aabb)
    sp.set_step(0, 10)
    return sp.train()


def test_moved_samples_move_every_accessor_by_one_offset_and_leave_the_host_samples_alone():
    rs = samples()
    x = rs.frustums.get_positions().clone()
    start, blob = rs.frustums.get_start_positions().clone(), rs.frustums.get_gaussian_blob()
    moved = perturbed_samples(rs, preconditioner(alpha=0.3))
    q = moved.frustums.get_positions()
    expected = preconditioner(alpha=0.3)(x.reshape(-1, 3)).view(x.shape)  # same seed, same draw
    assert torch.allclose(q, expected, atol=1e-5)
    offset = q - x
    assert torch.allclose(moved.frustums.get_start_positions(), start + offset, atol=1e-5)  # SDF fields
    moved_blob = moved.frustums.get_gaussian_blob()  # MipNeRF: the mean moves, the covariance stays
    assert torch.allclose(moved_blob.mean, blob.mean + offset, atol=1e-5) and torch.allclose(moved_blob.cov, blob.cov)
    inside = (x.abs() <= 1.5).all(-1)
    assert inside.any() and (~inside).any()
    assert (q[inside].abs() <= 1.5 + 1e-5).all()  # reflected into the box
    assert (q - x).abs().mean() == pytest.approx(0.3 * math.sqrt(2 / math.pi), rel=0.2)
    assert torch.equal(rs.frustums.get_positions(), x) and type(rs.frustums) is Frustums  # the host's samples
    assert isinstance(moved.frustums, SeamFrustums) and torch.equal(moved.camera_indices, rs.camera_indices)


def test_existing_offsets_are_kept_and_gradients_reach_the_origins():
    base = torch.full((2, 4, 3), 0.1)
    rs = samples(n_rays=2, n=4, origin=(0.0, 0.0, 1.0), far=1.5, offsets=base.clone())
    origins = rs.frustums.origins.clone().requires_grad_(True)
    rs.frustums.origins = origins
    x = rs.frustums.get_positions().detach()
    moved = perturbed_samples(rs, preconditioner(alpha=1e-3, boundary="none"))
    q = moved.frustums.get_positions()
    assert torch.allclose(q, x, atol=0.01) and not torch.allclose(q, x)  # moved from the offset position
    q.sum().backward()
    assert torch.allclose(origins.grad, torch.ones_like(origins))


class Probe(nn.Module):
    """A field that is not a nerfstudio Field: found by its forward(ray_samples)."""

    def __init__(self, read_positions=True):
        super().__init__()
        self.linear = nn.Linear(3, 1)
        self.read_positions = read_positions
        self.seen = []

    def forward(self, ray_samples, compute_normals=False):
        f = ray_samples.frustums
        self.seen.append(f.get_positions().detach().clone() if self.read_positions else f.directions.clone())
        return {"out": self.linear(f.directions)}


class Holder(nn.Module):
    def __init__(self, **probe):
        super().__init__()
        self.field = Probe(**probe)
        self.sampler_like = nn.Linear(3, 3)  # forward takes no ray_samples: not a field


def test_the_seam_moves_the_samples_a_field_instance_reads_and_records_it():
    model = Holder()
    sp = preconditioner(alpha=1e-2, boundary="none")
    assert attach_seam(model, sp) == ["field"]
    field = model.field
    assert isinstance(field, SeamField) and isinstance(field, Probe) and not isinstance(model.sampler_like, SeamField)
    assert list(field.state_dict()) == list(Probe().state_dict())  # the host's keys
    rs = samples()
    x = rs.frustums.get_positions()
    field.forward(rs)  # models call .forward directly
    field(ray_samples=rs)  # and through __call__ with a keyword
    assert all(not torch.allclose(seen, x) and torch.allclose(seen, x, atol=0.1) for seen in field.seen)
    assert field.sp_handle.perturbed_calls == 2 and "origins" in field.sp_handle.reads
    check_reached(model, "Holder", 0)  # it read the moved positions
    field.eval()
    field.forward(rs)
    assert torch.equal(field.seen[-1], x)  # eval: the plain positions
    field.train()
    moved = perturbed_samples(rs, sp)
    field.forward(moved)  # already moved samples (a field nested in another): not moved twice
    assert torch.equal(field.seen[-1], moved.frustums.get_positions())


def test_num_samples_averages_draws():
    model = Holder()
    attach_seam(model, preconditioner(alpha=1e-2, boundary="none", num_samples=3))
    model.field.forward(samples())
    assert len(model.field.seen) == 3 and model.field.sp_handle.perturbed_calls == 1


def test_a_field_that_reads_no_position_of_its_samples_is_refused_naming_it():
    model = Holder(read_positions=False)
    attach_seam(model, preconditioner(alpha=1e-2, boundary="none"))
    with pytest.raises(InputError, match=r"SP reached no field of Holder"):
        check_reached(model, "Holder", 0)  # not called yet
    model.field.forward(samples())
    with pytest.raises(InputError, match=r"test_seam.Probe \(model.field\) of Holder: it was called with RaySamples but read directions"):
        check_reached(model, "Holder", 0)


def test_plain_submodules_stay_plain():
    """Plain names are attribute paths, nested ones too."""
    model = Holder()
    assert attach_seam(model, preconditioner(), plain={"field": "why"}) == []
    assert not isinstance(model.field, SeamField)
    model = Holder()
    model.outer = nn.Module()
    model.outer.inner = Probe()
    assert attach_seam(model, preconditioner(), plain={"outer.inner": "why"}) == ["field"]
    assert not isinstance(model.outer.inner, SeamField)


@pytest.mark.parametrize("name", POSITION_METHODS)
def test_method_trains_a_few_iterations(name, tiny_scene, tmp_path):
    trainer, record = run_recording(tiny_radiance_config(name, tiny_scene, tmp_path, steps=3))
    assert len(record) == 3
    for step, (loss, parts, metrics) in enumerate(record):
        assert math.isfinite(loss) and all(math.isfinite(v) for v in parts.values())
        assert (metrics["sp_alpha"] > 0) == (step < 2)  # end 1.0: the last step trains the plain field
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
    assert rs.frustums.offsets is None and type(rs.frustums) is Frustums  # the model's samples are untouched
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


def test_nerfacto_box_boundary_must_match_contraction(tiny_scene, tmp_path, monkeypatch):
    """Refused from the config, before the model is built (``ns-train`` checks it before it writes
    config.yml); a contracting field no table knows (a plugin's) is refused after the first step, when
    it has read the moved samples (nerfacto's proposal networks contract too, but are never handed samples)."""
    from sp_plugins.nerfstudio import table

    config = tiny_radiance_config("sp-nerfacto", tiny_scene, tmp_path / "a", steps=3, boundary="reflect")
    with pytest.raises(InputError, match=r"boundary reflect needs a bounded scene, but NerfactoModel contracts space"):
        run_recording(config)
    monkeypatch.setattr(table, "CONTRACTED_MODELS", {})  # as for a model the table does not name
    with pytest.raises(InputError, match=r"NerfactoField \(model.field\) contracts space \(scene contraction is on\)"):
        run_recording(config)
    monkeypatch.undo()
    config = tiny_radiance_config("sp-nerfacto", tiny_scene, tmp_path / "b", steps=2, boundary="reflect")
    config.pipeline.model.disable_scene_contraction = True  # a bounded nerfacto: reflecting is right
    trainer, record = run_recording(config)
    assert len(record) == 2 and trainer.pipeline.model.sp.config.boundary == "reflect"


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
    # end 1.0: SP ends at the last step, 9
    assert sp.alpha == pytest.approx(AlphaSchedule("exponential", 0.05, end_step=9)(loaded["step"] + 1))
    # the seam swapped the class of the field the host built; its checkpoint keys are the host's own
    from nerfstudio.fields.vanilla_nerf_field import NeRFField

    field = second.pipeline.model.field_fine
    assert isinstance(field, SeamField) and isinstance(field, NeRFField) and field.sp is sp
    assert not any("_sp" in k for k in loaded["pipeline"] if "field_fine" in k)


def test_samples_handed_over_unmoved_stop_the_run(monkeypatch):
    """If the offset were drawn but never applied, the reach check says so instead of a silent run."""
    model = Holder()
    sp = preconditioner(alpha=1e-2, boundary="none")
    attach_seam(model, sp)
    monkeypatch.setattr(type(sp), "forward", lambda self, x: x)  # the mutation: positions come back as they went in
    model.field.forward(samples())
    assert "origins" in model.field.sp_handle.reads
    with pytest.raises(InputError, match=r"SP reached the fields of Holder in training step 3 but moved no sample"):
        check_reached(model, "Holder", 3)


@pytest.mark.parametrize("boundary", ["reflect", "clamp"])
def test_a_box_boundary_on_a_field_that_contracts_space_is_refused_after_the_first_step(boundary):
    """Both box boundaries (not only ``reflect``) are refused on a field with a spatial distortion
    that is not an SDF field."""
    model = Holder()
    model.field.spatial_distortion = nn.Identity()  # as nerfacto's field with scene contraction on
    attach_seam(model, preconditioner(alpha=1e-2, boundary=boundary))
    model.field.forward(samples())
    check_reached(model, "Holder", 0, "".join(["no", "ne"]))  # no box (an equal string, as parsed from a command line)
    with pytest.raises(InputError, match=rf"^--pipeline.model.sp.boundary {boundary} needs a bounded scene, but Probe \(model.field\) "
                                          r"contracts space \(scene contraction is on\); pass --pipeline.model.sp.boundary none$"):
        check_reached(model, "Holder", 0, boundary)


class BuiltinForward(nn.Module):
    """A submodule whose ``forward`` is a builtin: ``inspect.signature`` raises ``ValueError``."""

    forward = torch.relu


class NoForward(nn.Module):
    """A submodule whose ``forward`` is not callable: ``inspect.signature`` raises ``TypeError``."""

    forward = None


class NoArguments(nn.Module):
    """A submodule whose ``forward`` takes nothing but ``self``."""

    def forward(self):
        return None


def test_submodules_whose_forward_has_no_readable_signature_are_not_fields():
    """``attach_seam`` walks every submodule a host built; one whose ``forward`` signature cannot be
    read, or that takes no argument, is not a field and does not stop it."""
    model = Holder()
    model.builtin, model.nothing, model.no_arguments = BuiltinForward(), NoForward(), NoArguments()
    assert attach_seam(model, preconditioner()) == ["field"]
    assert type(model.builtin) is BuiltinForward and type(model.nothing) is NoForward and type(model.no_arguments) is NoArguments


class FieldLikeModel(Holder):
    """A model whose own ``forward`` takes ``ray_samples`` (as a field's would)."""

    def forward(self, ray_samples):
        return self.field(ray_samples)


class TensorOrSamples(Probe):
    """A field that is also called with a tensor of positions (no samples to move)."""

    def forward(self, ray_samples, compute_normals=False):
        if isinstance(ray_samples, torch.Tensor):
            return ray_samples * 2.0
        return super().forward(ray_samples, compute_normals)


def test_the_model_itself_is_never_a_seam_field_and_calls_without_samples_are_the_hosts():
    """``attach_seam`` swaps the classes of the model's fields, never the model's own (even when its
    forward takes ``ray_samples``); a seam field called with anything but ``RaySamples`` runs the host's
    forward untouched while training."""
    model = FieldLikeModel()
    model.sp = preconditioner()  # the model owns its preconditioner, as SPModelBase does
    assert attach_seam(model, model.sp) == ["field"]
    assert type(model) is FieldLikeModel and type(model.sp) is StochasticPreconditioner
    holder = Holder()
    holder.field = TensorOrSamples()
    attach_seam(holder, preconditioner())
    x = torch.rand(5, 3)
    assert torch.equal(holder.field.forward(x), x * 2.0) and holder.field.sp_handle.perturbed_calls == 0


def test_a_plain_submodule_does_not_stop_the_fields_after_it():
    """A plain submodule (one ``table.PLAIN_FIELDS`` names, e.g. a background model) listed before a
    field: the field after it still gets the seam."""
    model = Holder()
    model.later = Probe()
    assert attach_seam(model, preconditioner(), plain={"field": "why"}) == ["later"]
    assert isinstance(model.later, SeamField) and not isinstance(model.field, SeamField)


def test_a_move_that_is_not_a_number_or_not_recorded_stops_the_run():
    """A first move of NaN (the perturbation produced no number) is no move, and neither is none
    recorded (largest move 0)."""
    model = Holder()
    attach_seam(model, preconditioner(alpha=1e-2, boundary="none"))
    model.field.sp_handle.perturbed_calls = 1
    with pytest.raises(InputError, match=r"moved no sample \(largest move 0\)"):
        check_reached(model, "Holder", 0)
    model.field.forward(samples())
    model.field.sp_handle.first_move = torch.tensor(float("nan"))
    with pytest.raises(InputError, match=r"moved no sample \(largest move nan\)"):
        check_reached(model, "Holder", 0)


def test_a_field_class_defined_in_a_function_still_gets_the_seam():
    """A field class no path imports (defined in a function, as a plugin's factory may) gets a local
    seam subclass, once per class, and is moved like any other."""

    class LocalProbe(Probe):
        pass

    model = Holder()
    model.field, model.other = LocalProbe(), LocalProbe()
    assert attach_seam(model, preconditioner(alpha=1e-2, boundary="none")) == ["field", "other"]
    assert type(model.field) is type(model.other) and type(model.field).__name__ == "SPField_LocalProbe"
    rs = samples()
    model.field.forward(rs)
    assert not torch.equal(model.field.seen[-1], rs.frustums.get_positions())


def test_an_sp_model_names_the_host_model_it_is_built_on():
    """``sp_host_class()`` of an SP model variant is the host's model class (what presets, tables and
    error lines look up), not one of ours."""
    from nerfstudio.models.vanilla_nerf import NeRFModel

    from sp_plugins.nerfstudio import variants

    assert variants.variant("Model", NeRFModel).sp_host_class() is NeRFModel


@pytest.mark.parametrize("where", ["before", "after"])
def test_sp_training_callbacks_run_at_every_iteration_where_named(where):
    """The host hook SP's schedule and first-step check ride on: nerfstudio runs it at every step, at the
    named place."""
    from sp_plugins.nerfstudio.model import SPModel
    from tests.helpers.exact import check_runs_every_iteration_where_named

    # (sp_training_callback reads nothing of the model)
    check_runs_every_iteration_where_named(lambda record: SPModel.sp_training_callback(None, where, record), where)
