"""``reflect``, ``apply_boundary`` and ``as_bounds`` (sp_plugins.core.boundary) exactly: the fold compared with the
mod-2 mirror of ``tests/core/test_properties.py`` (values and gradients) for origins of every broadcast layout the
sparse fold distinguishes (same shape, a suffix of ``y``'s shape, a scalar, a non-suffix such as ``[N, 1]`` or
``[1, dim]``), on a cube and on non-cubic boxes, in the sparse and the dense fold; coordinates exactly on a wall;
the clamp's inside test at the walls; kinds given as parsed strings. The mutants each test kills are listed in
``bench/results/mutation_study/kills.json``.

Surviving mutants left as equivalent (no input in the functions' contract tells them apart):
``bounds.dim() == 2`` -> ``!= 2`` / ``== 1`` / ``== 3`` / ``>= 2`` / ``< 2`` (``bounds[0], bounds[1]`` and ``lo, hi =
bounds`` take the same two rows of any tensor that has two); ``len(shape) - origin.dim()`` -> ``**`` / ``*`` / ``<<`` /
``^`` / ``|`` / ``+`` and ``tuple(...) == tuple(origin.shape)`` -> ``<=`` / ``is``, ``origin.shape == shape`` -> ``is``
(they only send a broadcastable origin to the expand path or the suffix path where both give the same origins);
``flipped = idx[:0]`` -> ``idx[:1]`` / ``idx[:-1]`` (idx is empty there); ``squeeze(1)`` -> ``squeeze(0)`` (an
``[M, 1]`` index tensor gives the same values and gradients); ``&`` -> ``*`` on bool tensors (logical and);
``min(v) == max(v)`` -> ``is`` (both return ``v[0]`` when all are equal, distinct floats otherwise); ``kind ==
"clamp"`` -> ``<=`` (only "clamp" and "reflect" reach it; "reflect" > "clamp"); ``device.type == "cpu"`` -> ``<=``
(no torch device type sorts before "cpu"); removed ``@staticmethod`` on ``_dense`` / ``backward`` (both called
through the class)."""

import zlib

import pytest
import torch

from sp_plugins.core.boundary import apply_boundary, as_bounds, dense_fold, reflect, sparse_fold_on

from .test_properties import fold_reference

F64 = torch.float64

# (lo, hi) as given to ``reflect`` / ``apply_boundary``: a cube as scalars, a cube as [dim] tensors, a non-cube
# whose lo is the same on every axis (a Python float start, a tensor width), a fully non-cubic box.
BOXES = {
    "cube-scalars": (0.0, 1.0),
    "cube-tensors": (torch.full((3,), -0.5, dtype=F64), torch.full((3,), 1.5, dtype=F64)),
    "same-lo": (torch.zeros(3, dtype=F64), torch.tensor([1.0, 2.0, 3.0], dtype=F64)),
    "non-cube": (torch.tensor([-1.0, 0.0, 0.5], dtype=F64), torch.tensor([1.0, 2.0, 3.0], dtype=F64)),
}


def _box(name):
    lo, hi = BOXES[name]
    return torch.as_tensor(lo, dtype=F64).expand(3), torch.as_tensor(hi, dtype=F64).expand(3)


def _reference(y, lo, hi, origin):
    """The fold of ``y`` where ``origin`` (broadcast to ``y``) is inside ``[lo, hi]``, ``y`` elsewhere."""
    folded = fold_reference(y, lo, hi)
    if origin is None:
        return folded
    keep = (origin >= lo) & (origin <= hi)
    return torch.where(keep, folded, y)


def _origins(kind, k, n, lo, hi, g):
    """Origins of layout ``kind`` for draws ``[k, n, 3]`` (``k == 0``: ``[n, 3]``): inside the box, with some
    rows / axes outside it (which must be left alone)."""
    shape = (n, 3) if k == 0 else (k, n, 3)
    mid, half = (lo + hi) * 0.5, (hi - lo) * 0.5
    if kind == "same":
        o = mid + half * (torch.rand(shape, generator=g, dtype=F64) * 2 - 1)
        o.view(-1, 3)[::3] += 5.0 * half  # every third point outside on every axis
        o.view(-1)[1::7] -= 7.0  # and scattered coordinates outside
        return o
    if kind == "suffix":  # [n, 3] origins of [k, n, 3] draws (``idx % origin.numel()``)
        o = mid + half * (torch.rand(n, 3, generator=g, dtype=F64) * 2 - 1)
        o[::3] += 5.0 * half
        o.view(-1)[1::5] -= 7.0
        return o
    if kind == "rows":  # [n, 1]: one value per point on every axis (the expand path)
        o = torch.full((n, 1), 0.25, dtype=F64) * (hi.min() - lo.max()).clamp(min=0) + lo.max()
        o = torch.where(torch.arange(n)[:, None] % 2 == 1, o, torch.full_like(o, 50.0))
        return o
    if kind == "axes":  # [1, 3]: one value per axis for every point (the expand path)
        o = mid.clone()
        o[1] = hi[1] + 3.0  # the middle axis' origin is outside
        return o[None]
    if kind == "scalar":  # a 0-d origin (inside the box on every axis)
        return (lo.max() + hi.min()) * 0.5
    raise AssertionError(kind)


