"""Property-based reference check of the core: Hypothesis draws the settings, and each
result is compared with a direct implementation of the paper's formulas written here, not with
the library's own helpers.

The reference: a perturbed query is ``x + alpha * eps`` with ``eps`` zero-mean, unit-variance noise
per axis; ``reflect`` folds a coordinate into ``[lo, hi]`` by the mod-2 mirror (u = (y - lo) / w,
t = u mod 2, folded = t if t <= 1 else 2 - t); ``clamp`` projects; a coordinate whose origin lies
outside the box is left as drawn. The schedules are the formulas of ``AlphaSchedule``'s docstring,
ending at ``min(round(end * total), total - 1)``.
"""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sp_plugins.core import AlphaGrid, AlphaSchedule, SPConfig, perturb, perturbed_mean, reflect

FAST = settings(max_examples=25, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
SLOW = settings(max_examples=8, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])

NOISES = ("gaussian", "uniform", "squared-gaussian")
DTYPES = (torch.float32, torch.float64, torch.float16, torch.bfloat16)


def gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


@st.composite
def boxes(draw, dim=None):
    """Non-unit, off-centre, generally non-cubic boxes ``(lo [dim], hi [dim])`` in float64."""
    dim = draw(st.sampled_from((2, 3))) if dim is None else dim
    lo = [draw(st.floats(-5.0, 5.0)) for _ in range(dim)]
    width = [draw(st.floats(0.1, 4.0)) for _ in range(dim)]
    if draw(st.booleans()):
        width = [width[0]] * dim  # a cube now and then (the sparse fold's scalar path)
    lo = torch.tensor(lo, dtype=torch.float64)
    return lo, lo + torch.tensor(width, dtype=torch.float64)


def fold_reference(y, lo, hi):
    """The mod-2 mirror of the paper's bounded domains, written independently of core.boundary."""
    w = hi - lo
    t = torch.remainder((y - lo) / w, 2.0)
    return torch.where(t <= 1.0, t, 2.0 - t) * w + lo


def noise_reference(shape, kind, generator, dtype):
    """The paper's noise kinds from the raw draws of ``generator`` (zero mean, unit variance):
    N(0, 1); U(-sqrt 3, sqrt 3); sign(z) z^2 / sqrt 3."""
    if kind == "uniform":
        return (torch.rand(shape, generator=generator, dtype=dtype) * 2.0 - 1.0) * math.sqrt(3.0)
    z = torch.randn(shape, generator=generator, dtype=dtype)
    return z if kind == "gaussian" else z * z.abs() / math.sqrt(3.0)


def positions(lo, hi, n, seed, outside_share=0.1):
    """``n`` positions inside the box, a share of them placed outside it (a host's empty space)."""
    u = torch.rand(n, lo.numel(), generator=gen(seed), dtype=torch.float64)
    x = lo + (hi - lo) * u
    k = int(n * outside_share)
    x[:k] = hi + (hi - lo) * (0.05 + u[:k])
    return x


@FAST
@given(
    box=boxes(),
    noise=st.sampled_from(NOISES),
    boundary=st.sampled_from(("reflect", "clamp", "none")),
    widths=st.floats(0.0, 3.0),
    k=st.integers(1, 4),
    dtype=st.sampled_from(DTYPES),
    per_point=st.booleans(),
    seed=st.integers(0, 2**31 - 1),
)
def test_perturb_equals_the_reference(box, noise, boundary, widths, k, dtype, per_point, seed):
    """perturb == x + alpha * eps, then the boundary, for any box, alpha up to three box widths, K
    draws and dtype; half-precision positions are computed and returned in float32."""
    lo, hi = box
    x64 = positions(lo, hi, 300, seed)
    x = x64.to(dtype)
    alpha = widths * float((hi - lo).max())
    a = torch.rand(300, generator=gen(seed + 1), dtype=torch.float64) * alpha if per_point else alpha
    out_dtype = torch.promote_types(dtype, torch.float32)
    bounds = (lo.to(out_dtype), hi.to(out_dtype)) if boundary != "none" else None
    y = perturb(x, a.to(dtype) if per_point else a, noise=noise, boundary=boundary, bounds=bounds, num_samples=k,
                generator=gen(seed))
    assert y.dtype == out_dtype
    assert y.shape == ((k,) if k > 1 else ()) + x.shape
    # the reference in float64 from the same draws (the noise is drawn in the output dtype)
    shape = ((k,) if k > 1 else ()) + x.shape
    eps = noise_reference(shape, noise, gen(seed), out_dtype).double()
    origin = x.to(out_dtype).double()
    a_ref = (a.to(dtype).to(out_dtype).double()[:, None] if per_point else a)
    raw = origin + a_ref * eps
    inside = ((origin >= lo) & (origin <= hi)).expand_as(raw)
    if boundary == "reflect":
        ref = torch.where(inside, fold_reference(raw, lo, hi), raw)
    elif boundary == "clamp":
        ref = torch.where(inside, torch.maximum(torch.minimum(raw, hi), lo), raw)
    else:
        ref = raw
    tol = 1e-9 if out_dtype == torch.float64 else 2e-5
    scale = float(hi.abs().max() + lo.abs().max() + alpha * 10)
    assert torch.allclose(y.double(), ref, atol=tol * scale, rtol=0)
    if boundary != "none":  # every coordinate that started inside ends inside
        slack = tol * scale
        assert bool(((y.double() >= lo - slack) & (y.double() <= hi + slack))[inside].all())


