import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from sp_plugins import SPConfig
from sp_plugins.encodings import HashGrid
from sp_plugins.encodings.level_mask import PerPointLevelMask, level_mask, levels_from_alpha
from sp_plugins.tasks.fields import EncodingConfig
from sp_plugins.tasks.image import (
    ImageFitConfig, draw_pixels, importance_weights, load_image, pixel_centres, psnr, save_image,
)

GRID_2D = EncodingConfig(levels=6, log2_table_size=12, base_resolution=4, max_resolution=64)


def half_detailed_image(size=64):
    """Left half: a flat colour; right half: a one-pixel checkerboard."""
    img = np.zeros((size, size, 3), dtype=np.float32)
    img[:, : size // 2] = (0.2, 0.5, 0.8)
    yy, xx = np.mgrid[:size, size // 2 : size]
    img[:, size // 2 :] = ((xx + yy) % 2)[..., None].astype(np.float32)
    return img


def test_pixel_centres_are_row_major_x_then_y():
    p = pixel_centres(2, 4)
    assert p.shape == (8, 2)
    assert p[1].tolist() == [0.375, 0.25]  # second pixel of the first row
    assert p[4].tolist() == [0.125, 0.75]  # first pixel of the second row


def test_a_short_fit_raises_psnr():
    img = half_detailed_image(32)
    trainer = ImageFitConfig(steps=150, batch=4096, encoding=GRID_2D, hidden=(32,)).setup(img)
    before = trainer.psnr()
    trainer.fit()
    after = trainer.psnr()
    assert after > before + 5.0
    assert np.mean(trainer.history["loss"][-10:]) < 0.5 * np.mean(trainer.history["loss"][:10])


def test_the_alpha_map_shrinks_where_the_image_has_detail():
    img = half_detailed_image(64)
    config = ImageFitConfig(
        steps=200, batch=4096, encoding=GRID_2D, hidden=(32,), adaptive_alpha=True,
        sp=SPConfig(alpha0=0.02, schedule="step", end=1.0), alpha_map_lr=0.02,
    )
    trainer = config.setup(img)
    assert tuple(trainer.sp.alpha_grid.values().shape) == (4, 4)  # 1/16 of 64 x 64
    trainer.fit()
    values = trainer.sp.alpha_grid.values().numpy()  # [H, W], last axis is x
    flat, detailed = values[:, 0].mean(), values[:, -1].mean()
    assert detailed < 0.7 * flat


def test_image_io_round_trip_and_errors(tmp_path):
    img = half_detailed_image(8)
    path = save_image(img, tmp_path / "a.png")
    back = load_image(path)
    assert back.shape == (8, 8, 3)
    assert psnr(back, img) > 45
    with pytest.raises(ValueError, match="no such file"):
        load_image(tmp_path / "missing.png")
    (tmp_path / "bad.png").write_bytes(b"not an image")
    with pytest.raises(ValueError, match="cannot be read"):
        load_image(tmp_path / "bad.png")
    with pytest.raises(ValueError, match="adaptive_alpha"):
        ImageFitConfig(adaptive_alpha=True, sp=SPConfig(enabled=False), encoding=GRID_2D).setup(img)


# -- phase 2: alpha-map guided adaptive techniques ------------------------------------------------
ADAPTIVE = dict(
    steps=200, batch=4096, encoding=GRID_2D, hidden=(32,), adaptive_alpha=True, alpha_map_lr=0.02,
    sp=SPConfig(alpha0=0.02, schedule="step", end=0.5),
)


def test_importance_sampling_draws_pixels_in_proportion_to_inverse_alpha():
    alpha = torch.tensor([0.01] * 500 + [0.001] * 500)  # right half: 10x lower alpha (finer detail)
    weights = importance_weights(alpha, uniform_share=0.5)
    assert weights.sum().item() == pytest.approx(1.0)
    g = torch.Generator().manual_seed(0)
    idx = draw_pixels(torch.cumsum(weights.double(), 0), 40_000, g)
    assert idx.min() >= 0 and idx.max() < 1000
    right = (idx >= 500).double().mean().item()
    expected = 0.5 * 10 / 11 + 0.5 * 0.5  # the 1/alpha share plus the uniform share
    assert right == pytest.approx(expected, abs=4 * (expected * (1 - expected) / 40_000) ** 0.5)
    # within a half, draws are uniform (no pixel is favoured beyond its weight)
    counts = torch.bincount(idx, minlength=1000).double()
    assert counts[500:].std() / counts[500:].mean() < 0.15


def test_a_high_alpha_query_gets_fewer_levels_than_a_low_alpha_query():
    levels = levels_from_alpha(torch.tensor([1e-4, 1e-3, 3e-3, 1e-2, 1e-1]), 1e-3, 1e-2, num_levels=6, min_levels=2)
    assert levels.tolist()[0] == 6 and levels.tolist()[1] == 6  # at and below the low end: all levels
    assert levels[3].item() == pytest.approx(2) and levels[4].item() == pytest.approx(2)
    assert 2 < levels[2].item() < 6
    assert torch.equal(level_mask(torch.tensor([2.5]), 4, 2), torch.tensor([[1.0, 1.0, 1.0, 1.0, 0.5, 0.5, 0.0, 0.0]]))
    grid = HashGrid(num_levels=6, features_per_level=2, log2_hashmap_size=10, base_resolution=4, max_resolution=64,
                    backend="torch", n_input_dims=2, init_scale=1.0)

    def alpha_of(x):  # high alpha on the left
        return torch.where(x[:, 0] < 0.5, 1e-2, 1e-3)

    masked = PerPointLevelMask(grid, lambda x: levels_from_alpha(alpha_of(x), 1e-3, 1e-2, 6, 2))
    x = torch.tensor([[0.2, 0.5], [0.8, 0.5]], requires_grad=True)
    feats = masked(x)
    assert torch.all(feats[0, 4:] == 0) and feats[0, :4].abs().min() > 0  # 2 levels x 2 features
    assert feats[1].abs().min() > 0  # low alpha: every level
    assert torch.equal(feats[1], grid(x)[1])
    feats.sum().backward()  # gradients still reach the unmasked rows
    grad = grid.table.grad.clone()  # the torch backend's one parameter
    assert grad.abs().sum() > 0
    grid.table.grad = None  # the same sum with the masked levels zeroed by hand: the same gradient
    keep = torch.ones_like(feats)
    keep[0, 4:] = 0
    (grid(x) * keep).sum().backward()
    assert torch.allclose(grad, grid.table.grad, atol=1e-7)


def half_textured_image(size=64, period=6):
    """Left half: a flat colour; right half: a smooth texture the grid can represent. (A
    one-pixel checkerboard does not pull alpha down: the field never learns it, so blurring
    its queries costs nothing there.)"""
    img = np.empty((size, size, 3), dtype=np.float32)
    img[:] = (0.2, 0.5, 0.8)
    yy, xx = np.mgrid[:size, :size]
    texture = 0.5 + 0.5 * np.sin(2 * np.pi * xx / period) * np.cos(2 * np.pi * yy / period)
    img[:, size // 2 :] = texture[:, size // 2 :, None]
    return img


def test_phase2_starts_when_sp_ends_and_guides_sampling_and_levels():
    img = half_textured_image(64)
    config = ImageFitConfig(**ADAPTIVE, importance_sampling=True, level_masking=True, level_mask_min_levels=2.0)
    trainer = config.setup(img)
    for _ in range(100):
        trainer.step()
    assert trainer.phase2_step is None and trainer.sp.alpha_grid.param.requires_grad
    trainer.step()  # step 100: the step schedule is 0 from here
    assert trainer.phase2_step == 100 and not trainer.sp.alpha_grid.param.requires_grad
    frozen = trainer.sp.alpha_grid.values().clone()
    # more draws on the detailed (right) half, where the map learned low alpha
    idx = draw_pixels(trainer._pixel_cdf, 20_000, torch.Generator().manual_seed(1))
    right = ((idx % 64) >= 32).double().mean().item()
    assert right > 0.55
    # fewer levels on the flat half than on the detailed one
    levels = trainer.levels_at(torch.tensor([[0.1, 0.5], [0.9, 0.5]]))
    assert levels[0] < levels[1] - 1
    trainer.fit()
    assert torch.equal(trainer.sp.alpha_grid.values(), frozen)  # the map stays as learned
    assert np.mean(trainer.history["loss"][-10:]) < 0.5 * np.mean(trainer.history["loss"][:10])
    assert trainer.psnr() > 12


def test_lr_decay_applies_once_at_its_fraction():
    trainer = ImageFitConfig(steps=30, batch=256, encoding=GRID_2D, hidden=(8,), lr=0.01, lr_decay=0.6, lr_decay_at=0.5).setup(
        half_detailed_image(16)
    )
    lrs = []
    for _ in range(30):
        trainer.step()
        lrs.append(trainer.optimizer.param_groups[0]["lr"])
    assert lrs[14] == pytest.approx(0.01) and lrs[15] == pytest.approx(0.006)  # from step 15 = 0.5 * 30 on
    assert lrs[-1] == pytest.approx(0.006)  # applied once: not decayed again
    assert lrs.count(pytest.approx(0.01)) == 15 and lrs.count(pytest.approx(0.006)) == 15


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(importance_sampling=True), "add --adaptive-alpha"),
        (dict(level_masking=True), "add --adaptive-alpha"),
        (dict(ADAPTIVE, level_masking=True, encoding=EncodingConfig(kind="fourier")), "hash-grid"),
        (dict(ADAPTIVE, importance_sampling=True, sp=SPConfig(alpha0=0.02, schedule="step", end=1.0)), "never ends"),
        (dict(sp=SPConfig(alpha_grid=True)), "--adaptive-alpha"),
        (dict(ADAPTIVE, importance_uniform=0.2), "applies with --importance-sampling"),
        (dict(ADAPTIVE, level_mask_min_levels=3.0), "applies with --level-masking"),
    ],
)
def test_adaptive_options_that_cannot_apply_are_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        ImageFitConfig(**kwargs).setup(half_detailed_image(16))


def test_sp_fit_image_adaptive_writes_its_map_and_says_so_in_metrics(tmp_path):
    path = save_image(half_detailed_image(32), tmp_path / "in.png")
    out = tmp_path / "run"
    sp_fit = Path(sys.executable).with_name("sp-fit")
    cmd = [str(sp_fit), "image", str(path), "--out", str(out), "--steps", "20", "--batch", "512", "--adaptive-alpha",
           "--importance-sampling", "--level-masking", "--level-mask-min-levels", "2", "--sp.schedule", "step",
           "--sp.end", "0.5", "--lr-decay", "0.6", "--encoding.levels", "4", "--encoding.log2-table-size", "10",
           "--encoding.base-resolution", "4", "--encoding.max-resolution", "32", "--hidden", "16", "--quiet"]
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["sp"]["alpha_grid"] is True and metrics["adaptive_alpha"] is True
    assert metrics["importance_sampling"] is True and metrics["level_masking"] is True and metrics["phase2_step"] == 10
    assert (out / "alpha_map.png").is_file()
    bad = subprocess.run(cmd[:3] + ["--out", str(tmp_path / "bad"), "--level-masking", "--quiet"], capture_output=True, text=True, timeout=300)
    assert bad.returncode == 2 and bad.stderr.strip().splitlines()[-1].startswith("sp-fit: error: --level-masking")
