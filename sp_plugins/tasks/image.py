"""2D image fitting with a hash grid, optionally with a learned alpha map.

Positions are pixel centres in ``[0, 1]^2`` (x to the right, y down the rows). The field is
queried at perturbed positions and compared with the colour of the unperturbed pixel, so it
learns the blurred image while alpha > 0. With ``adaptive_alpha`` alpha is an
:class:`~sp_plugins.AlphaGrid` at 1/16 of the image size trained with its own Adam (the
paper's alpha-map figure): it stays large where the image is smooth and shrinks on detail.

The paper's "alpha-map guided adaptive techniques" run in two phases. Phase 1 is SP with the
learnable map, while the SP schedule is on. Phase 2 starts at the first step where the schedule
reaches 0: SP is off, the map is frozen and read as a level-of-detail estimate, and it guides

- ``importance_sampling``: training pixels are drawn with probability proportional to
  ``1 / alpha`` (mixed with a uniform share), so detailed regions get more samples. The loss is
  not re-weighted: shifting the fit's effort to the detail is the point;
- ``level_masking``: each query may use only some hash-grid levels, all of them where alpha is
  at the map's low quantile, ``level_mask_min_levels`` at its high quantile, log-linear between
  (:mod:`sp_plugins.encodings.level_mask`), so smooth regions leave the fine levels' table rows
  to the detail. The mask is part of the fitted field (render and PSNR use it too).

``lr_decay`` / ``lr_decay_at`` give Instant-NGP's image schedule (x0.6 at 2/3 of training).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Optional, Tuple, Type, Union, cast

import numpy as np
import torch
from jaxtyping import Float
from torch import Tensor

from sp_plugins.core import AlphaGrid, SPConfig
from sp_plugins.encodings.level_mask import PerPointLevelMask, levels_from_alpha
from sp_plugins.tasks.trainer import ResumableTrainer, run_to_end
from sp_plugins.tasks.fields import EncodingConfig
from sp_plugins.tasks.settings import FitSettings


def _image_sp() -> SPConfig:
    # 1% of the image side, decaying to 0 over the first 20% of training (the paper: SP for
    # the first 6000 of 30000 steps).
    return SPConfig(alpha0=0.01, schedule="exponential", end=0.2)


def _image_encoding() -> EncodingConfig:
    return EncodingConfig(kind="hashgrid", levels=16, log2_table_size=14, base_resolution=8, max_resolution=512)


@dataclass
class ImageFitConfig(FitSettings):
    """Settings of an image fit (``sp-fit image``)."""

    _target: Type = field(default_factory=lambda: ImageFitTrainer)
    batch: int = 16384
    """Pixels per step (all pixels when the image is smaller)."""
    lr: float = 1e-2
    """Adam learning rate of the field (hash grids like large ones)."""
    adaptive_alpha: bool = False
    """Learn a spatially varying alpha map (AlphaGrid at 1/16 of the image size)."""
    alpha_map_downscale: int = 16
    """Image pixels per alpha-map cell along each axis."""
    alpha_map_lr: float = 1e-2
    """Adam learning rate of the alpha map (the paper: 0.01)."""
    importance_sampling: bool = False
    """Phase 2 (after SP ends): draw pixels with probability ~ 1/alpha (needs --adaptive-alpha)."""
    importance_uniform: float = 0.5
    """Share of the phase-2 pixel distribution that stays uniform (flat regions keep being fit)."""
    level_masking: bool = False
    """Phase 2: fewer hash-grid levels where alpha is high (needs --adaptive-alpha and a hash grid)."""
    level_mask_min_levels: float = 8.0
    """Levels usable at the alpha map's high quantile (all levels at its low quantile)."""
    level_mask_quantiles: Tuple[float, float] = (0.05, 0.95)
    """Quantiles of the alpha map taken as its low and high ends for the level mask."""
    lr_decay: float = 1.0
    """Multiply the field's learning rate by this at ``lr_decay_at`` (Instant-NGP: 0.6)."""
    lr_decay_at: float = 2.0 / 3.0
    """Fraction of training at which ``lr_decay`` applies."""
    encoding: EncodingConfig = field(default_factory=_image_encoding)
    sp: SPConfig = field(default_factory=_image_sp)

    def validate(self) -> None:
        if self.steps < 1 or self.batch < 1 or not self.lr > 0 or not self.alpha_map_lr > 0:  # NaN refused too
            raise ValueError("steps, batch, lr and alpha_map_lr must be positive")
        if self.alpha_map_downscale < 1:
            raise ValueError(f"alpha_map_downscale={self.alpha_map_downscale}: must be >= 1")
        if self.encoding.kind == "triplane":
            raise ValueError("encoding kind='triplane' is 3D only; use hashgrid, fourier or finer for images")
        for name in ("importance_sampling", "level_masking"):
            if getattr(self, name) and not self.adaptive_alpha:
                flag = name.replace("_", "-")
                raise ValueError(f"--{flag} uses the learned alpha map: add --adaptive-alpha (or drop --{flag})")
        defaults = {f.name: f.default for f in dataclasses.fields(ImageFitConfig)}
        for name, needs in (("importance_uniform", "importance_sampling"), ("level_mask_min_levels", "level_masking"),
                            ("level_mask_quantiles", "level_masking")):
            if getattr(self, name) != defaults[name] and not getattr(self, needs):
                raise ValueError(f"--{name.replace('_', '-')} applies with --{needs.replace('_', '-')}: add it or drop the option")
        if self.level_masking and self.encoding.kind != "hashgrid":
            raise ValueError(f"--level-masking masks hash-grid levels: use --encoding.kind hashgrid (got {self.encoding.kind!r})")
        if self.level_masking and not 0 < self.level_mask_min_levels <= self.encoding.levels:
            raise ValueError(
                f"level_mask_min_levels={self.level_mask_min_levels}: must be in (0, encoding.levels={self.encoding.levels}]"
            )
        lo, hi = self.level_mask_quantiles
        if not 0.0 <= lo < hi <= 1.0:
            raise ValueError(f"level_mask_quantiles={self.level_mask_quantiles}: need 0 <= low < high <= 1")
        if not 0.0 <= self.importance_uniform <= 1.0:
            raise ValueError(f"importance_uniform={self.importance_uniform}: must be in [0, 1]")
        if not (self.lr_decay > 0 and 0.0 < self.lr_decay_at < 1.0):
            raise ValueError(f"lr_decay={self.lr_decay}, lr_decay_at={self.lr_decay_at}: need lr_decay > 0 and 0 < lr_decay_at < 1")
        if self.lr_decay != 1.0 and round(self.lr_decay_at * self.steps) >= self.steps:
            # the decay happens at step round(lr_decay_at * steps): past the last one it would never apply
            raise ValueError(f"lr_decay_at={self.lr_decay_at} with steps={self.steps}: the decay would come at step "
                             f"{round(self.lr_decay_at * self.steps)}, after the last ({self.steps - 1}); lower --lr-decay-at")
        if self.sp.alpha_grid:
            raise ValueError("alpha_grid: --sp.alpha-grid is the 3D methods' alpha grid; for an image use --adaptive-alpha")
        self.encoding.validate()
        self.sp.validate()

    def setup(self, image: Float[np.ndarray, "h w 3"], **kwargs) -> "ImageFitTrainer":
        return self._target(self, image, **kwargs)


