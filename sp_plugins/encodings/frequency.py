"""Fourier-feature (NeRF positional) encoding, optionally integrated over a Gaussian (mip-NeRF).

``gamma(x) = [sin(w_k x_d), cos(w_k x_d)]`` with ``w_k = scale * 2**e_k`` and exponents ``e_k``
evenly spaced in ``[min_freq_exp, max_freq_exp]``. Given a per-axis variance ``var`` of the position
(a Gaussian ``N(x, diag(var))``), each feature is replaced by its expectation,
``E[sin(w (x + d))] = exp(-w**2 var / 2) sin(w x)`` (same for cos): the integrated positional
encoding of mip-NeRF. This is also exactly what stochastic preconditioning with Gaussian noise of
standard deviation ``alpha`` averages to (``var = alpha**2``).

Layout of the output: ``[sin(w_0 x_0), ..., sin(w_0 x_D), sin(w_1 x_0), ..., cos(...)...]``, i.e.
all sines (frequency-major) then all cosines, then the raw input if ``include_input``.
"""

from __future__ import annotations

import math
from typing import Optional

import torch
from jaxtyping import Float
from torch import Tensor, nn


class FrequencyEncoding(nn.Module):
    """Sines and cosines of the input at ``num_frequencies`` octaves.

    Args:
        n_input_dims: input width D.
        num_frequencies: K frequencies.
        min_freq_exp, max_freq_exp: exponents of the lowest and highest frequency (base 2).
        include_input: append ``x`` itself.
        scale: angular factor applied to every frequency (``2*pi``: period 1 at exponent 0,
            nerfstudio's ``NeRFEncoding`` convention; ``pi`` for NeRF's original one).
    """

    def __init__(
        self,
        n_input_dims: int = 3,
        num_frequencies: int = 6,
        min_freq_exp: float = 0.0,
        max_freq_exp: float = 5.0,
        include_input: bool = False,
        scale: float = 2 * math.pi,
    ) -> None:
        super().__init__()
        if n_input_dims < 1 or num_frequencies < 1:
            raise ValueError(f"n_input_dims={n_input_dims} and num_frequencies={num_frequencies} must be >= 1")
        if max_freq_exp < min_freq_exp:
            raise ValueError(f"max_freq_exp={max_freq_exp} must be >= min_freq_exp={min_freq_exp}")
        self.n_input_dims = n_input_dims
        self.num_frequencies = num_frequencies
        self.include_input = include_input
        self.n_output_dims = n_input_dims * (2 * num_frequencies + int(include_input))
        self.min_freq_exp, self.max_freq_exp, self.scale = float(min_freq_exp), float(max_freq_exp), float(scale)
        exps = torch.linspace(min_freq_exp, max_freq_exp, num_frequencies, dtype=torch.float64)
        self.angular_frequencies = tuple(float(v) for v in scale * 2.0**exps)

    def frequencies(self, like: Tensor) -> Float[Tensor, " k"]:
        """The angular frequencies in ``like``'s dtype, made on its device from Python numbers:
        no host-to-device copy (``torch.tensor(list, device=cuda)`` would synchronise the host
        with the GPU at every call), and no float64 buffer (MPS has none)."""
        exps = torch.linspace(self.min_freq_exp, self.max_freq_exp, self.num_frequencies, dtype=like.dtype, device=like.device)
        return torch.exp2(exps) * self.scale

    def get_out_dim(self) -> int:
        return self.n_output_dims

    def forward(
        self, x: Float[Tensor, "*batch dims"], variance: Optional[Float[Tensor, "*batch dims"]] = None
    ) -> Float[Tensor, "*batch out"]:
        """Encode ``x``; with ``variance`` (per-axis, or a ``[*batch, dims, dims]`` covariance whose
        diagonal is used) return the expected encoding under ``N(x, variance)``."""
        if x.shape[-1] != self.n_input_dims:
            raise ValueError(f"positions have {x.shape[-1]} coordinates; this encoding expects {self.n_input_dims}")
        w = self.frequencies(x)
        phase = (w[:, None] * x[..., None, :]).flatten(-2)  # [*batch, K * D], frequency-major
        features = torch.cat([torch.sin(phase), torch.cos(phase)], dim=-1)
        if variance is not None:
            if variance.shape[-2:] == (self.n_input_dims, self.n_input_dims) and variance.dim() == x.dim() + 1:
                variance = torch.diagonal(variance, dim1=-2, dim2=-1)
            if variance.shape[-1] != self.n_input_dims:
                raise ValueError(
                    f"variance must be [*batch, {self.n_input_dims}] or [*batch, {self.n_input_dims}, {self.n_input_dims}], "
                    f"got {tuple(variance.shape)}"
                )
            damping = torch.exp(-0.5 * (w[:, None] ** 2 * variance[..., None, :]).flatten(-2))
            features = features * torch.cat([damping, damping], dim=-1)
        if self.include_input:
            features = torch.cat([features, x], dim=-1)
        return features