@FAST
@given(box=boxes(), k=st.integers(1, 3), widths=st.floats(0.0, 4.0), sparse=st.booleans(), seed=st.integers(0, 2**31 - 1))
def test_reflect_is_the_mod_2_fold_with_a_plus_minus_one_derivative(box, k, widths, sparse, seed):
    """Both fold paths (the CPU's sparse one, the accelerators' dense one) against the mod-2 mirror,
    with ``[K, N, dim]`` draws against ``[N, dim]`` origins, and d(out)/dy = +-1."""
    lo, hi = box
    origin = positions(lo, hi, 400, seed)
    shape = ((k,) if k > 1 else ()) + origin.shape
    y = (origin + widths * float((hi - lo).max()) * torch.randn(shape, generator=gen(seed), dtype=torch.float64))
    y.requires_grad_()
    out = reflect(y, lo, hi, origin, sparse=sparse)
    inside = ((origin >= lo) & (origin <= hi)).expand(shape)
    ref = torch.where(inside, fold_reference(y.detach(), lo, hi), y.detach())
    assert torch.allclose(out, ref, atol=1e-9, rtol=0)
    upstream = torch.randn(shape, generator=gen(seed + 2), dtype=torch.float64)
    out.backward(upstream)
    h = 1e-7  # the fold is piecewise linear: a one-sided difference is exact away from the kinks
    numeric = (fold_reference(y.detach() + h, lo, hi) - ref) / h
    numeric = torch.where(inside, numeric, torch.ones_like(numeric))
    ok = (numeric.abs() - 1.0).abs() < 1e-3  # skip the rare coordinate within h of a wall
    assert float(ok.double().mean()) > 0.99
    assert torch.equal(y.grad[ok], (upstream * numeric.round())[ok])


@SLOW
@given(box=boxes(dim=3), noise=st.sampled_from(NOISES), boundary=st.sampled_from(("reflect", "clamp", "none")),
       frac=st.floats(0.002, 0.05), seed=st.integers(0, 2**31 - 1))
def test_per_axis_std_is_alpha_away_from_the_walls(box, noise, boundary, frac, seed):
    """Far from the walls (alpha <= 1/20 of the smallest side, at the centre) the offset has zero
    mean and standard deviation alpha along every axis, whatever the noise and boundary."""
    lo, hi = box
    alpha = frac * float((hi - lo).min())
    x = ((lo + hi) / 2).expand(20_000, 3).clone()
    y = perturb(x, alpha, noise=noise, boundary=boundary, bounds=(lo, hi) if boundary != "none" else None,
                generator=gen(seed))
    d = (y - x) / alpha
    assert torch.allclose(d.std(0), torch.ones(3, dtype=torch.float64), rtol=0.08)
    assert bool((d.mean(0).abs() < 0.06).all())


@SLOW
@given(k=st.integers(2, 6), noise=st.sampled_from(NOISES), alpha=st.floats(0.05, 2.0), seed=st.integers(0, 2**31 - 1))
def test_k_draws_are_independent_and_averaged(k, noise, alpha, seed):
    """K draws of one point are independent (pairwise correlation ~0) and perturbed_mean averages
    them: the mean of K offsets has variance alpha^2 / K."""
    x = torch.zeros(20_000, 2, dtype=torch.float64)
    draws = perturb(x, alpha, noise=noise, num_samples=k, generator=gen(seed)) / alpha  # [K, N, 2]
    flat = draws.reshape(k, -1)
    corr = torch.corrcoef(flat)
    assert float((corr - torch.eye(k, dtype=torch.float64)).abs().max()) < 0.05
    mean = perturbed_mean(lambda p: p, x, alpha, k, noise=noise, generator=gen(seed)) / alpha
    assert torch.allclose(mean, draws.mean(0), atol=1e-12)
    assert float(mean.var()) == pytest.approx(1.0 / k, rel=0.1)


