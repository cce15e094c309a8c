"""Every SP setting works on every registered method (issue 12's matrix).

For each SP method, four short runs cover every value of every option at least once (a covering
design, not the full product: the product is 8 x 2 x 2 x 3 x 3 x 4 runs):

| run | alpha grid | num_samples | noise | schedule | boundary |
|---|---|---|---|---|---|
| grid | on | 1 | uniform | linear | reflect (none where the scene is contracted) |
| multi | off | 2 | squared-gaussian | step | clamp (none where contracted) |
| plain | off | 1 | gaussian | exponential | none |
| constant | off | 1 | gaussian | constant | the method's default |

Each run (but the refused ones: an alpha grid on sp-tensorf, whose host encoding detaches its
input positions) trains a few iterations on the CPU: every loss is finite, the evaluation outputs equal
those of the same weights with SP switched off, and (``plain``) a checkpoint resumes at the same
alpha. ``multi`` calls the preconditioner exactly twice as often per step as ``plain``. Options
that cannot apply are refused at configuration time, naming the flag.
"""

from __future__ import annotations

import math

import pytest
import torch
from ns_tiny import _tiny_config, run_recording
from radiance_tiny import tiny_radiance_config

from sp_plugins.core import AlphaSchedule

SDF = ("sp-neus", "sp-neus-hashgrid", "sp-neuralangelo-lite")
RADIANCE = ("sp-relu-field", "sp-mipnerf", "sp-vanilla-nerf", "sp-nerfacto", "sp-tensorf")
CONTRACTED = {"sp-nerfacto"}  # scene contraction: only boundary "none" applies
REFUSED = {("sp-tensorf", "grid"): r"--pipeline\.model\.sp\.alpha-grid True cannot learn on sp-tensorf"}
"""Options that cannot apply: nerfstudio's TensoRF encoding detaches its input positions."""
BASELINES = ("neus-hashgrid", "neuralangelo-lite", "relu-field", "relu-field-flat")

RUNS = {
    "grid": dict(alpha_grid=True, alpha_grid_resolution=4, noise="uniform", schedule="linear", boundary="reflect"),
    "multi": dict(num_samples=2, noise="squared-gaussian", schedule="step", boundary="clamp"),
    "plain": dict(noise="gaussian", schedule="exponential", boundary="none"),
    "constant": dict(noise="gaussian", schedule="constant"),
}


def matrix_config(name, scene, out, *, steps, **sp):
    sp = {"alpha0": 0.05, "end": 1.0, "seed": 0, **sp}
    if name in CONTRACTED and "boundary" in sp:
        sp["boundary"] = "none"
    if name in SDF:
        config = _tiny_config(name, scene, out, steps=steps, **sp)
    else:
        config = tiny_radiance_config(name, scene, out, steps=steps, **sp)
    if name == "sp-neuralangelo-lite":
        config.pipeline.model.c2f_end = 0.1
    return config


def count_calls(monkeypatch):
    """Count every preconditioner forward call (a class-level patch: hooks call ``sp(x)``)."""
    from sp_plugins.core import StochasticPreconditioner

    counter = {"n": 0}
    plain = StochasticPreconditioner.forward

    def forward(self, x):
        counter["n"] += int(self.active)
        return plain(self, x)

    monkeypatch.setattr(StochasticPreconditioner, "forward", forward)
    return counter


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


@pytest.fixture(scope="module")
def calls_per_step():
    return {}


@pytest.mark.parametrize("run", list(RUNS))
@pytest.mark.parametrize("name", SDF + RADIANCE)
def test_every_option_trains_and_never_perturbs_eval(name, run, tiny_scene, tmp_path, calls_per_step, monkeypatch):
    settings = RUNS[run]
    if (name, run) in REFUSED:
        from sp_plugins.nerfstudio.errors import InputError

        config = matrix_config(name, tiny_scene, tmp_path / "run", steps=3, **settings)
        with pytest.raises(InputError, match=REFUSED[(name, run)]):
            config.setup(local_rank=0, world_size=1).setup()
        return
    config = matrix_config(name, tiny_scene, tmp_path / "run", steps=6 if run == "plain" else 3, **settings)
    counter = count_calls(monkeypatch)
    trainer, record = run_recording(config, stop_after=2 if run == "plain" else None)
    monkeypatch.undo()
    sp = trainer.pipeline.model.sp
    assert record and all(math.isfinite(loss) for loss, _, _ in record), f"{name}/{run}: non-finite loss"
    for key, value in settings.items():
        expected = "none" if (key == "boundary" and name in CONTRACTED) else value
        assert getattr(sp.config, key) == expected, f"{name}: sp.{key} did not reach the model"
    if run == "grid":
        assert "sp_alpha_grid" in trainer.optimizers.optimizers
        values = sp.alpha_grid.values()
        assert not torch.allclose(values, torch.full_like(values, 0.05), atol=1e-6), f"{name}: the alpha grid did not learn"
    if run in ("multi", "plain"):
        calls_per_step[(name, run)] = counter["n"] / len(record)
        if (name, "plain") in calls_per_step and (name, "multi") in calls_per_step:
            plain, multi = calls_per_step[(name, "plain")], calls_per_step[(name, "multi")]
            assert plain > 0 and multi == pytest.approx(2 * plain), f"{name}: num_samples 2 is not two draws per query"
    eval_outputs_equal_sp_off(trainer)

    if run == "plain":  # a checkpoint written mid-run resumes at the same step and alpha
        resumed = matrix_config(name, tiny_scene, tmp_path / "resumed", steps=6, **settings)
        resumed.load_dir = config.get_checkpoint_dir()
        second = resumed.setup(local_rank=0, world_size=1)
        second.setup()
        sp2 = second.pipeline.model.sp
        start = second._start_step
        assert 0 < start < 6 and int(sp2.step) == start and sp2._total == 6
        assert sp2.alpha == pytest.approx(AlphaSchedule("exponential", 0.05, end_step=6)(start))


@pytest.mark.parametrize("name", BASELINES)
@pytest.mark.parametrize("flag", [dict(alpha_grid=True), dict(num_samples=2)])
def test_baselines_refuse_options_that_only_act_through_sp(name, flag, tiny_scene, tmp_path):
    from sp_plugins.nerfstudio.errors import InputError

    build = _tiny_config if name in ("neus-hashgrid", "neuralangelo-lite") else tiny_radiance_config
    config = build(name, tiny_scene, tmp_path, steps=2, **flag)
    assert config.pipeline.model.sp.enabled is False
    with pytest.raises(InputError, match=r"--pipeline\.model\.sp\.(alpha-grid|num-samples).*enabled True"):
        config.setup(local_rank=0, world_size=1).setup()


def test_reflect_on_a_contracted_scene_is_refused(tiny_scene, tmp_path):
    config = tiny_radiance_config("sp-nerfacto", tiny_scene, tmp_path, steps=2, boundary="reflect")
    with pytest.raises(ValueError, match=r"--pipeline\.model\.sp\.boundary reflect"):
        config.setup(local_rank=0, world_size=1).setup()
