"""Where SP enters sdfstudio's SDFField: one offset per sample, shared by the stencil; the
gradient at the perturbed point; samplers and evaluation see the plain field."""

from __future__ import annotations

import math

import pytest
import torch

pytestmark = pytest.mark.usefixtures("patched")

N_RAYS, N_SAMPLES = 4, 5
ALPHA = 0.05


def tiny_field(numerical: bool, **changes):
    from nerfstudio.field_components.spatial_distortions import SceneContraction

    from sp_plugins.sdfstudio.seam import SeamSDFFieldConfig

    config = SeamSDFFieldConfig(
        use_grid_feature=True, num_layers=2, hidden_dim=32, geo_feat_dim=15, num_layers_color=2, hidden_dim_color=32,
        num_levels=4, log2_hashmap_size=11, base_res=8, max_res=64, inside_outside=False,
        use_numerical_gradients=numerical, **changes,
    )
    aabb = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    return config.setup(aabb=aabb, num_images=2, spatial_distortion=SceneContraction(order=float("inf")))


def preconditioner():
    from sp_plugins.core import SPConfig
    from sp_plugins.sdfstudio.seam import CONTRACTED_BOUNDS

    sp = SPConfig(alpha0=ALPHA, schedule="constant", seed=0).setup(bounds=CONTRACTED_BOUNDS)
    sp.set_step(0)
    return sp


def ray_samples():
    from nerfstudio.cameras.rays import Frustums, RaySamples

    g = torch.Generator().manual_seed(1)
    origins = torch.tensor([0.0, 0.0, 3.0]).expand(N_RAYS, N_SAMPLES, 3).contiguous()
    directions = torch.nn.functional.normalize(torch.randn(N_RAYS, 1, 3, generator=g) * 0.1 + torch.tensor([0.0, 0.0, -1.0]), dim=-1)
    directions = directions.expand(N_RAYS, N_SAMPLES, 3).contiguous()
    starts = torch.linspace(2.5, 3.5, N_SAMPLES).view(1, N_SAMPLES, 1).expand(N_RAYS, N_SAMPLES, 1).contiguous()
    frustums = Frustums(origins=origins, directions=directions, starts=starts, ends=starts + 0.1, pixel_area=torch.ones_like(starts))
    return RaySamples(frustums=frustums, camera_indices=torch.zeros(N_RAYS, N_SAMPLES, 1, dtype=torch.long), deltas=torch.full_like(starts, 0.1))


class Spy:
    """Records the positions of every ``forward_geonetwork`` call of one field."""

    def __init__(self, field) -> None:
        self.calls = []
        real = field.forward_geonetwork

        def spy(x):
            self.calls.append(x.detach().clone())
            return real(x)

        field.forward_geonetwork = spy


def plain_positions(samples):
    return samples.frustums.get_start_positions().reshape(-1, 3)


def test_training_query_is_perturbed_once_and_the_stencil_shares_the_offset():
    field, sp = tiny_field(numerical=True, fd_step=0.01), preconditioner()
    field.use_preconditioner(sp)
    field.train(), sp.train()
    spy, samples = Spy(field), ray_samples()
    field(samples, return_alphas=True)
    centre, stencil = spy.calls
    x = plain_positions(samples)
    offset = centre - x
    assert offset.abs().max() > 0 and 0.5 * ALPHA < offset.std() < 2 * ALPHA
    stencil = stencil.view(6, -1, 3) - centre  # sdfstudio stacks the six points first
    eye = torch.eye(3)
    expected = torch.stack([eye[0], -eye[0], eye[1], -eye[1], eye[2], -eye[2]])[:, None, :] * 0.01
    torch.testing.assert_close(stencil, expected.expand_as(stencil), rtol=0, atol=1e-6)


def test_analytic_normal_is_the_gradient_at_the_perturbed_point():
    from nerfstudio.field_components.field_heads import FieldHeadNames

    field, sp = tiny_field(numerical=False), preconditioner()
    field.use_preconditioner(sp)
    field.train(), sp.train()
    spy, samples = Spy(field), ray_samples()
    out = field(samples)
    q = spy.calls[0].requires_grad_(True)
    sdf = field.forward_geonetwork(q)[:, :1]
    (expected,) = torch.autograd.grad(sdf.sum(), q)
    torch.testing.assert_close(out[FieldHeadNames.GRADIENT].reshape(-1, 3), expected, rtol=1e-5, atol=1e-6)
    assert not torch.allclose(q.detach(), plain_positions(samples))


def test_eval_and_samplers_see_the_plain_field():
    field, sp = tiny_field(numerical=True, fd_step=0.01), preconditioner()
    field.use_preconditioner(sp)
    samples = ray_samples()
    field.train(), sp.train()
    spy = Spy(field)
    field.get_sdf(samples)  # the NeuS up-sampler
    torch.testing.assert_close(spy.calls[-1], plain_positions(samples), rtol=0, atol=0)
    sp.eval(), field.eval()  # model.eval() switches both: sp is a submodule of the model
    field(samples, return_alphas=True)
    torch.testing.assert_close(spy.calls[-2], plain_positions(samples), rtol=0, atol=0)


def test_sampler_queries_are_perturbed_when_asked():
    field, sp = tiny_field(numerical=False, perturb_sampler_queries=True), preconditioner()
    field.use_preconditioner(sp)
    field.train(), sp.train()
    spy, samples = Spy(field), ray_samples()
    field.get_sdf(samples)
    assert not torch.allclose(spy.calls[-1], plain_positions(samples))


