import numpy as np
import pytest

from sp_plugins import SPConfig
from sp_plugins.tasks.fields import EncodingConfig
from sp_plugins.tasks.image import ImageFitConfig, load_image, pixel_centres, psnr, save_image

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
