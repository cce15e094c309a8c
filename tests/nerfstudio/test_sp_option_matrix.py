"""Every SP setting works on every registered method (the matrix), and on nerfstudio's own
methods wrapped by ``sp-train``.

For each SP method, four short runs cover every value of every option at least once (a covering
design, not the full product: the product is 8 x 2 x 2 x 3 x 3 x 4 runs):

| run | alpha grid | num_samples | noise | schedule | boundary |
|---|---|---|---|---|---|
| grid | on | 1 | uniform | linear | reflect |
| multi | off | 2 | squared-gaussian | step | clamp |
| plain | off | 1 | gaussian | exponential | none |
| constant | off | 1 | gaussian | constant | the method's default |

The methods are ours (``sp-*``), the ``sp-train`` configs of nerfstudio's ``nerfacto``,
``vanilla-nerf`` and ``tensorf`` (``sp-train:<method>``: ``sp_methods`` on nerfstudio's own list,
the generic route that builds the host's fields as SP subclasses) and of our ``freenerf-lite``
(SP off by default, switched on by ``sp-train``), shrunk for the CPU.

Each run trains a few iterations on the CPU: every loss is finite, every setting reaches the
model's preconditioner, in every step with alpha > 0 a field is handed samples that moved against
the model's plain ones and reads them, the noise kind shows in the offsets' kurtosis, the evaluation
outputs equal those of the same weights with SP switched off, a learnable alpha grid moves, and
(``plain``) a checkpoint resumes at the same alpha. Options that cannot apply are refused with an
``InputError`` naming the flag:

- a box boundary (``reflect``, ``clamp``) where the scene is contracted (nerfacto's field has a
  ``spatial_distortion``): refused after the first step, once the contracting field has read the
  moved samples; the run then trains with boundary ``none``;
- an alpha grid on TensoRF (ours or nerfstudio's), when the model is built: its encoding detaches
  the positions it reads, so the grid could not learn.

``num_samples 2`` hands fields moved samples exactly twice as often, in every step, as the same
method's ``plain`` run: one test per method runs both itself (it does not depend on test order
or on ``-k``).
"""

from __future__ import annotations

import math

import pytest
import torch
from tests.helpers.ns_configs import in_process_data, shrink_model, sp_train_config
from tests.helpers.sp_fields import sp_fields
from tests.helpers.ns_configs import tiny_sdf_config, run_recording
from tests.helpers.ns_configs import tiny_radiance_config

from sp_plugins.core import AlphaSchedule
from sp_plugins.nerfstudio.runs import configure_run

SDF = ("sp-neus", "sp-neus-hashgrid", "sp-neuralangelo-lite")
RADIANCE = ("sp-relu-field", "sp-mipnerf", "sp-vanilla-nerf", "sp-nerfacto", "sp-tensorf")
SP_TRAIN = "sp-train:"
WRAPPED = ("sp-train:nerfacto", "sp-train:vanilla-nerf", "sp-train:tensorf")
"""nerfstudio's own methods as ``sp-train`` offers them (the generic route)."""
SP_OFF_OURS = ("freenerf-lite",)
"""Our methods with SP off by default that are no one's baseline (``table.SP_OFF_METHODS``)."""
OURS_UNDER_SP_TRAIN = tuple(SP_TRAIN + m for m in SP_OFF_OURS)
"""...and as ``sp-train`` offers them: our model class with SP switched on, not a generic variant."""
METHODS = SDF + RADIANCE + WRAPPED + OURS_UNDER_SP_TRAIN
CONTRACTED = {"sp-nerfacto", "sp-train:nerfacto"}
"""Scene contraction (the fields' ``spatial_distortion``): only boundary "none" applies."""
GRID_CANNOT_LEARN = r"--pipeline\.model\.sp\.alpha-grid True cannot learn on \S+: nerfstudio's TensoRF encoding detaches"
REFUSED = {("sp-tensorf", "grid"): GRID_CANNOT_LEARN, ("sp-train:tensorf", "grid"): GRID_CANNOT_LEARN}
"""Options that cannot apply: nerfstudio's TensoRF encoding detaches its input positions."""
BASELINES = ("neus-hashgrid", "neuralangelo-lite", "relu-field", "relu-field-flat")

RUNS = {
    "grid": dict(alpha_grid=True, alpha_grid_resolution=4, noise="uniform", schedule="linear", boundary="reflect"),
    "multi": dict(num_samples=2, noise="squared-gaussian", schedule="step", boundary="clamp"),
    "plain": dict(noise="gaussian", schedule="exponential", boundary="none"),
    "constant": dict(noise="gaussian", schedule="constant"),
}