@SLOW
@given(noise=st.sampled_from(NOISES), grid=st.booleans(), alpha=st.floats(0.01, 0.1), seed=st.integers(0, 1000))
def test_preconditioner_draws_the_configured_noise_kind(noise, grid, alpha, seed):
    """The offsets of a StochasticPreconditioner have the configured kind's shape: bounded by
    sqrt(3) alpha and kurtosis 1.8 (uniform), kurtosis 3 (gaussian) or 105/9 (squared-gaussian)."""
    cfg = SPConfig(alpha0=alpha, schedule="constant", noise=noise, boundary="none", alpha_grid=grid,
                   alpha_grid_resolution=3, seed=seed)
    sp = cfg.setup(total_steps=10, bounds=(-1.0, 1.0)).train()
    x = torch.rand(20_000, 3, generator=gen(seed)) * 2 - 1
    d = ((sp(x) - x) / alpha).detach().double().reshape(-1)
    kurtosis = float((d**4).mean() / (d**2).mean() ** 2)
    low, high = {"uniform": (1.6, 2.0), "gaussian": (2.7, 3.3), "squared-gaussian": (7.5, 18.0)}[noise]
    assert low < kurtosis < high
    assert (float(d.abs().max()) <= math.sqrt(3.0) * (1 + 1e-5)) == (noise == "uniform")


def resolved_end(end, total):
    """The end step the reference expects: a fraction rounds, an absolute step is taken as is; both
    at the last step (total - 1) at the latest."""
    step = round(end * total) if end <= 1 else int(end)
    return max(1, min(step, total - 1))


@st.composite
def schedules(draw):
    kind = draw(st.sampled_from(("step", "exponential", "linear")))
    total = draw(st.integers(2, 5000))
    if draw(st.booleans()):
        end = draw(st.floats(0.01, 1.0))
    else:
        end = float(draw(st.integers(2, max(2, total))))
    return kind, total, end


@FAST
@given(sched=schedules(), alpha0=st.floats(1e-4, 1.0), r=st.sampled_from((1e-3, 1e-2, 0.1)), data=st.data())
def test_schedule_equals_its_formula_and_is_zero_at_and_after_the_end(sched, alpha0, r, data):
    kind, total, end = sched
    s = AlphaSchedule.resolve(kind, alpha0, end=end, total_steps=total, final_ratio=r)
    T = resolved_end(end, total)
    assert s.end_step == T <= total - 1
    for t in data.draw(st.lists(st.integers(0, 3 * total), min_size=5, max_size=20)) + [0, T - 1, T, total - 1]:
        if t >= T:
            expected = 0.0
        elif kind == "step":
            expected = alpha0
        elif kind == "linear":
            expected = alpha0 * (1 - t / T)
        else:
            expected = alpha0 * (r ** (t / T) - r) / (1 - r)
        assert s(t) == pytest.approx(expected, rel=1e-12, abs=1e-15)
        assert (s(t) > 0) == (t < T)


@FAST
@given(sched=schedules(), alpha0=st.sampled_from((0.0, 0.02)), grid=st.booleans(),
       mode=st.sampled_from(("replace", "scaled")), num_samples=st.integers(1, 3), data=st.data())
def test_preconditioner_returns_exactly_x_in_eval_and_at_and_after_the_end(sched, alpha0, grid, mode, num_samples, data):
    """In eval mode at any step, and in training at and after the end step, the input itself comes
    back (and blurred() is one plain call); before the end, with a grid or alpha0 > 0, it moves."""
    kind, total, end = sched
    if not grid and alpha0 == 0.0:
        alpha0 = 0.02
    cfg = SPConfig(alpha0=alpha0, schedule=kind, end=end, alpha_grid=grid, alpha_grid_mode=mode, alpha_grid_init=0.03,
                   alpha_grid_resolution=3, num_samples=num_samples, seed=0)
    sp = cfg.setup(total_steps=total, bounds=(-1.0, 1.0))
    T = resolved_end(end, total)
    x = torch.rand(50, 3) * 2 - 1
    fn = lambda p: p.sum(-1)  # noqa: E731
    after = data.draw(st.integers(T, 3 * total))
    before = data.draw(st.integers(0, T - 1))
    sp.train()
    sp.set_step(after)
    assert sp.alpha == 0.0 and not sp.active and sp(x) is x and torch.equal(sp.blurred(fn, x), fn(x))
    sp.set_step(before)
    assert sp.active and sp.alpha > 0 and not torch.equal(sp(x), x)
    if grid and mode == "replace":
        assert sp.grid_scale == 1.0 and torch.equal(sp.alpha_at(x), sp.alpha_grid(x))
    sp.eval()
    assert sp(x) is x and torch.equal(sp.blurred(fn, x), fn(x))