_SIXTEEN_BIT_GREY = ("I;16", "I;16L", "I;16B", "I;16N")
_EIGHT_BIT = ("1", "L", "LA", "La", "P", "PA", "RGB", "RGBX", "RGBA", "RGBa", "CMYK", "YCbCr")


def load_image(path: Union[str, Path]) -> Float[np.ndarray, "h w 3"]:
    """RGB in [0, 1], scaled from the file's own bit depth.

    8-bit images (bilevel, grey, palette, RGB, CMYK, ...) are divided by 255; 16-bit grey (PIL's
    ``I;16`` modes, or ``I`` read from a PNG, whose only source is 16-bit grey) by 65535. PIL reads
    16-bit RGB(A) and grey + alpha PNGs as their high byte, so those are read with OpenCV instead (all
    16 bits; without OpenCV, to 1/255 with a warning). Grey is replicated; an alpha
    channel (or a palette's transparency) is composited on white. 32-bit integer and float images,
    and images smaller than 2x2, are refused with a ValueError naming the file.
    """
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: is a folder; give a file inside it" if path.is_dir() else f"{path}: no such file")
    try:
        with Image.open(path) as im:
            im.load()
            mode, fmt = im.mode, im.format
            if mode in _SIXTEEN_BIT_GREY or (mode == "I" and fmt == "PNG"):
                grey = np.asarray(im, dtype=np.float64)
                if grey.ndim != 2 or grey.min() < 0 or grey.max() > 65535:
                    raise ValueError(f"{path}: a {mode} image with values outside 0..65535; expected 8- or 16-bit pixels")
                rgb = np.repeat((grey / 65535.0).astype(np.float32)[..., None], 3, axis=2)
            elif fmt == "PNG" and _png_bit_depth_and_colour(path) in ((16, 2), (16, 4), (16, 6)):  # RGB, grey + alpha, RGBA
                rgb = _sixteen_bit_colour_png(path, im)
            elif mode in _EIGHT_BIT:
                if mode in ("LA", "La", "P", "PA", "RGBA", "RGBa") or "transparency" in im.info:
                    im = im.convert("RGBA")
                    background = Image.new("RGBA", im.size, (255, 255, 255, 255))
                    im = Image.alpha_composite(background, im)
                rgb = np.asarray(im.convert("RGB"), dtype=np.float32) / 255.0
            else:
                raise ValueError(
                    f"{path}: a {mode} image ({fmt or 'unknown format'}); expected 8- or 16-bit grey, palette, RGB or RGBA"
                )
    except (UnidentifiedImageError, OSError) as exc:
        raise ValueError(f"{path}: cannot be read as an image ({exc})") from exc
    if rgb.shape[0] < 2 or rgb.shape[1] < 2:
        raise ValueError(f"{path}: the image is {rgb.shape[1]}x{rgb.shape[0]}; need at least 2x2 pixels")
    return rgb


