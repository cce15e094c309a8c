"""The learnable alpha grid (sp_plugins.core.alpha_grid), exactly: what it reads at a position
(linear interpolation of the stored values between cell centres that sit on the bounds, clamped at
the edge, then mapped to alpha), each parameterisation's map both ways, the checkpoint conversion,
its refusals at their edges and what it exports. The reference interpolation below is written from
the definition, one point at a time. The mutants each test kills are listed in
``bench/results/mutation_study/kills.json``."""

from __future__ import annotations

import itertools
import math
import re

import numpy as np
import pytest
import torch

from sp_plugins.core.alpha_grid import AlphaGrid, map_figure_size

KINDS = ("log", "alpha", "softplus")


def parsed(word: str) -> str:
    """An equal string that is not the literal (as tyro hands over a flag's value)."""
    return "".join(list(word))


def reference_read(values: np.ndarray, lo, hi, x: np.ndarray) -> float:
    """Linear interpolation of ``values`` (``[H, W]`` or ``[D, H, W]``, last axis x) at one point
    ``x`` (x first), cell centres at ``lo + i (hi - lo) / (n - 1)``, clamped to the edge."""
    dim = values.ndim
    sizes = values.shape[::-1]  # along x, y(, z)
    lower, weights = [], []
    for axis in range(dim):
        t = (x[axis] - lo[axis]) / (hi[axis] - lo[axis]) * (sizes[axis] - 1)
        t = min(max(t, 0.0), sizes[axis] - 1.0)
        i = min(int(math.floor(t)), sizes[axis] - 2)
        lower.append(i)
        weights.append(t - i)
    total = 0.0
    for corner in itertools.product((0, 1), repeat=dim):
        w = 1.0
        index = []
        for axis, bit in enumerate(corner):
            w *= weights[axis] if bit else 1.0 - weights[axis]
            index.append(lower[axis] + bit)
        total += w * values[tuple(reversed(index))]
    return total