def _draws(k, n, lo, hi, g):
    shape = (n, 3) if k == 0 else (k, n, 3)
    mid, half = (lo + hi) * 0.5, (hi - lo) * 0.5
    return mid + half * 7.0 * (torch.rand(shape, generator=g, dtype=F64) * 2 - 1)  # most coordinates fold, some many times


def _check(y, lo_in, hi_in, origin, lo, hi, sparse):
    y = y.clone().requires_grad_(True)
    out = reflect(y, lo_in, hi_in, origin, sparse=sparse)
    yr = y.detach().clone().requires_grad_(True)
    ref = _reference(yr, lo, hi, origin)
    torch.testing.assert_close(out, ref, rtol=0, atol=1e-12)
    w = torch.linspace(0.5, 1.5, y.numel(), dtype=F64).view(y.shape)  # a non-uniform upstream gradient
    (gy,) = torch.autograd.grad((out * w).sum(), y)
    (gr,) = torch.autograd.grad((ref * w).sum(), yr)
    torch.testing.assert_close(gy, gr, rtol=0, atol=1e-12)  # +-w, to rounding


@pytest.mark.parametrize("sparse", [True, False])
@pytest.mark.parametrize("box", list(BOXES))
@pytest.mark.parametrize(
    "layout,k",
    [("none", 0), ("same", 0), ("same", 4), ("suffix", 4), ("rows", 0), ("rows", 3), ("axes", 0), ("axes", 3), ("scalar", 0), ("scalar", 3)],
)
def test_reflect_equals_the_mirror_for_every_origin_layout(layout, k, box, sparse):
    """``reflect(y, lo, hi, origin)`` equals the mod-2 mirror where the origin is inside the box and ``y`` elsewhere,
    values and gradients (+-1 per fold), for origins of ``y``'s shape, ``[N, dim]`` origins of ``[K, N, dim]`` draws,
    ``[N, 1]`` / ``[1, dim]`` origins (broadcast, not a suffix), a 0-d origin, on cubes and non-cubic boxes, sparse and
    dense."""
    g = torch.Generator().manual_seed(zlib.crc32(f"{layout}{k}{box}".encode()))
    lo_in, hi_in = BOXES[box]
    lo, hi = _box(box)
    n = 10
    y = _draws(k, n, lo, hi, g)
    origin = None if layout == "none" else _origins(layout, k, n, lo, hi, g)
    if origin is not None:
        keep = ((origin >= lo) & (origin <= hi)).expand(y.shape)
        assert keep.any() and (layout == "scalar" or not keep.all())  # both branches are exercised
    _check(y, lo_in, hi_in, origin, lo, hi, sparse)


@pytest.mark.parametrize("box", ["cube-scalars", "non-cube"])
def test_dense_fold_context_matches_the_sparse_fold(box):
    """``with dense_fold():`` the default fold (``sparse=None``) is the dense one and gives the same values and
    gradients as the mirror; ``sparse_fold_on`` is True on the CPU and False inside the block."""
    g = torch.Generator().manual_seed(5)
    lo_in, hi_in = BOXES[box]
    lo, hi = _box(box)
    y = _draws(3, 6, lo, hi, g)
    origin = _origins("suffix", 3, 6, lo, hi, g)
    assert sparse_fold_on(torch.device("cpu")) is True
    with dense_fold():
        assert sparse_fold_on(torch.device("cpu")) is False
        _check(y, lo_in, hi_in, origin, lo, hi, None)
    assert sparse_fold_on(torch.device("cpu")) is True
    assert sparse_fold_on(torch.device("meta")) is False
    _check(y, lo_in, hi_in, origin, lo, hi, None)


@pytest.mark.parametrize("sparse", [True, False])
def test_a_coordinate_on_a_wall_or_an_even_number_of_widths_away_has_derivative_plus_one(sparse):
    """On the box [0, 2] (scalars and a non-cube): ``y`` exactly at ``lo``, at ``lo -+ 2 w`` and ``hi + w`` (an even
    number of widths from ``lo``, where the fold's ``d`` is exactly 0) folds to ``lo`` with derivative +1, as the
    mirror's (``t = 0 <= 1``)."""
    for lo_in, hi_in in [(0.0, 2.0), (torch.tensor([0.0, -1.0, 1.0], dtype=F64), torch.tensor([2.0, 3.0, 2.0], dtype=F64))]:
        lo, hi = torch.as_tensor(lo_in, dtype=F64).expand(3), torch.as_tensor(hi_in, dtype=F64).expand(3)
        w = hi - lo
        y = torch.stack([lo, lo - 2 * w, lo + 2 * w, hi + w, lo + 4 * w, hi]).requires_grad_(True)
        out = reflect(y, lo_in, hi_in, sparse=sparse)
        expected = torch.stack([lo, lo, lo, lo, lo, hi])
        torch.testing.assert_close(out, expected, rtol=0, atol=1e-12)
        (gy,) = torch.autograd.grad(out.sum(), y)
        torch.testing.assert_close(gy, torch.ones_like(gy), rtol=0, atol=0)
        yr = y.detach().clone().requires_grad_(True)
        (gr,) = torch.autograd.grad(fold_reference(yr, lo, hi).sum(), yr)
        torch.testing.assert_close(gy, gr, rtol=0, atol=0)