def wrapped_config(name, scene, out, *, steps, rays=64, **sp):
    """``sp-train``'s config of built-in ``sp-train:<method>``, CPU-sized; the data manager runs in
    this process (a ``ParallelDataManager`` worker takes seconds to start and is not under test)."""
    config = sp_train_config(name[len(SP_TRAIN):])
    model = config.pipeline.model
    shrink_model(model)
    if hasattr(model, "implementation"):
        model.implementation = "torch"
    in_process_data(config)
    for key, value in sp.items():
        setattr(model.sp, key, value)
    return configure_run(config, scene / "blender", steps=steps, output_dir=out, rays_per_batch=rays)


def matrix_config(name, scene, out, *, steps, **sp):
    sp = {"alpha0": 0.05, "end": 1.0, "seed": 0, **sp}
    if name in SDF:
        config = tiny_sdf_config(name, scene, out, steps=steps, **sp)
    elif name.startswith(SP_TRAIN):
        config = wrapped_config(name, scene, out, steps=steps, **sp)
    else:
        config = tiny_radiance_config(name, scene, out, steps=steps, **sp)
    if name == "sp-neuralangelo-lite":
        config.pipeline.model.c2f_end = 0.1
    return config


def refused_at_build(config, match):
    """Building the trainer (pipeline, model) raises an ``InputError`` that matches ``match``."""
    from sp_plugins.adapter.errors import InputError

    with pytest.raises(InputError, match=match):
        config.setup(local_rank=0, world_size=1).setup()


def runnable(name, settings, scene, out):
    """The settings of run ``settings`` that ``name`` trains with: a box boundary in a contracted
    scene is first checked to be refused (naming the flag), then replaced by "none"."""
    from sp_plugins.adapter.errors import InputError

    boundary = settings.get("boundary", "none")
    if name in CONTRACTED and boundary != "none":
        with pytest.raises(InputError, match=rf"--pipeline\.model\.sp\.boundary {boundary}\b.*contracts space"):
            run_recording(matrix_config(name, scene, out, steps=2, **settings))
        return {**settings, "boundary": "none"}
    return settings


def count_calls(monkeypatch):
    """Count the samples the seam hands to fields that moved against the model's plain samples
    (``n``), and keep the offsets of the first such hand-over (``offsets``); the fields' read records
    say whether they read them."""
    from sp_plugins.nerfstudio import seam

    counter = {"n": 0, "offsets": None}
    plain = seam.perturbed_samples

    def perturbed_samples(samples, sp, *read):
        moved = plain(samples, sp, *read)
        offset = (moved.frustums.get_positions() - samples.frustums.get_positions()).detach()
        if float(offset.abs().max()) > 0:
            counter["n"] += 1
            if counter["offsets"] is None:
                counter["offsets"] = offset.reshape(-1)
        return moved

    monkeypatch.setattr(seam, "perturbed_samples", perturbed_samples)
    return counter


KURTOSIS = {"uniform": (1.4, 2.4), "gaussian": (2.4, 4.5), "squared-gaussian": (5.0, 30.0)}
"""E[d^4] / E[d^2]^2 of the offsets per axis: 1.8 (uniform), 3 (Gaussian), 105/9 (squared Gaussian)."""


def check_noise_kind(offsets, noise, label):
    d = offsets[offsets != 0].double()
    kurtosis = float((d**4).mean() / (d**2).mean() ** 2)
    lo, hi = KURTOSIS[noise]
    assert lo < kurtosis < hi, f"{label}: offsets' kurtosis {kurtosis:.2f} is not that of {noise} noise"


def eval_outputs_equal_sp_off(trainer) -> None:
    """Evaluation never perturbs: the same weights with alpha forced to 0 give identical outputs."""
    pipeline = trainer.pipeline
    model = pipeline.model
    ray_bundle, _ = pipeline.datamanager.next_train(0)
    ray_bundle = ray_bundle[:16] if len(ray_bundle) > 16 else ray_bundle
    model.eval()
    model.sp.set_step(0)
    with torch.no_grad():
        torch.manual_seed(1)
        with_sp = model(ray_bundle)
        alpha = model.sp._alpha
        model.sp._alpha = 0.0
        torch.manual_seed(1)
        without = model(ray_bundle)
        model.sp._alpha = alpha
    assert model.sp.alpha > 0 or model.sp.config.schedule != "constant"
    for key in ("rgb", "accumulation", "depth"):
        if key in with_sp:
            assert torch.equal(with_sp[key], without[key]), f"{key} differs in eval with SP on"


def calls_per_step(name, settings, scene, out, monkeypatch, steps=3):
    """Train ``steps`` iterations; the preconditioner calls (while active) of each iteration."""
    from nerfstudio.engine.trainer import Trainer

    counter, per_step = count_calls(monkeypatch), []
    iteration = Trainer.train_iteration

    def counted(self, step):
        before = counter["n"]
        result = iteration(self, step)
        per_step.append(counter["n"] - before)
        return result

    monkeypatch.setattr(Trainer, "train_iteration", counted)
    try:
        _, record = run_recording(matrix_config(name, scene, out, steps=steps, **settings))
    finally:
        monkeypatch.undo()
    assert len(per_step) == len(record) == steps
    return per_step


