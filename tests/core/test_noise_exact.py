"""Exact draws of each noise kind: ``sample_noise`` is the paper's kind computed from the
generator's raw draws (the reference of ``tests/core/test_properties.py``), whatever string object
names the kind. Written for the survivors of the pilot mutation study (``bench/mutation_study.py``
on ``sp_plugins/core/noise.py``)."""

from __future__ import annotations

import pytest
import torch

from sp_plugins.core import NOISE_KINDS, sample_noise
from tests.core.test_properties import noise_reference


def gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


@pytest.mark.parametrize("kind", NOISE_KINDS)
def test_a_kind_named_by_an_equal_string_draws_that_kind(kind):
    """A kind read from a command line or a file is an equal string, not the same object as the
    literal."""
    parsed = "".join(list(kind))  # equal, not interned
    assert parsed == kind and parsed is not kind
    out = sample_noise((64, 3), parsed, generator=gen(3), dtype=torch.float64)
    torch.testing.assert_close(out, noise_reference((64, 3), kind, gen(3), torch.float64), rtol=0, atol=1e-12)


def test_kind_is_a_keyword_and_the_rest_keyword_only():
    """``sample_noise(shape, kind=..., generator=...)`` as documented; ``generator`` cannot be passed by
    position (a third positional argument would silently be taken for it)."""
    out = sample_noise((16,), kind="uniform", generator=gen(1), dtype=torch.float64)
    torch.testing.assert_close(out, noise_reference((16,), "uniform", gen(1), torch.float64), rtol=0, atol=1e-12)
    with pytest.raises(TypeError):
        sample_noise((16,), "uniform", gen(1))