def test_as_bounds_layouts_and_its_default_check():
    """``as_bounds`` gives the same ``[dim]`` pair for scalars, ``[dim]`` tensors, a tuple of two 1-D tensors and a
    ``[2, dim]`` tensor (nerfstudio's aabb); by default it refuses an empty box with its exact message."""
    like = torch.zeros(1, dtype=F64)
    lo, hi = torch.tensor([-1.0, 0.0, 0.5], dtype=F64), torch.tensor([1.0, 2.0, 3.0], dtype=F64)
    for bounds in [(lo, hi), torch.stack([lo, hi]), (lo.tolist(), hi.tolist())]:
        a, b = as_bounds(bounds, 3, like)
        assert a.dtype == F64 and a.shape == (3,) and b.shape == (3,)
        assert torch.equal(a, lo) and torch.equal(b, hi)
    a, b = as_bounds((0.0, 1.0), 3, like)
    assert torch.equal(a, torch.zeros(3, dtype=F64)) and torch.equal(b, torch.ones(3, dtype=F64))
    empty = torch.stack([hi, lo])
    with pytest.raises(ValueError) as err:
        as_bounds(empty, 3, like)
    assert str(err.value) == (
        "bounds: the box is empty (lo=[1.0, 2.0, 3.0], hi=[-1.0, 0.0, 0.5]); every lo must be < hi"
    )
    with pytest.raises(ValueError, match="the box is empty"):
        as_bounds((1.0, 1.0), 3, like)
    a, b = as_bounds(empty, 3, like, check=False)  # skipped on request
    assert torch.equal(a, hi) and torch.equal(b, lo)


def test_clamp_counts_an_origin_on_a_wall_as_inside():
    """``apply_boundary(y, "clamp", (lo, hi), origin)``: coordinates whose origin is on ``lo`` or on ``hi`` (inside)
    are clamped, those whose origin is outside (just past either wall) are left alone."""
    lo, hi = torch.tensor([-1.0, 0.0, 0.5], dtype=F64), torch.tensor([1.0, 2.0, 3.0], dtype=F64)
    eps = 1e-9
    origin = torch.stack([lo, hi, lo - eps, hi + eps, (lo + hi) / 2])
    y = torch.stack([lo - 0.5, hi + 0.5, lo - 0.5, hi + 0.5, hi + 4.0])
    out = apply_boundary(y, "clamp", (lo, hi), origin)
    expected = torch.stack([lo, hi, lo - 0.5, hi + 0.5, hi])
    torch.testing.assert_close(out, expected, rtol=0, atol=0)
    torch.testing.assert_close(apply_boundary(y, "clamp", (lo, hi)), torch.stack([lo, hi, lo, hi, hi]), rtol=0, atol=0)


def test_reflect_keeps_an_origin_on_a_wall_inside():
    """``apply_boundary(..., "reflect", ...)`` with origins on ``lo`` / ``hi`` folds, just outside leaves alone,
    sparse and dense."""
    lo, hi = torch.tensor([-1.0, 0.0, 0.5], dtype=F64), torch.tensor([1.0, 2.0, 3.0], dtype=F64)
    eps = 1e-9
    origin = torch.stack([lo, hi, lo - eps, hi + eps])
    y = torch.stack([lo - 0.5, hi + 0.5, lo - 0.5, hi + 0.5])
    expected = torch.stack([lo + 0.5, hi - 0.5, lo - 0.5, hi + 0.5])
    torch.testing.assert_close(apply_boundary(y, "reflect", (lo, hi), origin), expected, rtol=0, atol=1e-12)
    with dense_fold():
        torch.testing.assert_close(apply_boundary(y, "reflect", (lo, hi), origin), expected, rtol=0, atol=1e-12)


def test_kinds_named_by_parsed_strings_behave_like_the_literals():
    """A kind read from a config (equal to the literal, not the same object): ``"none"`` returns ``y`` itself, even
    with no bounds and with ``y`` outside a given box; ``"clamp"`` clamps."""
    none, clamp, refl = "".join(list("none")), "".join(list("clamp")), "".join(list("reflect"))
    literal = "none"
    assert none == literal and none is not literal  # the point of the test
    y = torch.tensor([[-3.0, 0.5, 7.0]], dtype=F64)
    assert apply_boundary(y, none, None) is y
    assert apply_boundary(y, none, (0.0, 1.0)) is y
    lo, hi = torch.zeros(3, dtype=F64), torch.ones(3, dtype=F64)
    torch.testing.assert_close(apply_boundary(y, clamp, (lo, hi)), torch.tensor([[0.0, 0.5, 1.0]], dtype=F64))
    torch.testing.assert_close(apply_boundary(y, refl, (lo, hi)), fold_reference(y, lo, hi), rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="needs bounds"):
        apply_boundary(y, clamp, None)