def _png_bit_depth_and_colour(path: Path):
    """(bit depth, colour type) from a PNG's IHDR chunk (PIL does not report 16-bit colour)."""
    with open(path, "rb") as f:
        head = f.read(26)
    return (head[24], head[25]) if len(head) == 26 and head[12:16] == b"IHDR" else None


def _sixteen_bit_colour_png(path: Path, fallback) -> np.ndarray:
    """A 16-bit RGB(A) or grey + alpha PNG at full precision (OpenCV: BGR(A) uint16, grey + alpha as
    BGRA), alpha composited on white."""
    try:
        import cv2
    except ImportError:
        import warnings

        warnings.warn(f"{path}: a 16-bit colour PNG, read to 1/255 (its high byte): install opencv-python-headless "
                      "to read all 16 bits", stacklevel=3)
        im = fallback.convert("RGBA")
        im = _alpha_on_white(im)
        return np.asarray(im.convert("RGB"), dtype=np.float32) / 255.0
    pixels = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if pixels is None or pixels.dtype != np.uint16 or pixels.ndim != 3 or pixels.shape[2] not in (3, 4):
        raise ValueError(f"{path}: a 16-bit colour PNG OpenCV could not read; expected 16-bit RGB or RGBA")
    values = pixels[..., [2, 1, 0, 3][: pixels.shape[2]]].astype(np.float64) / 65535.0
    rgb = values[..., :3]
    if values.shape[2] == 4:
        alpha = values[..., 3:]
        rgb = rgb * alpha + (1.0 - alpha)
    return rgb.astype(np.float32)


def _alpha_on_white(im):
    from PIL import Image

    return Image.alpha_composite(Image.new("RGBA", im.size, (255, 255, 255, 255)), im)