def test_fixed_fd_step_wins_over_the_host_schedule_and_checkpoint_keys_match_the_host():
    from nerfstudio.fields.sdf_field import SDFFieldConfig

    field = tiny_field(numerical=True, fd_step=0.02)
    field.set_numerical_gradients_delta(0.5)  # what Neuralangelo's callback would do
    assert math.isclose(field.numerical_gradients_delta, 0.02)
    assert math.isclose(tiny_field(numerical=True).numerical_gradients_delta, 1e-4)  # host default kept
    host = tiny_field(numerical=True)
    plain_config = SDFFieldConfig(**{k: v for k, v in vars(host.config).items() if k in SDFFieldConfig.__dataclass_fields__ and k != "_target"})
    plain = plain_config.setup(aabb=host.aabb.data, num_images=2)
    assert set(field.state_dict()) == set(plain.state_dict())


def test_a_config_yml_saved_with_the_seams_old_class_names_loads(tmp_path):
    """An earlier release renamed the sdfstudio seam's field to ``SeamSDFField``; a config.yml saved before names
    ``SPSDFFieldConfig`` / ``SPSDFField``. The module defines no alias: the host's registry entry
    maps the old paths (``Host.renamed``), which our commands' config reader and, through the module's
    ``__getattr__``, any YAML loader (sdfstudio's own commands) read."""
    import yaml
    from nerfstudio.configs.method_configs import method_configs

    from sp_plugins.adapter.safe_config import load_run_config
    from sp_plugins.sdfstudio.registration import with_sp
    from sp_plugins.sdfstudio.seam import SeamSDFField, SeamSDFFieldConfig

    text = yaml.dump(with_sp(method_configs["neus"]).config)
    assert "sp_plugins.sdfstudio.seam.SeamSDFFieldConfig" in text and "SPSDFField" not in text
    (tmp_path / "config.yml").write_text(text.replace("seam.SeamSDFField", "seam.SPSDFField"))
    field = load_run_config(tmp_path / "config.yml", "--load-config").pipeline.model.sdf_field
    assert type(field) is SeamSDFFieldConfig and field._target is SeamSDFField
    import sp_plugins.sdfstudio.seam as seam

    assert "SPSDFField" not in vars(seam) and "SPSDFFieldConfig" not in vars(seam)
    plain = yaml.load((tmp_path / "config.yml").read_text(), Loader=yaml.Loader).pipeline.model.sdf_field  # the host's loader
    assert type(plain) is SeamSDFFieldConfig and plain._target is SeamSDFField
    with pytest.raises(AttributeError, match="has no attribute 'NoSuchField'"):
        seam.NoSuchField


def test_the_reach_check_refuses_a_field_without_sp_and_a_move_that_is_missing_or_not_a_number():
    """No handle on the field (SP never handed to it), calls counted without a recorded move, and a
    NaN move: each stops the run with its one line."""
    from torch import nn

    from sp_plugins.adapter.errors import InputError
    from sp_plugins.adapter.field import PreconditionerHandle
    from sp_plugins.sdfstudio.seam import check_reached

    model = nn.Module()
    model.field = nn.Module()
    with pytest.raises(InputError, match=r"^SP reached no SDF query of NeuSModel in training step 2: "):
        check_reached(model, "NeuSModel", 2)
    model.field.sp_handle = PreconditionerHandle(None)
    model.field.sp_handle.perturbed_calls = 3
    with pytest.raises(InputError, match=r"moved no position \(largest move 0\)"):
        check_reached(model, "NeuSModel", 2)
    model.field.sp_handle.first_move = torch.tensor(float("nan"))
    with pytest.raises(InputError, match=r"moved no position \(largest move nan\)"):
        check_reached(model, "NeuSModel", 2)


def test_queries_that_sp_does_not_move_leave_no_reach_record():
    """Evaluation, and a field whose handle holds no preconditioner, query the plain field and leave
    the reach record empty (no count, no first move of 0 that would fail the check of a later
    training step)."""
    field, sp = tiny_field(numerical=False), preconditioner()
    field.use_preconditioner(sp)
    field.eval(), sp.eval()
    field(ray_samples())
    assert field.sp_handle.perturbed_calls == 0 and field.sp_handle.first_move is None
    field.train(), sp.train()
    field(ray_samples())
    assert field.sp_handle.perturbed_calls == 1 and float(field.sp_handle.first_move) > 0
    field.use_preconditioner(None)
    spy, samples = Spy(field), ray_samples()
    field(samples)
    torch.testing.assert_close(spy.calls[0], plain_positions(samples), rtol=0, atol=0)


def test_the_seam_fields_constructor_has_the_hosts_parameters_and_defaults():
    """``SeamSDFField`` is built wherever sdfstudio builds its ``SDFField``: the same parameters with
    the same defaults (a caller that leaves one out gets the host's behaviour)."""
    import inspect

    from nerfstudio.fields.sdf_field import SDFField

    from sp_plugins.sdfstudio.seam import SeamSDFField

    ours, host = inspect.signature(SeamSDFField.__init__).parameters, inspect.signature(SDFField.__init__).parameters
    assert [(p.name, p.default) for p in ours.values()] == [(p.name, p.default) for p in host.values()]
    assert tiny_field(numerical=False).use_average_appearance_embedding is False
