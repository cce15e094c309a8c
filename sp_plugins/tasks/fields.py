"""Small neural fields for the fitting tasks: an input encoding followed by an MLP.

Encodings (``EncodingConfig.kind``):

- ``hashgrid``: :class:`sp_plugins.encodings.HashGrid` (tcnn options; torch backend on CPU).
- ``fourier``: :class:`sp_plugins.encodings.FrequencyEncoding`, octaves of pi on [-1, 1].
- ``triplane``: :class:`sp_plugins.encodings.TriplaneEncoding`, three planes summed.
- ``finer``: no encoding; the MLP itself is FINER (``sin(omega * (|z| + 1) * z)`` activations,
  a SIREN whose frequency grows with the pre-activation, Liu et al. 2024).

Every field takes positions in the task's domain box ``[lo, hi]^dim`` and maps them to the
encoding's own input range, so the tasks never deal with encoding conventions.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, Optional, Sequence, Tuple

import torch
from jaxtyping import Float
from torch import Tensor, nn

from sp_plugins.encodings import FrequencyEncoding, HashGrid, TriplaneEncoding

EncodingKind = Literal["hashgrid", "fourier", "triplane", "finer"]
ENCODING_KINDS: tuple[str, ...] = ("hashgrid", "fourier", "triplane", "finer")


@dataclass
class EncodingConfig:
    """Input encoding of a fitted field (the flags are ``--encoding.*`` in ``sp-fit``)."""

    kind: EncodingKind = "hashgrid"
    """hashgrid | fourier | triplane | finer."""
    levels: int = 16
    """hashgrid: number of levels."""
    features_per_level: int = 2
    """hashgrid: features per level."""
    log2_table_size: int = 16
    """hashgrid: log2 of the rows per level (the paper: 19 on a GPU)."""
    base_resolution: int = 16
    """hashgrid: coarsest level's resolution."""
    max_resolution: int = 1024
    """hashgrid: finest level's resolution (the paper: 2048)."""
    frequencies: int = 8
    """fourier: octaves 2^0 .. 2^(n-1) (times pi, on [-1, 1] coordinates)."""
    plane_resolution: int = 128
    """triplane: cells per side of each plane."""
    plane_features: int = 16
    """triplane: features per plane."""
    finer_omega: float = 30.0
    """finer: first-layer frequency omega_0."""
    finer_bias_scale: float = 1.0
    """finer: first-layer bias drawn from U(-k, k) (FINER's frequency-spreading init)."""

    def validate(self) -> None:
        if self.kind not in ENCODING_KINDS:
            raise ValueError(f"encoding kind={self.kind!r} is not known; allowed values: {', '.join(ENCODING_KINDS)}")
        if self.levels < 1 or self.base_resolution < 2 or self.max_resolution < self.base_resolution:
            raise ValueError(
                f"hashgrid: need levels >= 1 and 2 <= base_resolution <= max_resolution "
                f"(got {self.levels}, {self.base_resolution}, {self.max_resolution})"
            )
        if self.frequencies < 1 or self.plane_resolution < 2 or self.plane_features < 1:
            raise ValueError("fourier frequencies, triplane resolution and features must be positive")


class FinerLayer(nn.Module):
    """``sin(omega * (|z| + 1) * z)`` with ``z = W x + b``; SIREN-style init."""

    def __init__(self, d_in: int, d_out: int, omega: float, first: bool, bias_scale: float) -> None:
        super().__init__()
        self.linear = nn.Linear(d_in, d_out)
        self.omega = omega
        bound = 1.0 / d_in if first else math.sqrt(6.0 / d_in) / omega
        with torch.no_grad():
            self.linear.weight.uniform_(-bound, bound)
            if first:
                self.linear.bias.uniform_(-bias_scale, bias_scale)

    def forward(self, x: Tensor) -> Tensor:
        z = self.linear(x)
        return torch.sin(self.omega * (z.abs() + 1.0) * z)


def make_encoding(config: EncodingConfig, dim: int) -> Tuple[Optional[nn.Module], int]:
    """The encoding module (None for ``finer``) and its output width."""
    config.validate()
    if config.kind == "hashgrid":
        enc = HashGrid(
            num_levels=config.levels,
            features_per_level=config.features_per_level,
            log2_hashmap_size=config.log2_table_size,
            base_resolution=config.base_resolution,
            max_resolution=config.max_resolution,
            backend="auto",
            n_input_dims=dim,
        )
        return enc, enc.n_output_dims
    if config.kind == "fourier":
        # octaves 2^0 .. 2^(n-1) times pi on [-1, 1] coordinates (NeRF's convention)
        freq = FrequencyEncoding(dim, config.frequencies, 0.0, config.frequencies - 1.0, scale=math.pi)
        return freq, freq.n_output_dims
    if config.kind == "triplane":
        if dim != 3:
            raise ValueError("encoding kind='triplane' is 3D only; use hashgrid or fourier for images")
        planes = TriplaneEncoding(config.plane_resolution, config.plane_features, reduce="sum")
        return planes, planes.n_output_dims
    return None, 0


