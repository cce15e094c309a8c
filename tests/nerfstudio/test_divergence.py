"""The non-finite watch of our nerfstudio models (:mod:`sp_plugins.nerfstudio.divergence`): a NaN
loss stops the run in one line naming its first step and the learning-rate flags; under mixed
precision only a run of non-finite steps does."""

import pytest
import torch

from sp_plugins.adapter.errors import InputError
from sp_plugins.nerfstudio.divergence import NonFiniteWatch


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
