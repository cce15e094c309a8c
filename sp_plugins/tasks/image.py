"""2D image fitting with a hash grid, optionally with a learned alpha map.

Positions are pixel centres in ``[0, 1]^2`` (x to the right, y down the rows). The field is
queried at perturbed positions and compared with the colour of the unperturbed pixel, so it
learns the blurred image while alpha > 0. With ``adaptive_alpha`` alpha is an
:class:`~sp_plugins.AlphaGrid` at 1/16 of the image size trained with its own Adam (the
paper's alpha-map figure): it stays large where the image is smooth and shrinks on detail.
"""

from __future__ import annotations

import dataclasses
import math
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Tuple, Type, Union

import numpy as np
import torch
from jaxtyping import Float
from torch import Tensor

from sp_plugins.core import AlphaGrid, SPConfig
from sp_plugins.tasks.common import StepTimer, run_to_end
from sp_plugins.tasks.fields import EncodingConfig, NeuralField


def _image_sp() -> SPConfig:
    # 1% of the image side, decaying to 0 over the first 20% of training (the paper: SP for
    # the first 6000 of 30000 steps).
    return SPConfig(alpha0=0.01, schedule="exponential", end=0.2)


def _image_encoding() -> EncodingConfig:
    return EncodingConfig(kind="hashgrid", levels=16, log2_table_size=14, base_resolution=8, max_resolution=512)


def _trainer():
    return ImageFitTrainer


@dataclass
class ImageFitConfig:
    """Settings of an image fit (``sp-fit image``)."""

    _target: Type = field(default_factory=_trainer)
    steps: int = 2000
    seed: int = 0
    batch: int = 16384
    """Pixels per step (all pixels when the image is smaller)."""
    lr: float = 1e-2
    """Adam learning rate of the field (hash grids like large ones)."""
    hidden: Tuple[int, ...] = (64, 64)
    adaptive_alpha: bool = False
    """Learn a spatially varying alpha map (AlphaGrid at 1/16 of the image size)."""
    alpha_map_downscale: int = 16
    """Image pixels per alpha-map cell along each axis."""
    alpha_map_lr: float = 1e-2
    """Adam learning rate of the alpha map (the paper: 0.01)."""
    encoding: EncodingConfig = field(default_factory=_image_encoding)
    sp: SPConfig = field(default_factory=_image_sp)

    def validate(self) -> None:
        if self.steps < 1 or self.batch < 1 or self.lr <= 0 or self.alpha_map_lr <= 0:
            raise ValueError("steps, batch, lr and alpha_map_lr must be positive")
        if self.alpha_map_downscale < 1:
            raise ValueError(f"alpha_map_downscale={self.alpha_map_downscale}: must be >= 1")
        if self.encoding.kind == "triplane":
            raise ValueError("encoding kind='triplane' is 3D only; use hashgrid, fourier or finer for images")
        self.encoding.validate()
        self.sp.validate()

    def setup(self, image: Float[np.ndarray, "h w 3"], **kwargs) -> "ImageFitTrainer":
        return self._target(self, image, **kwargs)


def load_image(path: Union[str, Path]) -> Float[np.ndarray, "h w 3"]:
    """RGB in [0, 1] (grey is replicated, an alpha channel is composited on white)."""
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: is a folder; give a file inside it" if path.is_dir() else f"{path}: no such file")
    try:
        with Image.open(path) as im:
            im.load()
            if im.mode in ("RGBA", "LA", "P"):
                im = im.convert("RGBA")
                background = Image.new("RGBA", im.size, (255, 255, 255, 255))
                im = Image.alpha_composite(background, im)
            rgb = np.asarray(im.convert("RGB"), dtype=np.float32) / 255.0
    except (UnidentifiedImageError, OSError) as exc:
        raise ValueError(f"{path}: cannot be read as an image ({exc})") from exc
    if rgb.shape[0] < 2 or rgb.shape[1] < 2:
        raise ValueError(f"{path}: the image is {rgb.shape[1]}x{rgb.shape[0]}; need at least 2x2 pixels")
    return rgb


