"""Finite-difference stencils (sp_plugins.core.stencil), exactly: on a two-dimensional batch, with kinds named by
parsed strings, and every unknown kind refused, by every function that takes one. (``tests/core/test_stencil.py``
checks accuracy on one batch dimension, where axis 1 is axis -1.) The mutants each test kills are listed in
``bench/results/mutation_study/kills.json``."""

import pytest
import torch

from sp_plugins.core import stencil
from sp_plugins.core.stencil import finite_differences, stencil_gradient, stencil_laplacian, stencil_offsets


def quadratic(p):
    """f = x^2 + 2 y^2 + 3 z^2 + x: gradient (2x + 1, 4y, 6z), Laplacian 12, exact up to rounding for both stencils
    (no cross term: the tetrahedron's first-order error is in the cross terms)."""
    x, y, z = p.unbind(-1)
    return x * x + 2 * y * y + 3 * z * z + x


@pytest.mark.parametrize("kind", ["6pt", "4pt"])
def test_gradient_and_laplacian_on_a_two_dimensional_batch(kind):
    """Centres [2, 5, 3] with their values [2, 5]: the gradient [2, 5, 3] and the Laplacian [2, 5] of a quadratic,
    exact up to rounding."""
    c = torch.rand(2, 5, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    grad, lap = finite_differences(quadratic, c, 1e-3, kind, centre_values=quadratic(c))
    x, y, z = c.unbind(-1)
    torch.testing.assert_close(grad, torch.stack([2 * x + 1, 4 * y, 6 * z], -1), rtol=0, atol=1e-8)
    torch.testing.assert_close(lap, torch.full((2, 5), 12.0, dtype=torch.float64), rtol=0, atol=1e-4)


def test_kinds_named_by_parsed_strings_and_by_keyword(monkeypatch):
    """Equal strings that are not the literals (as a parsed flag) build the same offsets, gradient and Laplacian,
    also when the offsets are not cached yet; the kind may be passed by keyword."""
    c = torch.rand(7, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    for kind in ("6pt", "4pt"):
        literal = [t.clone() for t in (stencil_offsets(kind, dtype=torch.float64), *finite_differences(quadratic, c, 1e-3, kind, quadratic(c)))]
        monkeypatch.setattr(stencil, "_OFFSETS", {})
        parsed = "".join(list(kind))
        again = (stencil_offsets(kind=parsed, dtype=torch.float64), *finite_differences(quadratic, c, 1e-3, parsed, quadratic(c)))
        for a, b in zip(literal, again):
            assert torch.equal(a, b)


@pytest.mark.parametrize("kind", ["3pt", "8pt", "", "6PT"])
def test_an_unknown_kind_is_refused_by_every_function(kind, monkeypatch):
    """Kinds that sort before "4pt", after "6pt" or between them are refused with the line, by the offsets, the
    gradient and the Laplacian (which used to take any kind as "4pt", silently; before ``check_stencil_kind``
    the offsets' ``kind == "6pt"`` -> ``>=`` and ``kind == "4pt"`` -> ``<=`` survived too)."""
    monkeypatch.setattr(stencil, "_OFFSETS", {})
    message = f"^stencil={kind!r} is not a stencil; allowed values: 6pt, 4pt$"
    values = torch.zeros(2, 6)
    for call in (lambda: stencil_offsets(kind), lambda: stencil_gradient(values, 0.1, kind),
                 lambda: stencil_laplacian(values, torch.zeros(2), 0.1, kind)):
        with pytest.raises(ValueError, match=message):
            call()
