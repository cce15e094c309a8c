"""FreeNeRF-lite: FreeNeRF's two regularisers on nerfstudio's MipNeRF, the sparse-view method SP is compared with.

FreeNeRF (Yang, Pavone, Wang, "FreeNeRF: Improving Few-shot Neural Rendering with Free Frequency
Regularization", CVPR 2023, arXiv 2303.07418) adds two terms to MipNeRF, both free of extra queries:

- **Frequency regularisation.** The integrated positional encoding's bands are masked, and opened
  linearly while training: at step ``t`` with ``T`` the end of the regularisation and ``L`` bands, band
  ``i`` (1-based, lowest first) has weight 1 when ``i <= t L / T``, ``t L / T - floor(t L / T)`` when it
  is the next one, 0 above; from ``T`` on every band is open. The raw coordinates that MipNeRF appends
  to its encoding are always visible. So early training sees only a low-passed input, the cause the
  paper gives for few-view overfitting being high-frequency inputs seen too early.
- **Occlusion regularisation.** ``L_occ = (1 / K) sum_k sigma_k m_k`` over the ``K`` samples of each
  ray, near to far, with ``m_k = 1`` for the first ``M`` samples (the "regularisation range") and 0
  after: it penalises density right in front of the cameras (floaters, walls), which few views cannot
  rule out. Note the ``1 / K``: the term is the mean of the masked densities over *all* samples.

Values of the authors' released configs (Jiawei-Yang/FreeNeRF: ``configs/freenerf/*.gin``,
``internal/configs.py``; MipNeRF with 128 samples per level): occlusion weight 0.01 everywhere,
``M`` = 10 on DTU (their default), 20 on LLFF; the frequency mask ends at 90% / 20% / 50% of
43,945 / 87,891 / 131,836 steps for DTU 3 / 6 / 9 views, 90% for LLFF 3 views, 50% in their
8-view Blender (NeRF) runs. The SP paper's FreeNeRF runs end the mask at 70% of training: our default.
Where the release differs from the paper's description, we follow the description (documented here,
not copied): the release opens band 1 at step 0 (its pointer starts at 1), masks the view-direction
encoding too, penalises the samples of its last (fine) level and, on DTU, also penalises up to 15
samples whose colour is near white or black (a background prior; not implemented here). ``M`` counts
samples, so it covers ``M / K`` of each ray: a CPU-sized run with fewer samples should scale it
(``bench.radiance_methods`` does: ``M = 10 * K / 128``), or it would penalise the object itself.

SP is off (``sp.enabled False``) but present, so ``sp-train freenerf-lite`` is FreeNeRF + SP: the
seam moves the Gaussian means of the masked encoding as on ``sp-mipnerf``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Dict, List, Literal, Optional, Tuple, Type

import torch
from jaxtyping import Float
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes
from nerfstudio.field_components.encodings import NeRFEncoding
from nerfstudio.fields.vanilla_nerf_field import NeRFField
from nerfstudio.models.mipnerf import MipNerfModel
from torch import Tensor

from sp_plugins.adapter import presets
from sp_plugins.adapter.callbacks import model_schedule_callback
from sp_plugins.core import SPConfig
from sp_plugins.nerfstudio.mipnerf import SPMipNerfModel, SPMipNerfModelConfig
from sp_plugins.nerfstudio.radiance_configs import mipnerf_method

OCCLUSION_LOSS = "occ_reg_loss"
OCCLUSION_OUTPUT = "occ_reg"
"""The unweighted occlusion term among a training step's outputs."""


def frequency_mask_weights(bands: int, step: float, reg_end: float) -> List[float]:
    """FreeNeRF's weight of each of ``bands`` frequency bands (lowest first) at ``step`` of a
    regularisation that ends at step ``reg_end`` (reference values for tests and docs)."""
    if reg_end <= 0 or step >= reg_end:
        return [1.0] * bands
    visible = bands * step / reg_end
    return [min(1.0, max(0.0, visible - k)) for k in range(bands)]


def occlusion_loss(density: Float[Tensor, "*rays samples 1"], reg_range: int) -> Float[Tensor, ""]:
    """FreeNeRF's ``L_occ``: the mean over rays of ``(1 / K) * sum`` of the density of the first
    ``reg_range`` of the ``K`` samples (ordered near to far)."""
    samples = density.shape[-2]
    return density[..., :reg_range, 0].sum(dim=-1).mean() / samples


