"""HashGrid (torch backend): tcnn semantics, derivatives, continuity, backend choice."""

import logging

import pytest
import torch
import torch.nn.functional as F

from sp_plugins.encodings import HashGrid
from sp_plugins.encodings import hashgrid as hashgrid_module
from sp_plugins.encodings.grid_levels import HASH_PRIMES, grid_levels
from sp_plugins.encodings import hashgrid_torch
from sp_plugins.encodings.hashgrid_torch import corner_indices


def small_grid(interpolation="Linear", dtype=torch.float64, **kw):
    """Three levels of at most 2^7 rows: the first two dense (res 3 and 5), the last hashed (res 8)."""
    args = dict(num_levels=3, features_per_level=2, log2_hashmap_size=7, base_resolution=3, per_level_scale=1.6)
    args.update(kw)
    torch.manual_seed(0)
    grid = HashGrid(**args, interpolation=interpolation, backend="torch", init_scale=1.0, dtype=dtype)
    return grid


def test_level_geometry_follows_tcnn():
    levels = grid_levels(16, 3, 19, 16, 2048 ** (1 / 15) / 16 ** (1 / 15))
    assert levels[0].scale == 15.0 and levels[0].resolution == 16 and levels[0].size == 4096
    assert levels[1].resolution == 23 and levels[1].size == 12168  # 23^3 = 12167 padded to 8
    assert [lv.hashed for lv in levels] == [False] * 5 + [True] * 11  # 59^3 fits 2^19, 81^3 does not
    assert all(lv.size == 2**19 for lv in levels[5:])
    assert levels[-1].resolution == 2048
    assert [lv.offset for lv in levels[1:]] == [sum(lv.size for lv in levels[:i]) for i in range(1, 16)]


def test_small_grid_has_dense_and_hashed_levels():
    grid = small_grid()
    assert [lv.hashed for lv in grid.levels] == [False, False, True]
    assert [lv.resolution for lv in grid.levels] == [3, 5, 8]
    assert grid.table.shape == (sum(lv.size for lv in grid.levels) * 2,)  # flat: tcnn's params layout, 2 features per row


@pytest.mark.parametrize("interpolation, features", [("Linear", 2), ("Smoothstep", 2), ("Linear", 1), ("Smoothstep", 4)])
@pytest.mark.parametrize("embedding_bag", [True, False], ids=["bag", "gather"])
def test_gradcheck_inputs_and_table(interpolation, features, embedding_bag, monkeypatch):
    """First and second derivatives; 1, 2 and 4 features take the three table-access code paths.
    Levels of res 2 and 3 (dense) and 5 (hashed into 32 rows): 72 rows keep gradgradcheck quick."""
    if not embedding_bag:  # the forward used on devices without embedding_bag (e.g. MPS)
        monkeypatch.setattr(hashgrid_torch, "EMBEDDING_BAG_DEVICES", set())
    grid = small_grid(interpolation, features_per_level=features, log2_hashmap_size=5, base_resolution=2, per_level_scale=1.5)
    assert [lv.hashed for lv in grid.levels] == [False, False, True]
    x = torch.rand(6, 3, dtype=torch.float64, requires_grad=True)
    table = grid.table.detach().clone().requires_grad_(True)

    def f(x, table):
        return torch.func.functional_call(grid, {"table": table}, (x,))

    assert torch.autograd.gradcheck(f, (x, table), eps=1e-6, atol=1e-6)
    assert torch.autograd.gradgradcheck(f, (x, table), eps=1e-6, atol=1e-5)


def test_eikonal_double_backward_reaches_table_and_inputs():
    grid = small_grid("Smoothstep")
    x = torch.rand(64, 3, dtype=torch.float64, requires_grad=True)
    weights = torch.randn(grid.n_output_dims, dtype=torch.float64)
    sdf = grid(x) @ weights
    (g,) = torch.autograd.grad(sdf.sum(), x, create_graph=True)
    loss = (g.norm(dim=-1) - 1).square().mean()
    table_grad, x_grad = torch.autograd.grad(loss, [grid.table, x])
    assert table_grad.abs().sum() > 0 and x_grad.abs().sum() > 0


def test_input_gradient_alone_does_not_scatter_into_the_table(monkeypatch):
    """autograd.grad(y, x) must not pay for the table's gradient (the eikonal's first pass)."""
    calls = []
    real_splat = hashgrid_torch._splat_kernel
    monkeypatch.setattr(hashgrid_torch, "_splat_kernel", lambda *a: calls.append(1) or real_splat(*a))
    grid = small_grid()
    x = torch.rand(16, 3, dtype=torch.float64, requires_grad=True)
    (g,) = torch.autograd.grad(grid(x).sum(), x, create_graph=True)
    assert calls == []
    g.square().sum().backward()  # now the table does need its gradient (through the input gradient)
    assert calls and grid.table.grad.abs().sum() > 0