class NeuralField(nn.Module):
    """``encoding -> MLP`` on positions in ``[lo, hi]^dim``.

    Args:
        dim: 2 (image) or 3 (SDF).
        out_dim: 1 for an SDF, 3 for RGB.
        hidden: MLP hidden widths.
        activation: ``softplus`` (beta 100, smooth second derivative for the eikonal loss) or
            ``relu``; ignored for ``finer``.
        include_input: feed the raw coordinates to the MLP next to the features (needed for the
            geometric initialisation, harmless otherwise).
        geometric_init: start as the SDF of a sphere of ``init_radius`` (SAL, Atzmon & Lipman
            2020): the encoding's weights start at 0, the coordinate path is a sphere.
        bounds: the domain box.
    """

    def __init__(
        self,
        encoding: EncodingConfig,
        *,
        dim: int = 3,
        out_dim: int = 1,
        hidden: Sequence[int] = (64, 64),
        activation: Literal["softplus", "relu"] = "softplus",
        include_input: bool = True,
        geometric_init: bool = False,
        init_radius: float = 0.5,
        bounds: Tuple[float, float] = (-1.0, 1.0),
    ) -> None:
        super().__init__()
        if activation not in ("softplus", "relu"):
            raise ValueError(f"activation={activation!r}: use 'softplus' or 'relu'")
        if geometric_init and (encoding.kind == "finer" or out_dim != 1):
            raise ValueError("geometric_init applies to SDF fields (out_dim=1) with a non-FINER encoding")
        self.dim, self.lo, self.hi = dim, float(bounds[0]), float(bounds[1])
        self.kind = encoding.kind
        self.encoding, enc_dim = make_encoding(encoding, dim)
        self.include_input = include_input or encoding.kind == "finer"
        d_in = enc_dim + (dim if self.include_input else 0)
        widths = [d_in, *hidden, out_dim]
        if encoding.kind == "finer":
            layers = [
                FinerLayer(widths[i], widths[i + 1], encoding.finer_omega, i == 0, encoding.finer_bias_scale)
                for i in range(len(widths) - 2)
            ]
            last = nn.Linear(widths[-2], out_dim)
            bound = math.sqrt(6.0 / widths[-2]) / encoding.finer_omega
            nn.init.uniform_(last.weight, -bound, bound)
            self.mlp = nn.Sequential(*layers, last)
            return
        act = (lambda: nn.Softplus(beta=100.0)) if activation == "softplus" else nn.ReLU
        mods: list[nn.Module] = []
        for i in range(len(widths) - 1):
            mods.append(nn.Linear(widths[i], widths[i + 1]))
            if i < len(widths) - 2:
                mods.append(act())
        self.mlp = nn.Sequential(*mods)
        if geometric_init:
            self._geometric_init(init_radius, enc_dim)

    def _geometric_init(self, radius: float, enc_dim: int) -> None:
        if not self.include_input:
            raise ValueError("geometric_init needs include_input=True (the sphere is built from the coordinates)")
        linears = [m for m in self.mlp if isinstance(m, nn.Linear)]
        with torch.no_grad():
            for i, lin in enumerate(linears):
                d_out, d_in = lin.weight.shape
                if i == len(linears) - 1:
                    lin.weight.normal_(math.sqrt(math.pi) / math.sqrt(d_in), 1e-4)
                    lin.bias.fill_(-radius)
                    continue
                lin.weight.normal_(0.0, math.sqrt(2.0) / math.sqrt(d_out))
                lin.bias.zero_()
                if i == 0:
                    lin.weight[:, self.dim :].zero_()  # coordinates come first, then features
        # The sphere is built in unit-box coordinates, (x - centre) / half-width.

    def _normalised(self, x: Tensor) -> Tensor:
        """Coordinates in [-1, 1] (the MLP's raw input and the Fourier / FINER input)."""
        return (x - 0.5 * (self.lo + self.hi)) * (2.0 / (self.hi - self.lo))

    def forward(self, x: Float[Tensor, "*batch dim"]) -> Float[Tensor, "*batch out"]:
        batch = x.shape[:-1]
        flat = x.reshape(-1, self.dim)
        s = self._normalised(flat)
        feats = []
        if self.include_input:
            feats.append(s)
        if self.encoding is not None:
            # hash grids and triplanes take [0, 1]; Fourier features take [-1, 1]
            feats.append(self.encoding(s) if self.kind == "fourier" else self.encoding(0.5 * (s + 1.0)))
        h = torch.cat(feats, dim=-1) if len(feats) > 1 else feats[0]
        return self.mlp(h).reshape(*batch, -1)