class FreeNeRFEncoding(NeRFEncoding):
    """nerfstudio's (integrated) positional encoding times a per-channel mask: each sin / cos
    channel carries its band's weight, the appended raw coordinates weight 1.

    ``freq_mask`` is a persistent buffer, so a checkpoint evaluates with the mask it trained with
    (all ones after the regularisation ends); :meth:`set_visible` moves it on the device, without a
    host copy."""

    def __init__(self, in_dim: int, num_frequencies: int, min_freq_exp: float, max_freq_exp: float, include_input: bool = False) -> None:
        super().__init__(in_dim, num_frequencies, min_freq_exp, max_freq_exp, include_input)
        # output layout of NeRFEncoding: [sin | cos], each axis-major (axis d, band k at d * L + k), then the raw input
        band = torch.arange(in_dim * num_frequencies, dtype=torch.float32) % num_frequencies
        raw = torch.full((in_dim if include_input else 0,), -math.inf)  # -inf: visible at any step
        self.register_buffer("band_index", torch.cat([band, band, raw]), persistent=False)
        self.register_buffer("freq_mask", torch.ones(self.get_out_dim()))
        self.visible_bands = float(num_frequencies)
        """Python mirror of the bands visible (``t L / T``, capped at ``L``): metrics read it, not the buffer."""

    def set_visible(self, bands: float) -> None:
        """Open the first ``bands`` bands (a fraction opens the next one partly)."""
        bands = min(float(bands), float(self.num_frequencies))
        if bands == self.visible_bands:
            return
        self.visible_bands = bands
        with torch.no_grad():
            torch.clamp(bands - self.band_index, 0.0, 1.0, out=self.freq_mask)

    def _load_from_state_dict(self, *args, **kwargs) -> None:
        super()._load_from_state_dict(*args, **kwargs)
        self.visible_bands = math.nan  # the loaded mask's bands are not known here: the next set_visible writes

    def forward(
        self, in_tensor: Float[Tensor, "*bs input_dim"], covs: Optional[Float[Tensor, "*bs input_dim input_dim"]] = None
    ) -> Float[Tensor, "*bs output_dim"]:
        return super().forward(in_tensor, covs) * self.freq_mask


class FreeNeRFField(NeRFField):
    """nerfstudio's ``NeRFField`` that hands the density of each query to the model while the
    model collects them (:attr:`density_log`, a list; None otherwise), for the occlusion term."""

    density_log: Optional[List[Tensor]] = None

    def get_density(self, ray_samples):
        density, embedding = super().get_density(ray_samples)
        if self.density_log is not None:
            self.density_log.append(density)
        return density, embedding