def ramp(shape, seed=0) -> torch.Tensor:
    """Positive, distinct alphas in [0.05, 0.5] (every cell tells apart)."""
    return 0.05 + 0.45 * torch.rand(shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


@pytest.mark.parametrize("kind", KINDS)
def test_a_2d_grid_reads_the_interpolated_alpha_of_its_stored_values_on_uneven_bounds(kind):
    """A 2D grid on uneven bounds reads, at each point, the bilinear interpolation of its stored values mapped to
    alpha by its parameterisation."""
    lo, hi = (-0.5, 1.0), (2.5, 3.0)
    grid = AlphaGrid(dim=2, resolution=(5, 4), init=0.1, bounds=(lo, hi), parameterization=kind)
    grid.set_values(ramp((4, 5)))
    stored = grid.param.detach().double()[0, 0].numpy()
    to_alpha = {"log": np.exp, "alpha": lambda r: np.maximum(r, 0.0), "softplus": lambda r: np.log1p(np.exp(r))}[kind]
    points = np.array([[-0.5, 1.0], [2.5, 3.0], [0.1, 1.3], [1.7, 2.9], [2.49, 1.01], [0.0, 2.0], [1.25, 1.5]])
    got = grid(torch.tensor(points, dtype=torch.float32)).detach().double().numpy()[:, 0]
    want = [to_alpha(reference_read(stored, lo, hi, p)) for p in points]
    np.testing.assert_allclose(got, want, rtol=2e-5)


def test_a_3d_grid_reads_its_corners_exactly_and_clamps_outside_its_bounds():
    """A 3D grid reads its node values exactly at the nodes, and a point outside its bounds as the nearest border."""
    grid = AlphaGrid(dim=3, resolution=(3, 4, 2), init=0.1, bounds=(-2.0, 1.0))
    values = ramp((2, 4, 3), seed=1)
    grid.set_values(values)
    for k, j, i in itertools.product(range(2), range(4), range(3)):
        x = torch.tensor([[-2.0 + 3.0 * i / 2, -2.0 + 3.0 * j / 3, -2.0 + 3.0 * k / 1]])
        assert float(grid(x).detach()) == pytest.approx(float(values[k, j, i]), rel=1e-5)
    far = torch.tensor([[-9.0, -9.0, -9.0], [9.0, 9.0, 9.0], [-9.0, 9.0, 0.25]])
    corner, logs = values.numpy(), grid.param.detach().double()[0, 0].numpy()  # log: interpolated, then exp
    want = [corner[0, 0, 0], corner[1, 3, 2], math.exp(reference_read(logs, (-2, -2, -2), (1, 1, 1), np.array([-2.0, 1.0, 0.25])))]
    np.testing.assert_allclose(grid(far).detach().double().numpy()[:, 0], want, rtol=1e-5)


def test_a_batch_of_any_shape_reads_alpha_in_that_shape():
    """A batch of points of any shape reads one alpha per point, in that shape."""
    grid = AlphaGrid(dim=3, resolution=4, init=0.2)
    grid.set_values(ramp((4, 4, 4), seed=2))
    x = torch.rand(3, 5, 7, 3, generator=torch.Generator().manual_seed(0)) * 2 - 1
    a = grid(x)
    assert a.shape == (3, 5, 7, 1)
    assert torch.equal(a.reshape(-1, 1), grid(x.reshape(-1, 3)))


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("alpha", [1e-4, 0.03, 0.7, 5.0])
def test_each_parameterisation_stores_what_maps_back_to_alpha(kind, alpha):
    """Each parameterisation stores log alpha, alpha or inverse softplus alpha, which maps back to the alpha set."""
    grid = AlphaGrid(dim=2, resolution=3, init=alpha, parameterization=kind)
    stored = {"log": math.log(alpha), "alpha": alpha, "softplus": math.log(math.expm1(alpha))}[kind]
    assert torch.allclose(grid.param.double(), torch.full((1, 1, 3, 3), stored, dtype=torch.float64), rtol=1e-6, atol=1e-7)
    assert torch.allclose(grid.values().double(), torch.full((3, 3), alpha, dtype=torch.float64), rtol=1e-5)


def test_an_alpha_grid_reads_a_negative_stored_value_as_zero():
    """The ``alpha`` parameterisation reads a negative stored value as zero."""
    grid = AlphaGrid(dim=2, resolution=2, init=0.5, parameterization="alpha")
    with torch.no_grad():
        grid.param.copy_(torch.tensor([[[[-0.3, 0.2], [0.0, 0.9]]]]))
    assert torch.allclose(grid.values(), torch.tensor([[0.0, 0.2], [0.0, 0.9]]))


@pytest.mark.parametrize("kind", KINDS)
def test_a_parameterisation_named_by_a_parsed_string_reads_as_the_literal(kind):
    """A parameterisation named by a parsed (equal, not identical) string stores and reads as the literal."""
    literal = AlphaGrid(dim=2, resolution=3, init=0.3, parameterization=kind)
    other = AlphaGrid(dim=2, resolution=3, init=0.3, parameterization=parsed(kind))
    assert torch.equal(other.param, literal.param)
    assert torch.equal(other.values(), literal.values())


@pytest.mark.parametrize("stored, loaded", list(itertools.permutations(KINDS, 2)))
def test_a_checkpoint_of_another_parameterisation_loads_as_the_same_alphas(stored, loaded):
    """A checkpoint of one parameterisation loads into another as the same alphas (from 1e-4 to 0.5)."""
    source = AlphaGrid(dim=2, resolution=(3, 2), init=0.1, parameterization=stored)
    values = torch.tensor([[1e-4, 0.02, 0.5], [0.3, 0.001, 0.07]], dtype=torch.float64)
    source.set_values(values)
    target = AlphaGrid(dim=2, resolution=(3, 2), init=0.1, parameterization=loaded)
    target.load_state_dict(source.state_dict())
    assert torch.allclose(target.values().double(), values, rtol=1e-4)


@pytest.mark.parametrize("loaded", ["log", "softplus"])
def test_an_alpha_checkpoint_with_a_zero_cell_loads_into_a_finite_grid(loaded):
    """An ``alpha`` grid stores 0 where Adam pushed a cell below it; loaded into a log or softplus
    grid it must stay finite (a -inf stored value reads NaN wherever interpolation gives it weight
    0)."""
    state = {"alpha": torch.tensor([[[[0.0, 0.2], [0.3, 0.4]]]])}
    grid = AlphaGrid(dim=2, resolution=2, init=0.1, parameterization=loaded)
    grid.load_state_dict(state)
    assert bool(torch.isfinite(grid.param).all())
    x = torch.tensor([[1.0, 1.0], [-1.0, 1.0], [0.0, 0.0], [-1.0, -1.0]])  # the last: the zero cell itself
    a = grid(x).detach()[:, 0]
    assert bool(torch.isfinite(a).all()) and float(a[-1]) < 1e-20
    assert a[:2].tolist() == pytest.approx([0.4, 0.3], rel=1e-5)


def test_a_checkpoint_that_stores_two_parameterisations_is_refused():
    """Which of two stored grids is meant is not knowable: the first is converted and the other is
    an unexpected key (strict loading refuses it)."""
    grid = AlphaGrid(dim=2, resolution=2, init=0.1, parameterization="softplus")
    state = {"log_alpha": torch.zeros(1, 1, 2, 2), "alpha": torch.full((1, 1, 2, 2), 0.4)}
    with pytest.raises(RuntimeError, match=r'Unexpected key\(s\) in state_dict: "alpha"'):
        grid.load_state_dict(state)


def test_the_defaults_are_a_3d_grid_of_128_cells_at_alpha_003_on_the_unit_cube():
    """The defaults: a 3D log grid of 128 cells per axis at alpha 0.03 on [-1, 1]^3."""
    grid = AlphaGrid()
    assert (grid.dim, tuple(grid.param.shape), grid.init, grid.parameterization) == (3, (1, 1, 128, 128, 128), 0.03, "log")
    assert grid.lo.tolist() == [-1.0] * 3 and grid.hi.tolist() == [1.0] * 3
    assert float(grid.values()[0, 0, 0]) == pytest.approx(0.03, rel=1e-6)


@pytest.mark.parametrize("init", [0.0, -0.5, math.inf, math.nan, -math.inf])
def test_an_initial_alpha_that_is_not_a_finite_positive_number_is_refused(init):
    """An initial alpha that is not a finite number > 0 (zero, negative, infinite, NaN) is refused in one line."""
    with pytest.raises(ValueError, match=r"^init=.*: the initial alpha must be a finite number > 0$"):
        AlphaGrid(dim=2, resolution=2, init=init)


@pytest.mark.parametrize("init", [1e-6, 0.5, 3.0])
def test_a_small_or_large_positive_initial_alpha_is_accepted(init):
    """Any finite positive initial alpha, small or large, is accepted and read back."""
    assert float(AlphaGrid(dim=2, resolution=2, init=init).values().mean()) == pytest.approx(init, rel=1e-5)


@pytest.mark.parametrize("dim, resolution", [(3, (4, 4)), (3, (4, 4, 4, 4)), (2, (4,)), (2, 1), (3, (4, 1, 4)), (2, (2, 0))])
def test_a_resolution_of_the_wrong_length_or_under_two_cells_is_refused(dim, resolution):
    """A resolution with too few or too many sizes, or a size under two cells, is refused in one line."""
    with pytest.raises(ValueError, match=rf"^resolution=.*: need {dim} sizes, each >= 2$"):
        AlphaGrid(dim=dim, resolution=resolution)


@pytest.mark.parametrize("dim, resolution", [(2, 2), (3, (2, 3, 2)), (2, (2, 7))])
def test_two_cells_per_axis_is_enough(dim, resolution):
    """Two cells per axis is accepted; the grid has the resolution's shape."""
    res = [resolution] * dim if isinstance(resolution, int) else list(resolution)
    assert tuple(AlphaGrid(dim=dim, resolution=resolution).param.shape[2:]) == tuple(reversed(res))


@pytest.mark.parametrize("dim", [1, 4])
def test_a_grid_that_is_not_2d_or_3d_is_refused(dim):
    with pytest.raises(ValueError, match=rf"^dim={dim}: an alpha grid is 2D or 3D$"):
        AlphaGrid(dim=dim, resolution=2)


@pytest.mark.parametrize("bad", [
    torch.full((3, 2), 0.1),   # the transpose: a larger first size
    torch.full((2, 2), 0.1),   # smaller
    torch.full((2, 4), 0.1),   # larger last size
    torch.full((1, 2, 3), 0.1),  # one more axis
])
def test_set_values_refuses_a_grid_of_another_shape(bad):
    """``set_values`` refuses values of another shape, naming the shape needed and the one given."""
    grid = AlphaGrid(dim=2, resolution=(3, 2), init=0.1)
    with pytest.raises(ValueError, match=rf"^set_values: need \(2, 3\) positive alphas, got {re.escape(str(tuple(bad.shape)))}$"):
        grid.set_values(bad)


@pytest.mark.parametrize("bad_value", [0.0, -0.2])
def test_set_values_refuses_an_alpha_that_is_not_positive(bad_value):
    """``set_values`` refuses a zero or negative alpha and leaves the grid unchanged."""
    grid = AlphaGrid(dim=2, resolution=(3, 2), init=0.1)
    values = torch.full((2, 3), 0.1)
    values[1, 2] = bad_value
    with pytest.raises(ValueError, match=r"^set_values: need \(2, 3\) positive alphas, got \(2, 3\)$"):
        grid.set_values(values)
    assert torch.allclose(grid.values(), torch.full((2, 3), 0.1))  # unchanged


def test_its_repr_names_dim_shape_init_and_parameterisation():
    """Its repr names the dimension, the stored shape, the initial alpha and the parameterisation."""
    grid = AlphaGrid(dim=3, resolution=(4, 3, 2), init=0.025, parameterization="softplus")
    assert grid.extra_repr() == "dim=3, shape=(2, 3, 4), init=0.025, parameterization=softplus"


@pytest.mark.parametrize("shape, size", [
    ((10, 10), (5.0, 5.5)),         # square
    ((20, 10), (5.0, 10.5)),        # twice as tall
    ((10, 40), (5.0, 1.75)),        # four times as wide
    ((8, 25611), (5.0, 1.0)),       # wider than 10:1: clamped at 0.1
    ((25611, 8), (5.0, 50.5)),      # taller than 10:1: clamped at 10
])
def test_a_2d_maps_figure_is_5_inches_wide_and_as_tall_as_its_clamped_aspect(shape, size):
    """A 2D map's figure is 5 inches wide and 5 times its aspect (clamped to [0.1, 10]) plus half an inch tall."""
    assert map_figure_size(shape) == pytest.approx(size, rel=1e-12)


def test_the_exported_map_colours_alpha_from_zero_into_nested_folders(tmp_path):
    """The colour scale starts at alpha 0 (half the largest alpha is the colour map's middle), and
    the PNG is written into folders that do not exist yet."""
    import matplotlib
    from PIL import Image

    grid = AlphaGrid(dim=2, resolution=(8, 8), init=0.1)
    values = torch.full((8, 8), 0.5)
    values[:, :4] = 0.25
    grid.set_values(values)
    png = grid.export(tmp_path / "a" / "b" / "alpha")
    assert png == tmp_path / "a" / "b" / "alpha.png"
    pixels = np.asarray(Image.open(png).convert("RGB")).reshape(-1, 3).astype(int)
    cmap = matplotlib.colormaps["magma"]
    for share in (0.5, 1.0):
        colour = np.round(np.array(cmap(share)[:3]) * 255).astype(int)
        assert (np.abs(pixels - colour).max(axis=1) <= 2).sum() > 1000, (share, colour)


def test_a_3d_grid_exports_its_volume_as_npy_last_axis_x(tmp_path):
    """A 3D grid exports its alphas as a ``.npy`` volume, ``[D, H, W]`` (last axis x), in a folder it makes."""
    grid = AlphaGrid(dim=3, resolution=(4, 3, 2), init=0.1)
    values = ramp((2, 3, 4), seed=3)
    grid.set_values(values)
    path = grid.export(tmp_path / "deep" / "alpha.png")
    assert path == tmp_path / "deep" / "alpha.npy"
    np.testing.assert_allclose(np.load(path), values.numpy(), rtol=1e-6)

