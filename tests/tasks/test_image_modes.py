"""sp-fit image: each image mode loads its real pixel values (scaled from its own bit depth) or is refused."""
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from sp_plugins.tasks.image import load_image


def write_png16(path, pixels):
    """A 16-bit PNG (grey for [h, w], grey + alpha for [h, w, 2], RGB for [h, w, 3], RGBA for [h, w, 4])
    written byte by byte, so no library's 16-bit support is assumed."""
    pixels = np.asarray(pixels, dtype=">u2")
    h, w = pixels.shape[:2]
    colour = 0 if pixels.ndim == 2 else {2: 4, 3: 2, 4: 6}[pixels.shape[2]]
    raw = b"".join(b"\x00" + pixels[y].tobytes() for y in range(h))  # filter 0 on every row

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", w, h, 16, colour, 0, 0, 0)
    Path(path).write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))
    return Path(path)


GREY16 = np.array([[0, 1000, 30000], [40000, 65535, 257]], dtype=np.uint16)


def test_16_bit_grey_png_loads_its_real_values(tmp_path):
    for name, path in [("pil", tmp_path / "pil.png"), ("bytes", write_png16(tmp_path / "bytes.png", GREY16))]:
        if name == "pil":
            Image.fromarray(GREY16).save(path)
        with Image.open(path) as im:
            assert im.mode.startswith("I")  # the mode that used to clip to white
        rgb = load_image(path)
        assert rgb.shape == (2, 3, 3) and rgb.dtype == np.float32
        np.testing.assert_allclose(rgb, np.repeat(GREY16[..., None] / 65535.0, 3, axis=2), atol=1e-6)
        assert rgb.mean() < 0.6  # not the ~99.6% white the 8-bit conversion gave


def test_16_bit_rgb_and_rgba_pngs_load_all_16_bits(tmp_path):
    # 1000 and 1001 share their high byte: a reader of the high byte alone gives them the same value
    rgb16 = np.array([[[65535, 0, 30000], [1000, 1001, 40000]], [[12345, 54321, 100], [0, 0, 0]]], dtype=np.uint16)
    rgb = load_image(write_png16(tmp_path / "rgb.png", rgb16))
    np.testing.assert_allclose(rgb, rgb16 / 65535.0, atol=1e-6)
    assert rgb[0, 0, 0] == 1.0 and rgb[1, 1].tolist() == [0.0, 0.0, 0.0]
    assert rgb[0, 1, 1] > rgb[0, 1, 0]
    alpha = np.array([[65535, 0], [32768, 65535]], dtype=np.uint16)[..., None]
    rgba = load_image(write_png16(tmp_path / "rgba.png", np.concatenate([rgb16, alpha], axis=2)))
    a = alpha / 65535.0
    np.testing.assert_allclose(rgba, rgb16 / 65535.0 * a + (1 - a), atol=1e-6)  # composited on white
    assert rgba[0, 1].tolist() == [1.0, 1.0, 1.0]  # fully transparent: white


def test_8_bit_grey_rgba_palette_and_bilevel_load_their_values(tmp_path):
    grey = np.array([[0, 51], [204, 255]], dtype=np.uint8)
    Image.fromarray(grey, "L").save(tmp_path / "l.png")
    np.testing.assert_allclose(load_image(tmp_path / "l.png"), np.repeat(grey[..., None] / 255.0, 3, axis=2), atol=1e-6)

    rgba = np.array([[[255, 0, 0, 255], [0, 255, 0, 0]], [[0, 0, 255, 51], [10, 20, 30, 255]]], dtype=np.uint8)
    Image.fromarray(rgba, "RGBA").save(tmp_path / "rgba.png")
    a = rgba[..., 3:] / 255.0
    np.testing.assert_allclose(load_image(tmp_path / "rgba.png"), rgba[..., :3] / 255.0 * a + (1 - a), atol=1.0 / 255 + 1e-6)

    pal = Image.new("P", (2, 2))
    pal.putpalette([255, 0, 0, 0, 128, 0, 0, 0, 255] + [0] * (256 * 3 - 9))
    pal.putdata([0, 1, 2, 1])
    pal.save(tmp_path / "p.png")
    expected = np.array([[[1, 0, 0], [0, 128 / 255, 0]], [[0, 0, 1], [0, 128 / 255, 0]]], dtype=np.float32)
    np.testing.assert_allclose(load_image(tmp_path / "p.png"), expected, atol=1e-6)
    pal.save(tmp_path / "pt.png", transparency=1)  # palette entry 1 transparent: white
    expected[0, 1] = expected[1, 1] = 1.0
    np.testing.assert_allclose(load_image(tmp_path / "pt.png"), expected, atol=1e-6)

    bits = Image.fromarray(np.array([[True, False], [False, True]]))
    assert bits.mode == "1"
    bits.save(tmp_path / "b.png")
    np.testing.assert_allclose(load_image(tmp_path / "b.png")[..., 0], [[1, 0], [0, 1]], atol=1e-6)


def test_1x1_and_float_images_are_refused_naming_the_file(tmp_path):
    Image.new("RGB", (1, 1), (10, 20, 30)).save(tmp_path / "one.png")
    with pytest.raises(ValueError, match=r"one\.png: the image is 1x1; need at least 2x2"):
        load_image(tmp_path / "one.png")
    Image.fromarray(np.full((2, 2), 0.5, dtype=np.float32), "F").save(tmp_path / "f.tif")
    with pytest.raises(ValueError, match=r"f\.tif: a F image .*expected 8- or 16-bit"):
        load_image(tmp_path / "f.tif")


TINY = ["--encoding.levels", "2", "--encoding.log2-table-size", "8", "--encoding.base-resolution", "4",
        "--encoding.max-resolution", "8", "--hidden", "8", "--batch", "64", "--quiet"]


def test_sp_fit_image_trains_on_a_16_bit_png_and_refuses_a_1x1(tmp_path):
    dark = np.full((8, 8), 6554, dtype=np.uint16)  # 0.1: the old loader read this as pure white
    path = write_png16(tmp_path / "dark16.png", dark)
    sp_fit = Path(sys.executable).with_name("sp-fit")
    out = tmp_path / "run"
    run = subprocess.run([str(sp_fit), "image", str(path), "--out", str(out), "--steps", "150", "--lr", "0.05", "--no-sp"]
                         + TINY, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    with Image.open(out / "fitted.png") as im:
        fitted = np.asarray(im.convert("RGB"), dtype=np.float32) / 255.0
    assert abs(float(fitted.mean()) - 0.1) < 0.05  # trained on 0.1 grey, not on white
    import json

    assert json.loads((out / "metrics.json").read_text())["psnr"] > 20

    Image.new("RGB", (1, 1)).save(tmp_path / "one.png")
    out1 = tmp_path / "run1"
    bad = subprocess.run([str(sp_fit), "image", str(tmp_path / "one.png"), "--out", str(out1), "--steps", "2"] + TINY,
                         capture_output=True, text=True, timeout=300)
    assert bad.returncode == 2
    lines = bad.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("sp-fit: error: ") and "one.png" in lines[0] and "2x2" in lines[0]
    assert not out1.exists()