@dataclass
class FreeNeRFModelConfig(SPMipNerfModelConfig):
    """MipNeRF + FreeNeRF's frequency and occlusion regularisation (SP off; ``sp-train`` turns it on)."""

    _target: Type = field(default_factory=lambda: FreeNeRFModel)
    sp: SPConfig = field(default_factory=lambda: dataclasses.replace(presets.MIPNERF, enabled=False))
    freq_reg: bool = True
    """Mask the position encoding's frequency bands, opened linearly until ``freq_reg_end``."""
    freq_reg_end: float = 0.7
    """Where every band is open: a fraction of training (<= 1; the SP paper's FreeNeRF runs: 0.7) or a step."""
    occ_reg_mult: float = 0.01
    """Weight of the occlusion term (FreeNeRF: 0.01); 0 switches it off."""
    occ_reg_range: int = 10
    """Samples penalised at the near end of each ray (FreeNeRF: 10 of 128 on DTU, 20 on LLFF)."""
    occ_reg_samples: Literal["coarse", "fine"] = "coarse"
    """Which pass's samples: the coarse (uniform, so the first ``M`` are the nearest stretch of every
    ray) or the fine (the released code's last level, placed by the coarse weights)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.freq_reg_end <= 0:
            raise ValueError(f"freq_reg_end={self.freq_reg_end}: must be > 0 (a fraction of training or a step)")
        if self.occ_reg_mult < 0 or self.occ_reg_range < 0:
            raise ValueError("occ_reg_mult and occ_reg_range must be >= 0")


class FreeNeRFLosses(MipNerfModel):
    """The occlusion term, below the SP mixin in the method resolution order so that SP's
    non-finite watch sees it with the colour losses."""

    config: FreeNeRFModelConfig

    def get_loss_dict(self, outputs, batch, metrics_dict=None) -> Dict[str, Tensor]:
        losses = super().get_loss_dict(outputs, batch, metrics_dict)
        term = outputs.get(OCCLUSION_OUTPUT)
        if self.training and term is not None:
            losses[OCCLUSION_LOSS] = self.config.occ_reg_mult * term
        return losses


class FreeNeRFModel(SPMipNerfModel, FreeNeRFLosses):
    """MipNeRF whose field is a :class:`FreeNeRFField` on a :class:`FreeNeRFEncoding`."""

    config: FreeNeRFModelConfig

    def populate_host_modules(self) -> None:
        super().populate_host_modules()
        host = self.field
        host.__class__ = FreeNeRFField  # adds behaviour only: the weights the host drew are kept
        enc = host.position_encoding
        host.position_encoding = FreeNeRFEncoding(enc.in_dim, enc.num_frequencies, enc.min_freq, enc.max_freq, enc.include_input)
        self.frequency_mask_at(0, None)

    @property
    def encoding(self) -> FreeNeRFEncoding:
        return self.field.position_encoding  # type: ignore[return-value]

    def reg_end_steps(self, total: int) -> float:
        end = self.config.freq_reg_end
        return end * total if end <= 1 else end

    def frequency_mask_at(self, step: int, total: Optional[int]) -> float:
        """Set the mask for ``step`` of a ``total``-step run; returns the bands visible. Before the
        run's length is known (a model built outside a trainer) the mask is that of step 0."""
        bands = self.encoding.num_frequencies
        if not self.config.freq_reg:
            visible = float(bands)
        elif total is None:
            visible = 0.0
        else:
            end = self.reg_end_steps(total)
            visible = float(bands) if step >= end else bands * step / end
        self.encoding.set_visible(visible)
        return visible

    def get_training_callbacks(self, training_callback_attributes: TrainingCallbackAttributes) -> List[TrainingCallback]:
        callbacks = super().get_training_callbacks(training_callback_attributes)
        return callbacks + [model_schedule_callback(self.frequency_mask_at, self.sp_run_length(training_callback_attributes),
                                                   self.sp_training_callback)]

    def get_outputs(self, ray_bundle) -> Dict[str, Tensor]:
        c = self.config
        if not (self.training and c.occ_reg_mult > 0 and c.occ_reg_range > 0):
            return super().get_outputs(ray_bundle)
        field_ = self.field
        field_.density_log = log = []  # type: ignore[union-attr]
        try:
            outputs = super().get_outputs(ray_bundle)
        finally:
            field_.density_log = None  # type: ignore[union-attr]
        # MipNeRF queries its field in two passes, each num_samples times (the SP seam's draws): the
        # first half of the log is the coarse pass; the occlusion term is linear in density, so the
        # mean over draws equals the term of the averaged density
        half = len(log) // 2
        passes: Tuple[List[Tensor], List[Tensor]] = (log[:half], log[half:])
        chosen = passes[0 if c.occ_reg_samples == "coarse" else 1]
        outputs[OCCLUSION_OUTPUT] = torch.stack([occlusion_loss(d, c.occ_reg_range) for d in chosen]).mean()
        return outputs

    def get_metrics_dict(self, outputs, batch) -> Dict[str, Tensor]:
        metrics = super().get_metrics_dict(outputs, batch)
        if self.training:
            metrics["freq_reg_visible_bands"] = self.encoding.visible_bands  # a Python mirror: no device read
        return metrics


def freenerf_method(name: str, description: str):
    """``sp-mipnerf``'s trainer config (nerfstudio's MipNeRF settings, 7500 steps) on
    :class:`FreeNeRFModelConfig`, SP off."""
    spec = mipnerf_method(name, sp=False, description=description)
    model = spec.config.pipeline.model
    kept = {f.name: getattr(model, f.name) for f in dataclasses.fields(model) if f.init and f.name not in ("_target", "sp")}
    spec.config.pipeline.model = FreeNeRFModelConfig(**kept)
    return spec


__all__ = [
    "FreeNeRFEncoding",
    "FreeNeRFField",
    "FreeNeRFModel",
    "FreeNeRFModelConfig",
    "OCCLUSION_LOSS",
    "OCCLUSION_OUTPUT",
    "freenerf_method",
    "frequency_mask_weights",
    "occlusion_loss",
]