def save_image(rgb: Float[np.ndarray, "h w 3"], path: Union[str, Path]) -> Path:
    from PIL import Image

    path = Path(path)
    Image.fromarray((np.clip(rgb, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)).save(path)
    return path


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """Peak signal-to-noise ratio in dB for values in [0, 1]."""
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return float("inf") if mse == 0 else -10.0 * math.log10(mse)


def pixel_centres(h: int, w: int) -> Float[Tensor, "hw 2"]:
    """``(x, y)`` of every pixel centre in [0, 1]^2, row-major."""
    ys = (torch.arange(h, dtype=torch.float32) + 0.5) / h
    xs = (torch.arange(w, dtype=torch.float32) + 0.5) / w
    yy, xx = torch.meshgrid(ys, xs, indexing="ij")
    return torch.stack([xx.reshape(-1), yy.reshape(-1)], dim=-1)


class ImageFitTrainer:
    """One image fit; :meth:`step` runs one iteration (interleavable, like the SDF trainer)."""

    def __init__(self, config: ImageFitConfig, image: Float[np.ndarray, "h w 3"], *, device: str = "cpu") -> None:
        config.validate()
        image = np.asarray(image, dtype=np.float32)
        if image.ndim != 3 or image.shape[2] != 3 or not np.isfinite(image).all():
            raise ValueError("image: need a finite [H, W, 3] array")
        self.config = config
        self.device = torch.device(device)
        self.height, self.width = image.shape[:2]
        self.image = image
        self.colours = torch.as_tensor(image.reshape(-1, 3), device=self.device)
        self.positions = pixel_centres(self.height, self.width).to(self.device)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(config.seed)
            self.field = NeuralField(
                config.encoding, dim=2, out_dim=3, hidden=config.hidden, activation="relu",
                include_input=False, bounds=(0.0, 1.0),
            ).to(self.device)
        sp_config = config.sp if config.sp.seed is not None else dataclasses.replace(config.sp, seed=config.seed + 1)
        self.sp = sp_config.setup(total_steps=config.steps, bounds=(0.0, 1.0), dim=2).to(self.device)
        self.sp.train()
        groups = [{"params": list(self.field.parameters()), "lr": config.lr}]
        if config.adaptive_alpha:
            if not sp_config.enabled or sp_config.alpha0 <= 0:
                raise ValueError("adaptive_alpha needs SP on with alpha0 > 0 (its initial value)")
            res = (max(2, self.width // config.alpha_map_downscale), max(2, self.height // config.alpha_map_downscale))
            # The schedule still scales the map (alpha_at), so the fit ends as a plain field.
            self.sp.alpha_grid = AlphaGrid(dim=2, resolution=res, init=sp_config.alpha0, bounds=(0.0, 1.0)).to(self.device)
            groups.append({"params": list(self.sp.alpha_grid.parameters()), "lr": config.alpha_map_lr})
        self.optimizer = torch.optim.Adam(groups, betas=(0.9, 0.99), eps=1e-15)
        self.generator = torch.Generator(device=self.device)
        self.generator.manual_seed(config.seed)
        self.step_index = 0
        self.history: dict[str, list[float]] = defaultdict(list)
        self.timer = StepTimer()

    def rgb(self, x: Float[Tensor, "n 2"]) -> Float[Tensor, "n 3"]:
        return torch.sigmoid(self.field(x))

    def step(self) -> dict[str, float]:
        c = self.config
        with self.timer:
            alpha = self.sp.set_step(self.step_index, c.steps)
            n = len(self.positions)
            if c.batch >= n:
                idx = torch.arange(n, device=self.device)
            else:
                idx = torch.randint(n, (c.batch,), generator=self.generator, device=self.device)
            pred = self.sp.blurred(self.rgb, self.positions[idx])
            loss = (pred - self.colours[idx]).square().mean()
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            self.optimizer.step()
        self.step_index += 1
        record = {"loss": loss.item(), "alpha": float(alpha)}
        if self.sp.alpha_grid is not None:
            record["alpha_map_mean"] = float(self.sp.alpha_grid.values().mean())
        for k, v in record.items():
            self.history[k].append(v)
        return record

    @property
    def done(self) -> bool:
        return self.step_index >= self.config.steps

    @torch.no_grad()
    def render(self, chunk: int = 65536) -> Float[np.ndarray, "h w 3"]:
        """The plain field at every pixel centre."""
        self.field.eval()
        out = torch.cat([self.rgb(self.positions[s : s + chunk]) for s in range(0, len(self.positions), chunk)])
        self.field.train()
        return out.reshape(self.height, self.width, 3).cpu().numpy()

    def psnr(self) -> float:
        return psnr(self.render(), self.image)

    def fit(self, callback=None, progress: bool = False) -> None:
        """Run the remaining steps (``callback(trainer, record)`` after each)."""
        run_to_end(self, "sp-fit image", callback, progress)