@pytest.mark.parametrize("run", list(RUNS))
@pytest.mark.parametrize("name", METHODS)
def test_every_option_trains_and_never_perturbs_eval(name, run, tiny_scene, tmp_path, monkeypatch):
    if (name, run) in REFUSED:
        refused_at_build(matrix_config(name, tiny_scene, tmp_path / "run", steps=3, **RUNS[run]), REFUSED[(name, run)])
        return
    settings = runnable(name, RUNS[run], tiny_scene, tmp_path / "refused")
    config = matrix_config(name, tiny_scene, tmp_path / "run", steps=6 if run == "plain" else 3, **settings)
    counter = count_calls(monkeypatch)
    trainer, record = run_recording(config, stop_after=2 if run == "plain" else None)
    monkeypatch.undo()
    model = trainer.pipeline.model
    sp = model.sp
    assert record and all(math.isfinite(loss) for loss, _, _ in record), f"{name}/{run}: non-finite loss"
    sp_steps = len(record) - (len(record) == config.max_num_iterations and run != "constant")  # end 1.0: the last is plain
    assert counter["n"] >= sp_steps, f"{name}/{run}: no field was handed moved samples in every SP step"
    fields = [f for f in sp_fields(model) if f.sp_handle.perturbed_calls]
    assert fields and all("origins" in f.sp_handle.reads for f in fields), f"{name}/{run}: a field did not read the moved samples"
    check_noise_kind(counter["offsets"], sp.config.noise, f"{name}/{run}")
    for key, value in settings.items():
        assert getattr(sp.config, key) == value, f"{name}: sp.{key} did not reach the model"
    if name in WRAPPED:  # the generic route: the host's fields carry the seam
        assert type(model).__name__.startswith("SPModel__nerfstudio_dmodels_d") and sp_fields(model)
    if name in OURS_UNDER_SP_TRAIN:  # our model class, SP switched on by sp-train
        assert type(model).__module__.startswith("sp_plugins.nerfstudio.") and model.sp.config.enabled and sp_fields(model)
    if run == "grid":
        assert "sp_alpha_grid" in trainer.optimizers.optimizers
        values = sp.alpha_grid.values()
        assert not torch.allclose(values, torch.full_like(values, 0.05), atol=1e-6), f"{name}: the alpha grid did not learn"
    eval_outputs_equal_sp_off(trainer)

    if run == "plain":  # a checkpoint written mid-run resumes at the same step and alpha
        resumed = matrix_config(name, tiny_scene, tmp_path / "resumed", steps=6, **settings)
        resumed.load_dir = config.get_checkpoint_dir()
        second = resumed.setup(local_rank=0, world_size=1)
        second.setup()
        sp2 = second.pipeline.model.sp
        start = second._start_step
        assert 0 < start < 6 and int(sp2.step) == start and sp2._total == 6
        assert sp2.alpha == pytest.approx(AlphaSchedule("exponential", 0.05, end_step=5)(start))  # end 1.0: the last step


@pytest.mark.parametrize("name", BASELINES + SP_OFF_OURS)
@pytest.mark.parametrize("flag", [dict(alpha_grid=True), dict(num_samples=2)])
def test_baselines_refuse_options_that_only_act_through_sp(name, flag, tiny_scene, tmp_path):
    from sp_plugins.adapter.errors import InputError

    build = tiny_sdf_config if name in ("neus-hashgrid", "neuralangelo-lite") else tiny_radiance_config
    config = build(name, tiny_scene, tmp_path, steps=2, **flag)
    assert config.pipeline.model.sp.enabled is False
    with pytest.raises(InputError, match=r"--pipeline\.model\.sp\.(alpha-grid|num-samples).*enabled True"):
        config.setup(local_rank=0, world_size=1).setup()


@pytest.mark.parametrize("name", METHODS)
def test_num_samples_2_draws_twice_per_query_in_every_step(name, tiny_scene, tmp_path, monkeypatch):
    """The ``multi`` run against the same method's ``plain`` run, both run here."""
    plain, multi = (
        calls_per_step(name, runnable(name, RUNS[run], tiny_scene, tmp_path / "box"), tiny_scene, tmp_path / run, monkeypatch)
        for run in ("plain", "multi")
    )
    assert all(n > 0 for n in plain[:-1]) and plain[-1] == 0, f"{name}: moved samples in every step but the (plain) last: {plain}"
    assert multi == [2 * n for n in plain], f"{name}: num_samples 2 is not two draws per query (plain {plain}, multi {multi})"


def test_reflect_on_a_contracted_scene_is_refused(tiny_scene, tmp_path):
    config = tiny_radiance_config("sp-nerfacto", tiny_scene, tmp_path, steps=2, boundary="reflect")
    with pytest.raises(ValueError, match=r"--pipeline\.model\.sp\.boundary reflect"):
        run_recording(config)