def test_dense_level_matches_direct_trilinear_lookup():
    # one dense level, res 9 (scale 8): compare with grid_sample on the same values as a volume
    grid = HashGrid(num_levels=1, features_per_level=4, log2_hashmap_size=12, base_resolution=9, backend="torch", init_scale=1.0, dtype=torch.float64)
    lv = grid.levels[0]
    assert not lv.hashed and lv.resolution == 9 and lv.scale == 8.0
    res = lv.resolution
    volume = grid.table.view(-1, 4)[: res**3].detach().T.reshape(1, 4, res, res, res)  # rows are x + y*res + z*res^2 -> [F, z, y, x]
    # stay where the +1 corner is inside the grid: pos = 8x + 0.5 <= res - 1
    x = torch.rand(500, 3, dtype=torch.float64) * (7.5 / 8)
    pos = x * lv.scale + 0.5
    coords = (2 * pos / (res - 1) - 1).view(1, -1, 1, 1, 3)  # grid_sample wants (x, y, z) order
    expected = F.grid_sample(volume, coords, mode="bilinear", align_corners=True).view(4, -1).T
    torch.testing.assert_close(grid(x), expected)


def test_dense_far_face_wraps_like_tcnn():
    # at x = 1 the +1 corner of level 0 (res 9) is vertex 9: tcnn computes (9 + y*9 + z*81) mod rows
    grid = HashGrid(num_levels=1, features_per_level=1, log2_hashmap_size=12, base_resolution=9, backend="torch", dtype=torch.float64)
    lv = grid.levels[0]
    cell = torch.tensor([[[8], [2], [3]]])
    rows = corner_indices(cell, grid.levels, 2**12)[0, :, 0]
    expected = [(cx + cy * 9 + cz * 81) % lv.size for cx in (8, 9) for cy in (2, 3) for cz in (3, 4)]
    assert rows.tolist() == expected


def test_out_of_range_cells_index_like_tcnn_uint32():
    """Perturbed points can leave [0, 1]: negative cells wrap through uint32 exactly as in tcnn."""
    levels = grid_levels(2, 3, 10, 8, 4.0)  # res 8 (dense, 512 rows) and res 32 (hashed)
    cell = torch.randint(-40, 40, (2, 3, 30))
    rows = corner_indices(cell, levels, 2**10)
    for n in range(30):
        for k in range(8):
            c = [int(cell[0, d, n]) + ((k >> (2 - d)) & 1) for d in range(3)]
            dense = sum(((c[d] % 2**32) * 8**d) for d in range(3)) % 2**32 % levels[0].size
            assert int(rows[0, k, n]) == dense
            c = [int(cell[1, d, n]) + ((k >> (2 - d)) & 1) for d in range(3)]
            h = 0
            for d in range(3):
                h ^= ((c[d] % 2**32) * HASH_PRIMES[d]) % 2**32
            assert int(rows[1, k, n]) == h % 2**10
    grid = small_grid()
    out = grid(torch.rand(100, 3, dtype=torch.float64) * 3 - 1)
    assert torch.isfinite(out).all()


def test_hashed_level_uses_tcnn_primes_in_uint32():
    levels = grid_levels(2, 3, 10, 16, 2.0)
    assert levels[1].hashed
    cell = torch.randint(0, 30, (2, 3, 50))
    rows = corner_indices(cell, levels, 2**10)
    for n in range(50):
        for k in range(8):
            c = [int(cell[1, d, n]) + ((k >> (2 - d)) & 1) for d in range(3)]
            h = 0
            for d in range(3):
                h ^= (c[d] * HASH_PRIMES[d]) & 0xFFFFFFFF
            assert int(rows[1, k, n]) == h % 2**10  # rows within the level


@pytest.mark.parametrize("level", [0, 2])
def test_output_continuous_across_cell_faces(level):
    grid = small_grid("Linear")
    scale = grid.levels[level].scale
    x = torch.rand(200, 3, dtype=torch.float64)
    face = torch.randint(1, int(scale), (200,)).double()
    x[:, 1] = (face - 0.5) / scale  # pos_y = face exactly: a cell face of this level
    eps = 1e-9
    below, above = x.clone(), x.clone()
    below[:, 1] -= eps
    above[:, 1] += eps
    gap = (grid(above) - grid(below)).abs().max()
    lipschitz = 2 * grid.table.abs().max() * grid.levels[-1].scale * 3
    assert gap <= lipschitz * 2 * eps * 10


def _dy_grad(grid, x):
    x = x.clone().requires_grad_(True)
    out = grid(x)
    w = torch.linspace(-1, 1, out.shape[-1], dtype=out.dtype)
    (g,) = torch.autograd.grad((out @ w).sum(), x)
    return g[:, 1]


