"""The non-finite watch of our nerfstudio models (:mod:`sp_plugins.nerfstudio.divergence`): a NaN
loss stops the run in one line naming its first step and the learning-rate flags; under mixed
precision only a run of non-finite steps does."""

from types import SimpleNamespace

import pytest
import torch
from nerfstudio.engine.callbacks import TrainingCallbackLocation

from sp_plugins.adapter.errors import InputError
from sp_plugins.nerfstudio.divergence import NonFiniteWatch, divergence_callback


def groups():
    return ["fields", "proposal_networks"]


def test_a_nan_loss_stops_naming_its_first_step_the_loss_and_the_flags():
    watch = NonFiniteWatch()
    watch.update({"rgb_loss": torch.tensor(1.0)}, 0)
    watch.raise_if_diverged(0, groups)  # finite: nothing
    watch.update({"rgb_loss": torch.tensor(float("nan")), "eikonal_loss": torch.tensor(0.5)}, 1)
    watch.update({"rgb_loss": torch.tensor(2.0), "eikonal_loss": torch.tensor(0.5)}, 2)
    with pytest.raises(InputError, match=r"^training step 1: the loss became NaN or infinite \(rgb_loss\); .* stopped at step 2 "
                                         r".*--optimizers\.fields\.optimizer\.lr, --optimizers\.proposal-networks\.optimizer\.lr"):
        watch.raise_if_diverged(2, groups)


def test_under_mixed_precision_only_a_run_of_non_finite_steps_stops():
    watch = NonFiniteWatch()
    watch.mixed_precision = True
    inf = {"rgb_loss": torch.tensor(float("inf"))}
    for step in range(NonFiniteWatch.MIXED_PRECISION_RUN - 1):
        watch.update(inf, step)
    watch.update({"rgb_loss": torch.tensor(1.0)}, 9)  # GradScaler skipped the transient infs
    watch.raise_if_diverged(9, groups)
    for step in range(10, 10 + NonFiniteWatch.MIXED_PRECISION_RUN):
        watch.update(inf, step)
    with pytest.raises(InputError, match=r"^training step 0: "):
        watch.raise_if_diverged(19, groups)


@pytest.mark.parametrize("value", [float("inf"), float("-inf"), float("nan")])
def test_without_mixed_precision_one_non_finite_step_stops_even_after_finite_ones(value):
    """Without mixed precision nothing skips a bad step: a single non-finite loss (inf as well as NaN) is a
    divergence, reported with its step after the run went on finite."""
    watch = NonFiniteWatch()
    watch.update({"rgb_loss": torch.tensor(1.0)}, 0)
    watch.update({"rgb_loss": torch.tensor(value)}, 1)
    for step in range(2, 5):
        watch.update({"rgb_loss": torch.tensor(1.0)}, step)
    with pytest.raises(InputError, match=r"^training step 1: the loss became NaN or infinite \(rgb_loss\); .* at step 4 "):
        watch.raise_if_diverged(4, groups)


@pytest.mark.parametrize("value", [float("inf"), float("nan")])
def test_under_mixed_precision_the_run_that_stops_is_exactly_mixed_precision_run_steps_in_a_row(value):
    """Under mixed precision the steps GradScaler skips (up to ``MIXED_PRECISION_RUN - 1`` non-finite steps in a
    row, read while the run is still non-finite) are not a divergence; the ``MIXED_PRECISION_RUN``-th in a row is,
    named by the first non-finite step. A finite step starts the count again: runs that are short, however many,
    never add up."""
    bad = {"rgb_loss": torch.tensor(value)}
    watch = NonFiniteWatch()
    watch.mixed_precision = True
    step = 0
    for _ in range(3):  # three runs one short of the limit, each ended by a finite step
        for _ in range(NonFiniteWatch.MIXED_PRECISION_RUN - 1):
            watch.update(bad, step)
            watch.raise_if_diverged(step, groups)  # read at every step, mid-run: nothing
            step += 1
        watch.update({"rgb_loss": torch.tensor(1.0)}, step)
        watch.raise_if_diverged(step, groups)
        step += 1
    for _ in range(NonFiniteWatch.MIXED_PRECISION_RUN - 1):
        watch.update(bad, step)
        step += 1
    watch.raise_if_diverged(step - 1, groups)
    watch.update(bad, step)  # the limit reached
    with pytest.raises(InputError, match=rf"^training step 0: the loss became NaN or infinite \(rgb_loss\); .* at step {step} "):
        watch.raise_if_diverged(step, groups)


def _attributes(mixed_precision, scaler_on):
    """The trainer's attributes a callback is built from; ``scaler_on`` None: a trainer without a GradScaler."""
    config = SimpleNamespace(mixed_precision=mixed_precision, logging=SimpleNamespace(steps_per_log=10), steps_per_save=0,
                             max_num_iterations=100)
    trainer = SimpleNamespace(config=config, _start_step=0)
    if scaler_on is not None:
        trainer.grad_scaler = SimpleNamespace(is_enabled=lambda: scaler_on)
    return SimpleNamespace(trainer=trainer)


@pytest.mark.parametrize("mixed_precision, scaler_on, skips", [(True, True, True), (True, False, False),
                                                               (False, True, False), (False, False, False)])
def test_the_callback_lets_a_step_pass_only_where_the_grad_scaler_of_a_mixed_precision_run_skips_it(
        mixed_precision, scaler_on, skips):
    """The trainer's callback reads the watch at the logging step; an inf loss there is let pass only when the
    run is in mixed precision *and* its GradScaler is on (what skips such a step); with either off it stops
    the run."""
    watch = NonFiniteWatch()
    callback = divergence_callback(watch, groups, _attributes(mixed_precision, scaler_on))
    assert watch.mixed_precision is skips
    watch.update({"rgb_loss": torch.tensor(float("inf"))}, 0)
    if skips:
        callback.run_callback_at_location(0, TrainingCallbackLocation.AFTER_TRAIN_ITERATION)
    else:
        with pytest.raises(InputError, match=r"^training step 0: "):
            callback.run_callback_at_location(0, TrainingCallbackLocation.AFTER_TRAIN_ITERATION)


def test_a_trainer_without_a_grad_scaler_is_not_mixed_precision():
    """A trainer with ``mixed_precision`` set but no GradScaler (nothing skips its steps) is watched as a full
    precision run."""
    watch = NonFiniteWatch()
    divergence_callback(watch, groups, _attributes(True, None))
    assert watch.mixed_precision is False


def test_a_cause_the_model_knows_comes_before_the_generic_advice_and_none_keeps_the_message():
    watch = NonFiniteWatch()
    watch.update({"rgb_loss": torch.tensor(float("nan"))}, 3)
    with pytest.raises(InputError) as plain:
        watch.raise_if_diverged(3, groups, lambda: None)
    assert "likely cause" not in str(plain.value) and ": lower the learning rate (" in str(plain.value)
    with pytest.raises(InputError) as hinted:
        watch.raise_if_diverged(3, groups, lambda: "the collider")
    assert ": likely cause: the collider; otherwise lower the learning rate (" in str(hinted.value)
    assert len(str(hinted.value).splitlines()) == 1
