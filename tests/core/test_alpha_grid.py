import torch
import torch.nn.functional as F

from sp_plugins import AlphaGrid, perturb


def test_alpha_grid_starts_at_init_and_is_positive():
    grid = AlphaGrid(dim=3, resolution=8, init=0.03)
    x = torch.rand(100, 3) * 2 - 1
    a = grid(x)
    assert a.shape == (100, 1)
    assert torch.allclose(a, torch.full_like(a, 0.03), rtol=1e-5)
    with torch.no_grad():
        grid.param.fill_(-50.0)
    assert bool((grid(x) > 0).all())


def test_gradients_reach_the_alpha_grid():
    grid = AlphaGrid(dim=2, resolution=(8, 4), init=0.1)
    x = torch.rand(256, 2) * 2 - 1
    y = perturb(x, grid(x), generator=torch.Generator().manual_seed(0))
    (torch.sin(10 * y) - torch.sin(10 * x)).pow(2).mean().backward()
    assert grid.param.grad is not None
    assert float(grid.param.grad.abs().sum()) > 0


def test_fitting_drives_alpha_lower_where_the_target_has_detail():
    """Fit a small grid field through perturbed queries while learning alpha (the paper's
    adaptive alpha). Detail (a high-frequency sine) lives on x > 0, a gentle ramp on x < 0:
    blurring costs more on the detailed half, so the learned alpha must end lower there."""
    torch.manual_seed(0)

    def target(p):
        x = p[..., 0]
        return torch.where(x > 0, torch.sin(40 * x), 0.3 * x)

    values = torch.nn.Parameter(torch.zeros(1, 1, 64, 64))

    def model(p):
        return F.grid_sample(values, p.view(1, 1, -1, 2), align_corners=True, padding_mode="border").view(-1)

    grid = AlphaGrid(dim=2, resolution=16, init=0.05)
    opt = torch.optim.Adam([{"params": grid.parameters(), "lr": 0.01}, {"params": [values], "lr": 0.05}])
    for _ in range(400):
        x = torch.rand(4096, 2) * 2 - 1
        y = perturb(x, grid(x), boundary="reflect", bounds=(-1.0, 1.0), validate=False)
        loss = (model(y) - target(x)).pow(2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    alpha = grid.values()  # [H, W], last axis is x
    W = alpha.shape[1]
    detailed = float(alpha[:, W // 2 + 1 :].mean())
    smooth = float(alpha[:, : W // 2 - 1].mean())
    assert detailed < 0.5 * smooth
    assert smooth > 0.01  # the smooth half kept a sizeable blur


def test_export_writes_an_image_and_a_volume(tmp_path):
    import numpy as np
    from PIL import Image

    png = AlphaGrid(dim=2, resolution=(12, 6), init=0.02).export(tmp_path / "alpha")
    assert png.suffix == ".png" and Image.open(png).size[0] > 0
    npy = AlphaGrid(dim=3, resolution=5, init=0.02).export(tmp_path / "alpha3d")
    vol = np.load(npy)
    assert vol.shape == (5, 5, 5) and np.allclose(vol, 0.02, rtol=1e-5)
