"""The stochastic-preconditioning perturbation: query a field at ``x + alpha * noise``."""

from __future__ import annotations

import math
from typing import Callable, Optional, Union

import torch
from jaxtyping import Float
from torch import Tensor

from sp_plugins.core.boundary import BoundaryKind, BoundsLike, apply_boundary, as_bounds, check_boundary_kind
from sp_plugins.core.noise import NoiseKind, sample_noise

AlphaLike = Union[float, Float[Tensor, "*batch 1"], Float[Tensor, "*batch"]]


def check_alpha(alpha: AlphaLike) -> None:
    """Reject negative or NaN alpha. Tensors are checked with one host sync: callers on a hot path
    validate once at set-up and skip this."""
    if isinstance(alpha, Tensor):
        if not bool(torch.isfinite(alpha).all()) or bool((alpha < 0).any()):
            raise ValueError("alpha: every value must be finite and >= 0 (got negative, NaN or inf)")
    elif not (isinstance(alpha, (int, float)) and math.isfinite(alpha) and alpha >= 0):
        raise ValueError(f"alpha={alpha!r}: must be a finite number >= 0")


def check_positions(x: Tensor) -> None:
    if not bool(torch.isfinite(x).all()):
        raise ValueError("positions: contain NaN or inf; fix the input points before perturbing them")


def compute_dtype(dtype: torch.dtype) -> torch.dtype:
    """The dtype SP computes and returns positions in: at least float32. A half-precision offset
    would be rounded away: fp16's spacing on [0.5, 1] is 2^-11 ~ 5e-4 and bf16's 2^-8 ~ 4e-3,
    larger than a typical late alpha."""
    return torch.promote_types(dtype, torch.float32)


def perturb(
    x: Float[Tensor, "*batch dim"],
    alpha: AlphaLike,
    *,
    noise: NoiseKind = "gaussian",
    boundary: BoundaryKind = "none",
    bounds: Optional[BoundsLike] = None,
    num_samples: int = 1,
    generator: Optional[torch.Generator] = None,
    validate: bool = True,
) -> Tensor:
    """Perturb positions by ``alpha`` times zero-mean unit-variance noise, then apply a boundary.

    Args:
        x: positions ``[*batch, dim]``.
        alpha: standard deviation of the offset per axis: a float or a per-point tensor
            (``[*batch]`` or ``[*batch, 1]``, e.g. from an :class:`AlphaGrid`).
        noise: ``gaussian`` | ``uniform`` | ``squared-gaussian`` (see :mod:`sp_plugins.core.noise`).
        boundary: ``reflect`` | ``clamp`` | ``none``; ``reflect`` and ``clamp`` need ``bounds``.
            Only coordinates that start inside the box are folded back into it.
        bounds: ``(lo, hi)`` as scalars or ``[dim]`` tensors, or a ``[2, dim]`` tensor.
        num_samples: K > 1 returns ``[K, *batch, dim]`` independent perturbations (average the
            field over them with :func:`perturbed_mean`).
        generator: for reproducible noise.
        validate: check alpha and positions for NaN / negative values (one host sync).

    Returns:
        ``[*batch, dim]`` (or ``[K, *batch, dim]``) perturbed positions, in float32 at least: a
        float16 / bfloat16 ``x`` (and ``alpha``) is promoted and never rounded back, so a small
        alpha still moves it. Gradients flow to ``x`` and to a tensor ``alpha`` (the
        reparameterisation trick).
    """
    check_boundary_kind(boundary)
    if num_samples < 1:
        raise ValueError(f"num_samples={num_samples}: must be >= 1")
    if validate:
        check_alpha(alpha)
        check_positions(x)
    x = x.to(compute_dtype(x.dtype))  # a no-op for float32 / float64 (the same tensor)
    if isinstance(alpha, Tensor):
        alpha = alpha.to(x.dtype)
    box = as_bounds(bounds, x.shape[-1], x, check=validate) if bounds is not None else None
    shape = (num_samples, *x.shape) if num_samples > 1 else x.shape
    eps = sample_noise(shape, noise, generator=generator, device=x.device, dtype=x.dtype)
    if isinstance(alpha, Tensor):
        if alpha.dim() == x.dim() - 1:
            alpha = alpha[..., None]
        y = torch.addcmul(x, eps, alpha)
    elif x.requires_grad:
        y = torch.add(x, eps, alpha=alpha)
    else:  # reuse the noise buffer: one pass, no allocation
        y = torch.add(x, eps, alpha=alpha, out=eps)
    return apply_boundary(y, boundary, box, origin=x)


def perturbed_mean(
    fn: Callable[[Tensor], Tensor],
    x: Float[Tensor, "*batch dim"],
    alpha: AlphaLike,
    num_samples: int,
    **perturb_kwargs,
) -> Tensor:
    """Monte-Carlo estimate of the blurred field ``E[fn(x + alpha * eps)]`` with K samples
    (the paper's multi-sample variant). ``fn`` maps ``[*batch, dim]`` to ``[*batch, ...]`` for
    any leading batch shape and is called once on all K draws."""
    xs = perturb(x, alpha, num_samples=num_samples, **perturb_kwargs)
    if num_samples == 1:
        return fn(xs)
    return fn(xs).mean(0)