@FAST
@given(dim=st.sampled_from((2, 3)), param=st.sampled_from(("log", "alpha", "softplus")), res=st.integers(2, 4),
       boundary=st.sampled_from(("reflect", "none")), via_preconditioner=st.booleans(), seed=st.integers(0, 2**31 - 1))
def test_alpha_grid_gradient_equals_finite_differences(dim, param, res, boundary, via_preconditioner, seed):
    """d loss / d (stored grid) through ``x + alpha(x) * eps`` (reparameterisation, the fold) equals
    central finite differences, for every parameterisation, by perturb or by the preconditioner."""
    if via_preconditioner:
        cfg = SPConfig(alpha0=0.05, schedule="constant", boundary=boundary, alpha_grid=True, alpha_grid_resolution=res,
                       alpha_grid_parameterization=param, seed=seed)
        sp = cfg.setup(total_steps=10, bounds=(-1.0, 1.0), dim=dim).double().train()
        grid = sp.alpha_grid
        g = sp._generator(torch.device("cpu"))
        state = g.get_state()
    else:
        grid = AlphaGrid(dim=dim, resolution=res, init=0.05, bounds=(-1.0, 1.0), parameterization=param).double()
    with torch.no_grad():
        grid.set_values(0.02 + 0.1 * torch.rand(*([res] * dim), generator=gen(seed), dtype=torch.float64))
    x = torch.rand(64, dim, generator=gen(seed + 1), dtype=torch.float64) * 1.6 - 0.8
    w = torch.randn(64, dim, generator=gen(seed + 2), dtype=torch.float64)

    def loss():
        if via_preconditioner:
            g.set_state(state)  # the same noise for every evaluation
            y = sp(x)
        else:
            y = perturb(x, grid(x), boundary=boundary, bounds=(-1.0, 1.0) if boundary == "reflect" else None,
                        generator=gen(seed + 3))
        return (torch.sin(3 * y) * w).sum()

    grid.zero_grad()
    loss().backward()
    analytic = grid.param.grad.reshape(-1).clone()
    flat = grid.param.data.view(-1)
    h = 1e-6
    for i in torch.randperm(flat.numel(), generator=gen(seed + 4))[:6].tolist():
        keep = float(flat[i])
        with torch.no_grad():
            flat[i] = keep + h
            up = float(loss())
            flat[i] = keep - h
            down = float(loss())
            flat[i] = keep
        assert analytic[i].item() == pytest.approx((up - down) / (2 * h), rel=1e-4, abs=1e-7)


@FAST
@given(dim=st.sampled_from((2, 3)), src=st.sampled_from(("log", "alpha", "softplus")),
       dst=st.sampled_from(("log", "alpha", "softplus")), seed=st.integers(0, 2**31 - 1))
def test_a_grid_loads_a_checkpoint_of_any_parameterisation(dim, src, dst, seed):
    """A checkpoint names how it stored alpha (log_alpha / alpha / logits); a grid of any
    parameterisation loads it (also strictly) to the same alpha."""
    a = AlphaGrid(dim=dim, resolution=3, init=0.03, parameterization=src)
    a.set_values(0.005 + 0.05 * torch.rand(*([3] * dim), generator=gen(seed)))
    b = AlphaGrid(dim=dim, resolution=3, init=0.03, parameterization=dst)
    parent = torch.nn.Module()
    parent.grid = b
    result = parent.load_state_dict({f"grid.{k}": v for k, v in a.state_dict().items()}, strict=True)
    assert not result.missing_keys and not result.unexpected_keys
    assert torch.allclose(b.values(), a.values(), rtol=1e-5)
    x = torch.rand(20, dim, generator=gen(seed + 1)) * 2 - 1
    if src == dst:
        assert torch.equal(b(x), a(x))