def test_smoothstep_derivative_continuous_linear_is_not():
    x = torch.rand(200, 3, dtype=torch.float64)
    level = 1
    grid_s = small_grid("Smoothstep")
    scale = grid_s.levels[level].scale
    face = torch.randint(1, int(scale), (200,)).double()
    x[:, 1] = (face - 0.5) / scale
    eps = 1e-9
    below, above = x.clone(), x.clone()
    below[:, 1] -= eps
    above[:, 1] += eps
    jump_s = (_dy_grad(grid_s, above) - _dy_grad(grid_s, below)).abs().max()
    grid_l = small_grid("Linear")
    jump_l = (_dy_grad(grid_l, above) - _dy_grad(grid_l, below)).abs().max()
    assert jump_s < 1e-5
    assert jump_l > 1e-2  # the test can see a derivative jump when there is one


def test_active_levels_mask_finer_levels():
    grid = small_grid()
    x = torch.rand(32, 3, dtype=torch.float64)
    full = grid(x)
    grid.set_active_levels(2)
    masked = grid(x)
    torch.testing.assert_close(masked[:, :4], full[:, :4])
    assert masked[:, 4:].abs().max() == 0
    masked.sum().backward()
    hashed = grid.levels[2]
    grad = grid.table.grad.view(grid.n_table_rows, -1)
    assert grad[hashed.offset :].abs().max() == 0
    assert grad[: hashed.offset].abs().max() > 0
    grid.set_active_levels(None)
    torch.testing.assert_close(grid(x), full)
    with pytest.raises(ValueError, match="active levels"):
        grid.set_active_levels(4)


def test_dtype_follows_input_and_batch_shape_kept():
    grid = small_grid(dtype=torch.float32)
    x = torch.rand(4, 5, 3, dtype=torch.float64)
    out = grid(x)
    assert out.dtype == torch.float64 and out.shape == (4, 5, grid.n_output_dims)
    torch.testing.assert_close(out.float(), grid(x.float()), rtol=1e-5, atol=1e-5)
    half = grid(x.half())  # positions are computed in float32, the result returned in half
    assert half.dtype == torch.float16
    torch.testing.assert_close(half.float(), grid(x.half().float()), rtol=1e-3, atol=1e-3)


def test_auto_falls_back_to_torch_here(caplog, monkeypatch):
    if hashgrid_module.tcnn_available():
        pytest.skip("tcnn and CUDA are available here")
    monkeypatch.setattr(hashgrid_module, "_logged_choices", set())
    with caplog.at_level(logging.INFO, logger=hashgrid_module.__name__):
        a = HashGrid(num_levels=2, log2_hashmap_size=8, backend="auto")
        b = HashGrid(num_levels=2, log2_hashmap_size=8, backend="auto")
    assert a.backend == b.backend == "torch"
    assert sum("'auto' -> 'torch'" in r.getMessage() for r in caplog.records) == 1  # logged once
    with pytest.raises(ValueError, match="tinycudann"):
        HashGrid(num_levels=2, log2_hashmap_size=8, backend="tcnn")


def test_tcnn_config_round_trip():
    grid = HashGrid(num_levels=5, features_per_level=4, log2_hashmap_size=11, base_resolution=8, max_resolution=128, interpolation="Smoothstep", backend="torch")
    again = HashGrid.from_tcnn_config(3, grid.tcnn_config(), backend="torch")
    assert again.levels == grid.levels and again.interpolation == "Smoothstep"
    nerfstudio_style = {"otype": "HashGrid", "n_levels": 4, "n_features_per_level": 2, "log2_hashmap_size": 10,
                        "base_resolution": 16, "per_level_scale": 1.5, "interpolation": "Linear"}
    assert HashGrid.from_tcnn_config(3, nerfstudio_style, backend="torch").n_output_dims == 8
    with pytest.raises(ValueError, match="otype"):
        HashGrid.from_tcnn_config(3, {"otype": "Frequency"}, backend="torch")


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(backend="cuda"), "backend"),
        (dict(interpolation="Cubic"), "interpolation"),
        (dict(per_level_scale=1.5, max_resolution=64), "not both"),
        (dict(n_input_dims=4), "n_input_dims"),
        (dict(features_per_level=3), "features_per_level"),
        (dict(grid_type="Dense", base_resolution=512, per_level_scale=2.0), "would hold"),
    ],
)
def test_bad_arguments_raise_value_error(kwargs, match):
    with pytest.raises(ValueError, match=match):
        HashGrid(num_levels=2, log2_hashmap_size=8, **kwargs)


def test_wrong_input_width_raises():
    grid = small_grid()
    with pytest.raises(ValueError, match="coordinates"):
        grid(torch.rand(5, 2, dtype=torch.float64))


def test_two_dimensional_grid():
    grid = HashGrid(num_levels=2, log2_hashmap_size=8, base_resolution=8, backend="torch", n_input_dims=2, init_scale=1.0, dtype=torch.float64)
    x = torch.rand(7, 2, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(grid, (x,), eps=1e-6, atol=1e-6)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_matches_cpu():
    grid = small_grid(dtype=torch.float32)
    x = torch.rand(100, 3)
    expected = grid(x)
    torch.testing.assert_close(grid.cuda()(x.cuda()).cpu(), expected)