def save_image(rgb: Float[np.ndarray, "h w 3"], path: Union[str, Path]) -> Path:
    from PIL import Image

    path = Path(path)
    Image.fromarray((np.clip(rgb, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)).save(path)
    return path


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """Peak signal-to-noise ratio in dB for values in [0, 1]."""
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return float("inf") if mse == 0 else -10.0 * math.log10(mse)


def importance_weights(alpha: Float[Tensor, " n"], uniform_share: float) -> Float[Tensor, " n"]:
    """Pixel probabilities: ``(1 - u) * (1/alpha) / sum(1/alpha) + u / n`` (low alpha, fine
    detail: drawn more often)."""
    inv = 1.0 / alpha.clamp_min(1e-12)
    return (1.0 - uniform_share) * inv / inv.sum() + uniform_share / len(alpha)


def draw_pixels(cdf: Float[Tensor, " n"], batch: int, generator: torch.Generator) -> Tensor:
    """``batch`` indices drawn with replacement from the distribution whose CDF is ``cdf``
    (inverse-CDF sampling: cheaper than ``torch.multinomial`` over a whole image)."""
    u = torch.rand(batch, generator=generator, device=cdf.device, dtype=cdf.dtype) * cdf[-1]
    return torch.searchsorted(cdf, u, right=True).clamp_max(len(cdf) - 1)


def pixel_centres(h: int, w: int) -> Float[Tensor, "hw 2"]:
    """``(x, y)`` of every pixel centre in [0, 1]^2, row-major."""
    ys = (torch.arange(h, dtype=torch.float32) + 0.5) / h
    xs = (torch.arange(w, dtype=torch.float32) + 0.5) / w
    yy, xx = torch.meshgrid(ys, xs, indexing="ij")
    return torch.stack([xx.reshape(-1), yy.reshape(-1)], dim=-1)


class ImageFitTrainer(ResumableTrainer):
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
        self.field = self._build_field(dim=2, out_dim=3, hidden=config.hidden, activation="relu", include_input=False,
                                       bounds=(0.0, 1.0))
        if config.level_masking:
            # inactive until phase 2; level masking needs a hash grid (validate), so there is an encoding
            self.field.encoding = PerPointLevelMask(cast(torch.nn.Module, self.field.encoding))
        sp_config = self._setup_sp(bounds=(0.0, 1.0), dim=2)
        groups = self._param_groups(sp_config)  # the field's (validate refuses SP's own alpha grid here)
        if config.adaptive_alpha:
            if not sp_config.enabled or sp_config.alpha0 <= 0:
                raise ValueError("adaptive_alpha needs SP on with alpha0 > 0 (its initial value)")
            res = (max(2, self.width // config.alpha_map_downscale), max(2, self.height // config.alpha_map_downscale))
            # The map alone is alpha while the SP schedule runs (sp.alpha_grid_mode "replace", the
            # paper's variant), then SP is off, so the fit ends as a plain field.
            alpha_map = AlphaGrid(dim=2, resolution=res, init=sp_config.alpha0, bounds=(0.0, 1.0),
                                  parameterization=sp_config.alpha_grid_parameterization).to(self.device)
            self.sp.preconditioner.alpha_grid = alpha_map
            groups.append({"params": list(alpha_map.parameters()), "lr": config.alpha_map_lr})
            end = self.sp.end_step
            # an end at the last step (end 1.0: SP off for that step only) leaves phase 2 no room either
            if (config.importance_sampling or config.level_masking) and (end is None or end >= config.steps - 1):
                raise ValueError(
                    "--importance-sampling / --level-masking start when SP ends, but the SP schedule "
                    f"({sp_config.schedule}, end={sp_config.end}) never ends before the last step ({config.steps - 1}): "
                    "give --sp.end < 1"
                )
        # fused: about 5-10x faster on a CPU for a 2^17+ table (bench/speed/hashgrid_speed.py)
        self.optimizer = torch.optim.Adam(groups, betas=(0.9, 0.99), eps=1e-15, fused=self.device.type in ("cpu", "cuda"))
        self._start_steps()
        self.phase2_step: Optional[int] = None
        """First step of phase 2 (the map guides the fit), once it has started."""
        self._pixel_cdf: Optional[Tensor] = None
        self.level_mask_alpha_range: Optional[Tuple[float, float]] = None

    # -- phase 2 ----------------------------------------------------------------------------
    @property
    def alpha_map(self) -> AlphaGrid:
        """The learned alpha map (``adaptive_alpha``: set up in ``__init__``; phase 2 runs only with one)."""
        return cast(AlphaGrid, self.sp.alpha_grid)

    @torch.no_grad()
    def pixel_alpha(self) -> Float[Tensor, " hw"]:
        """The learned (unscaled) alpha map at every pixel centre."""
        return self.alpha_map(self.positions)[:, 0]

    def levels_at(self, x: Float[Tensor, "n 2"]) -> Float[Tensor, " n"]:
        """Usable hash-grid levels at ``x`` in phase 2 (inverse to the map's alpha there)."""
        lo, hi = cast(Tuple[float, float], self.level_mask_alpha_range)  # set by start_phase2, which installs this
        c = self.config
        return levels_from_alpha(self.alpha_map(x)[:, 0], lo, hi, c.encoding.levels, c.level_mask_min_levels)

    @torch.no_grad()
    def start_phase2(self, step: Optional[int] = None) -> None:
        """Freeze the alpha map and switch on the techniques it guides (at ``step``, default the
        current one; a resumed fit calls it again with the saved step, on the frozen map)."""
        c = self.config
        self.phase2_step = self.step_index if step is None else int(step)
        self.alpha_map.requires_grad_(False)
        if c.importance_sampling:
            self._pixel_cdf = torch.cumsum(importance_weights(self.pixel_alpha(), c.importance_uniform).double(), 0)
        if c.level_masking:
            q = torch.tensor(c.level_mask_quantiles, dtype=torch.float32, device=self.device)
            lo, hi = torch.quantile(self.alpha_map.values().reshape(-1), q).tolist()
            self.level_mask_alpha_range = (lo, max(hi, lo * (1 + 1e-6)))
            cast(PerPointLevelMask, self.field.encoding).levels_fn = self.levels_at

    def rgb(self, x: Float[Tensor, "n 2"]) -> Float[Tensor, "n 3"]:
        return torch.sigmoid(self.field(x))

    def step(self) -> Mapping[str, float]:
        c = self.config
        with self.timer:
            alpha = self.sp.step_pre(self.step_index)
            if self.step_index == round(c.lr_decay_at * c.steps) and c.lr_decay != 1.0:
                self.optimizer.param_groups[0]["lr"] *= c.lr_decay
            if c.adaptive_alpha and self.phase2_step is None and alpha == 0.0 and self.step_index > 0:
                self.start_phase2()
            n = len(self.positions)
            if self._pixel_cdf is not None:
                idx = draw_pixels(self._pixel_cdf, c.batch, self.generator)
            elif c.batch >= n:
                idx = torch.arange(n, device=self.device)
            else:
                idx = torch.randint(n, (c.batch,), generator=self.generator, device=self.device)
            pred = self.sp.blurred(self.rgb, self.positions[idx])
            loss = (pred - self.colours[idx]).square().mean()
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            self.optimizer.step()
            self.sp.step_post(self.step_index)
        record = {"loss": loss, "alpha": alpha}
        if self.sp.alpha_grid is not None:
            with torch.no_grad():
                record["alpha_map_mean"] = self.alpha_map.values().mean()  # on the device, read with the loss
        return self._finish_step(record)

    def _diverged(self, step: int, loss: float) -> str:
        return super()._diverged(step, loss) + (" or --alpha-map-lr" if self.config.adaptive_alpha else "")

    def _extra_state(self) -> dict:
        return {"phase2_step": self.phase2_step}

    def _load_extra_state(self, state: dict) -> None:
        # the map was frozen at phase2_step, so the loaded map is the one phase 2 read then
        if state.get("phase2_step") is not None:
            self.start_phase2(state["phase2_step"])

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
