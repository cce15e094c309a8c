"""The host wiring of SP in our sdfstudio models (sp_plugins.sdfstudio.model), exactly: the box SP folds
into (the contraction's range, whatever the scene box), the settings refused, which field gets the
preconditioner and what the first-step check names, the training hook's place and rate. Each test names
the mutants of the study (``bench/mutation_study.py``) it was written for; each was shown failing on them."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch
from torch import nn

from sp_plugins.adapter.errors import InputError
from sp_plugins.core import SPConfig
from tests.sdfstudio.test_seam import tiny_field

pytestmark = pytest.mark.usefixtures("patched")


class _Host(nn.Module):
    """An sdfstudio ``SurfaceModel``'s part the wiring reads: its scene box and its SDF field."""


def _model(sp: SPConfig, field=None, aabb=((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0)), cls=None):
    from sp_plugins.sdfstudio.model import SDFFieldSPModel

    cls = cls or type("_Model", (SDFFieldSPModel, _Host), {})
    model = cls.__new__(cls)
    nn.Module.__init__(model)
    model.config = SimpleNamespace(sp=sp)
    model.scene_box = SimpleNamespace(aabb=torch.tensor(aabb))
    if field is not None:
        model.field = field
    return model


@pytest.mark.parametrize("aabb", [((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0)), ((-3.0, 0.0, -0.5), (5.0, 2.0, 0.5))])
def test_sp_folds_into_the_contraction_s_range_whatever_the_scene_box(aabb):
    """sdfstudio's SDF field is queried in contracted space, whose range is ``[-2, 2]^3`` for every
    scene box: the preconditioner's bounds are that range (the scene box only sets the diagonal a
    relative alpha is measured in)."""
    from sp_plugins.sdfstudio.seam import CONTRACTED_BOUNDS

    assert CONTRACTED_BOUNDS == (-2.0, 2.0)
    sp = _model(SPConfig(alpha0=0.1, relative_to_diagonal=True), aabb=aabb).build_preconditioner()
    lo, hi = sp.bounds_lo, sp.bounds_hi
    assert torch.equal(lo.expand(3), torch.full((3,), -2.0)) and torch.equal(hi.expand(3), torch.full((3,), 2.0))
    diagonal = float(torch.linalg.norm(torch.tensor(aabb[1]) - torch.tensor(aabb[0])))
    sp.set_step(0, 100)
    assert sp.alpha == pytest.approx(0.1 * diagonal, rel=1e-6)


@pytest.mark.parametrize("k", [1, 2, 3])
def test_only_one_draw_per_query_is_accepted(k):
    """The contraction moves each query once, so K draws cannot be averaged: K = 1 (the default) is
    accepted, K >= 2 refused naming K and the fix."""
    from sp_plugins.sdfstudio.model import unsupported_setting

    problem = unsupported_setting(SPConfig(num_samples=k))
    if k == 1:
        assert problem == ""
    else:
        assert problem.startswith(f"--pipeline.model.sp.num-samples {k} cannot apply to sdfstudio's SDF methods") and \
            problem.endswith("pass --pipeline.model.sp.num-samples 1")


def test_the_sdf_field_and_its_contraction_get_the_model_s_preconditioner():
    """The preconditioner the model owns (and checkpoints) is the one the SDF field perturbs with, and
    its scene contraction shares the field's handle (the seam is the contraction)."""
    sp_config = SPConfig(alpha0=0.1, boundary="reflect")
    field = tiny_field(numerical=False)
    model = _model(sp_config, field)
    model.sp = model.build_preconditioner()
    model.attach_sp()
    assert field.sp is model.sp and field.spatial_distortion.sp_handle is field.sp_handle


def test_a_field_that_is_not_the_seam_s_is_refused_naming_it():
    model = _model(SPConfig(), field=nn.Linear(3, 1))
    model.sp = model.build_preconditioner()
    with pytest.raises(TypeError, match=r"^_Model: SP needs the SDF field built from an SeamSDFFieldConfig, got Linear"):
        model.attach_sp()
    bare = _model(SPConfig())
    bare.sp = bare.build_preconditioner()
    with pytest.raises(TypeError, match=r"got NoneType"):
        bare.attach_sp()


def test_averaged_draws_are_refused_when_the_model_is_built_and_the_field_is_left_plain():
    """``attach_sp`` refuses ``num_samples`` 2 (runs not started by ``sp-sdfstudio-train``, which checks
    first) before the field gets a preconditioner."""
    field = tiny_field(numerical=False)
    model = _model(SPConfig(num_samples=2), field)
    model.sp = model.build_preconditioner()
    with pytest.raises(InputError, match=r"^--pipeline\.model\.sp\.num-samples 2 cannot apply"):
        model.attach_sp()
    assert field.sp_handle is None
    ok = _model(SPConfig(num_samples=1), tiny_field(numerical=False))
    ok.sp = ok.build_preconditioner()
    ok.attach_sp()  # K = 1: no refusal
    assert ok.field.sp is ok.sp


def test_the_first_step_check_names_the_host_model_and_the_step():
    """A field no training query went through stops the run naming the host model class (not ours) and
    the step it checked."""
    from sp_plugins.sdfstudio.model import SDFFieldSPModel

    class NeuSLikeModel(_Host):
        pass

    # in the module the real variants live in (sp_host_class: the first base not of sp_plugins)
    cls = type("SPNeuSLike", (SDFFieldSPModel, NeuSLikeModel), {"__module__": "sp_plugins.sdfstudio.variants"})
    assert cls.sp_host_class() is NeuSLikeModel
    model = _model(SPConfig(), tiny_field(numerical=False), cls=cls)
    model.sp = model.build_preconditioner()
    model.attach_sp()
    with pytest.raises(InputError, match=r"^SP reached no SDF query of NeuSLikeModel in training step 4:"):
        model.check_sp_reached(4)


@pytest.mark.parametrize("where", ["before", "after"])
def test_sp_training_callbacks_run_at_every_iteration_where_named(where):
    """The host hook SP's schedule and first-step check ride on: at every step, at the named place."""
    from sp_plugins.sdfstudio.model import SPModel
    from tests.helpers.exact import check_runs_every_iteration_where_named

    check_runs_every_iteration_where_named(lambda record: SPModel.sp_training_callback(None, where, record), where)


def test_the_run_length_is_read_where_sdfstudio_keeps_it_and_it_says_no_start_step():
    """sdfstudio: ``config.max_num_iterations`` on the attributes (no trainer), so SP keeps the step its
    checkpoint loaded (no start step)."""
    from sp_plugins.sdfstudio.model import SPModel

    assert SPModel.sp_run_length(None, SimpleNamespace(config=SimpleNamespace(max_num_iterations=40.0))) == (40, None)
    assert SPModel.sp_run_length(None, SimpleNamespace(trainer=SimpleNamespace(_start_step=3))) == (None, None)
