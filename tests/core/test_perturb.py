import math

import pytest
import torch
from scipy import stats

from sp_plugins import perturb
from sp_plugins.core import NOISE_KINDS, perturbed_mean, reflect, sample_noise


def gen(seed=0):
    g = torch.Generator()
    g.manual_seed(seed)
    return g


@pytest.mark.parametrize("kind", NOISE_KINDS)
def test_noise_kinds_have_zero_mean_and_unit_variance(kind):
    eps = sample_noise((400_000,), kind, generator=gen(1), dtype=torch.float64)
    assert abs(float(eps.mean())) < 0.01
    assert abs(float(eps.var()) - 1.0) < 0.02


def test_noise_kinds_differ_in_shape():
    g = sample_noise((200_000,), "gaussian", generator=gen(2))
    u = sample_noise((200_000,), "uniform", generator=gen(2))
    s = sample_noise((200_000,), "squared-gaussian", generator=gen(2))
    assert float(u.abs().max()) <= math.sqrt(3) + 1e-6
    kurt = lambda e: float((e**4).mean() / (e**2).mean() ** 2)  # noqa: E731
    assert kurt(u) == pytest.approx(1.8, abs=0.05)
    assert kurt(g) == pytest.approx(3.0, abs=0.1)
    assert kurt(s) == pytest.approx(105 / 9, rel=0.06)  # E[z^8] / E[z^4]^2 of z ~ N(0, 1)


def test_noise_docstring_states_the_kurtosis_it_draws():
    """The module documents each kind's shape: the squared Gaussian's kurtosis is 105/9, not 15."""
    import re

    import sp_plugins.core.noise as noise

    stated = re.search(r"kurtosis\s+E\[z\^8\] / E\[z\^4\]\^2 = 105/9 ~ ([0-9.]+)", noise.__doc__)
    assert stated is not None and "kurtosis 15" not in noise.__doc__
    e = sample_noise((400_000,), "squared-gaussian", generator=gen(5), dtype=torch.float64)
    assert float((e**4).mean() / (e**2).mean() ** 2) == pytest.approx(float(stated.group(1)), rel=0.06)


def test_reflect_keeps_uniform_uniform_but_clamp_does_not():
    n = 200_000
    x = torch.rand(n, 1, generator=gen(3), dtype=torch.float64)
    alpha = 1.0  # as large as the box
    refl = perturb(x, alpha, boundary="reflect", bounds=(0.0, 1.0), generator=gen(4))[:, 0].numpy()
    clmp = perturb(x, alpha, boundary="clamp", bounds=(0.0, 1.0), generator=gen(4))[:, 0].numpy()
    assert stats.kstest(refl, "uniform").pvalue > 1e-3
    assert stats.kstest(clmp, "uniform").pvalue < 1e-12
    # clamp piles a large share of the samples exactly on the faces
    assert ((clmp == 0.0) | (clmp == 1.0)).mean() > 0.3
    # chi-square on 50 bins confirms uniformity of the reflected points
    counts, _ = torch.histogram(torch.from_numpy(refl), bins=50, range=(0.0, 1.0))
    assert stats.chisquare(counts.numpy()).pvalue > 1e-3


@pytest.mark.parametrize("boundary", ["reflect", "clamp"])
def test_perturbed_points_stay_in_any_box(boundary):
    lo = torch.tensor([-2.0, 0.5, 10.0])
    hi = torch.tensor([3.0, 0.7, 10.25])
    x = lo + (hi - lo) * torch.rand(50_000, 3, generator=gen(5))
    y = perturb(x, 7.0, boundary=boundary, bounds=(lo, hi), generator=gen(6))  # many reflections
    assert bool(((y >= lo) & (y <= hi)).all())
    aabb = torch.stack([lo, hi])  # nerfstudio's SceneBox.aabb layout
    y2 = perturb(x, 7.0, boundary=boundary, bounds=aabb, generator=gen(6))
    assert torch.equal(y, y2)


def test_reflect_is_a_mirror_near_the_faces():
    lo, hi = torch.tensor(0.0), torch.tensor(1.0)
    x = torch.tensor([-0.25, 1.25, 2.5, -1.5, 0.3])
    assert torch.allclose(reflect(x, lo, hi), torch.tensor([0.25, 0.75, 0.5, 0.5, 0.3]))


@pytest.mark.parametrize("sparse", [True, False], ids=["sparse-fold", "dense-fold"])
def test_reflect_matches_an_unfolded_reference_in_a_non_cubic_box_with_its_derivative(sparse):
    """The fold only touches escaped coordinates: check it against the triangle-wave formula on
    every coordinate, many reflections deep, with some origins outside the box."""
    lo, hi = torch.tensor([-1.0, -2.0, 0.0], dtype=torch.float64), torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    width = hi - lo
    origin = torch.rand(5000, 3, generator=gen(11), dtype=torch.float64) * width * 1.2 + lo - 0.1 * width
    y = (origin + 3.0 * torch.randn(5000, 3, generator=gen(12), dtype=torch.float64)).requires_grad_()
    out = reflect(y, lo, hi, origin, sparse=sparse)
    u = (y.detach() - lo) / width
    wave = (u - 2 * torch.floor((u + 1) / 2)).abs()  # triangle wave, period 2, values in [0, 1]
    inside = (origin >= lo) & (origin <= hi)
    expected = torch.where(inside, wave * width + lo, y.detach())
    assert torch.allclose(out, expected, atol=1e-9)
    assert ((out >= lo) & (out <= hi))[inside].all()
    out.backward(torch.ones_like(out))
    slope = torch.sign(u - 2 * torch.floor((u + 1) / 2))  # +1 on rising, -1 on falling stretches
    numeric = torch.where(inside, slope, torch.ones_like(u))
    assert torch.equal(y.grad, numeric)


def test_dense_fold_takes_the_gpus_sync_free_branch_on_the_cpu_with_the_same_result():
    """What counts a GPU run's syncs on a CPU (sp-gpu-check) folds densely inside the switch; the
    default returns after it."""
    from sp_plugins.core import boundary

    cpu = torch.device("cpu")
    y = torch.randn(500, 3) * 3
    lo, hi = torch.tensor([-1.0, 0.0, -0.5]), torch.tensor([1.0, 0.5, 2.0])
    assert boundary.sparse_fold_on(cpu)
    with boundary.dense_fold():
        assert not boundary.sparse_fold_on(cpu)
        dense = reflect(y, lo, hi)
    assert boundary.sparse_fold_on(cpu)
    assert torch.equal(dense, reflect(y, lo, hi, sparse=False)) and torch.allclose(dense, reflect(y, lo, hi, sparse=True), atol=1e-6)


def test_reflect_accepts_non_contiguous_positions_and_gradients():
    y = (torch.randn(3, 400, generator=gen(13)) * 2.0).t().requires_grad_()  # [400, 3], transposed storage
    out = reflect(y, torch.tensor(-1.0), torch.tensor(1.0))
    assert (out.abs() <= 1.0).all()
    upstream = torch.randn(3, 400, generator=gen(14)).t()
    out.backward(upstream)  # a non-contiguous incoming gradient
    assert torch.equal(y.grad.abs(), upstream.abs())  # derivative +-1 everywhere


def test_mean_of_perturbed_sine_matches_gaussian_blur():
    w, alpha = 6.0, 0.2
    x = torch.linspace(-1, 1, 9, dtype=torch.float64)[:, None]
    samples = perturb(x, alpha, num_samples=200_000, generator=gen(7))
    mc = torch.sin(w * samples).mean(0)[:, 0]
    expected = math.exp(-(w**2) * alpha**2 / 2) * torch.sin(w * x[:, 0])
    assert torch.allclose(mc, expected, atol=0.006)
    # and it is really blurred: the unblurred sine is far off
    assert (mc - torch.sin(w * x[:, 0])).abs().max() > 0.2


def test_uniform_noise_blurs_with_a_sinc_kernel():
    w, alpha = 5.0, 0.3
    x = torch.linspace(-1, 1, 7, dtype=torch.float64)[:, None]
    mc = perturbed_mean(lambda p: torch.sin(w * p), x, alpha, 200_000, noise="uniform", generator=gen(8))[:, 0]
    a = math.sqrt(3) * w * alpha
    assert torch.allclose(mc, math.sin(a) / a * torch.sin(w * x[:, 0]), atol=0.006)


def test_per_point_alpha_and_gradients():
    x = torch.zeros(4, 3, requires_grad=True)
    alpha = torch.tensor([0.0, 0.1, 0.2, 0.4], requires_grad=True)
    y = perturb(x, alpha, generator=gen(9))
    assert torch.equal(y[0], x[0].detach())  # alpha 0 leaves the point alone
    y.sum().backward()
    assert torch.allclose(x.grad, torch.ones_like(x))
    assert alpha.grad is not None and alpha.grad.abs().sum() > 0  # reparameterisation trick
    # reflection flips the gradient sign for points that bounced
    z = torch.full((1, 1), 0.99, requires_grad=True)
    g = torch.Generator().manual_seed(0)
    while True:  # find a draw that crosses the face
        st = g.get_state()
        out = perturb(z, 0.5, boundary="reflect", bounds=(0.0, 1.0), generator=g)
        if float(sample_noise((1, 1), generator=torch.Generator().set_state(st))) > 0.02:
            break
    out.sum().backward()
    assert float(z.grad) == -1.0


def test_generator_makes_noise_reproducible():
    x = torch.rand(10, 3)
    assert torch.equal(perturb(x, 0.1, generator=gen(1)), perturb(x, 0.1, generator=gen(1)))
    assert not torch.equal(perturb(x, 0.1, generator=gen(1)), perturb(x, 0.1, generator=gen(2)))


def test_multi_sample_average_reduces_variance():
    x = torch.zeros(2000, 1, dtype=torch.float64)
    one = perturbed_mean(torch.sin, x, 0.5, 1, generator=gen(3))
    many = perturbed_mean(torch.sin, x, 0.5, 16, generator=gen(3))
    assert many.shape == one.shape == x.shape
    assert float(many.var()) < float(one.var()) / 8


@pytest.mark.parametrize(
    "kwargs, word",
    [
        (dict(alpha=-0.1), "alpha"),
        (dict(alpha=float("nan")), "alpha"),
        (dict(alpha=torch.tensor([0.1, -1.0])), "alpha"),
        (dict(alpha=0.1, noise="cauchy"), "noise"),
        (dict(alpha=0.1, boundary="wrap"), "boundary"),
        (dict(alpha=0.1, boundary="reflect", bounds=(1.0, 1.0)), "empty"),
        (dict(alpha=0.1, boundary="reflect"), "bounds"),
        (dict(alpha=0.1, num_samples=0), "num_samples"),
    ],
)
def test_bad_input_names_the_argument(kwargs, word):
    x = torch.rand(2, 3)
    with pytest.raises(ValueError, match=word):
        perturb(x, **kwargs)


def test_nan_positions_are_rejected():
    x = torch.rand(3, 3)
    x[1, 2] = float("nan")
    with pytest.raises(ValueError, match="positions"):
        perturb(x, 0.1)
    x[1, 2] = float("inf")
    with pytest.raises(ValueError, match="positions"):
        perturb(x, 0.1)


@pytest.mark.parametrize("boundary", ["reflect", "clamp"])
def test_samples_that_start_outside_the_box_are_not_pulled_in(boundary):
    """A host may hand over samples beyond its box (treated as empty space): folding them into
    the box would give them the density of the interior."""
    x = torch.tensor([[1.5, 0.0, 0.0], [-3.0, 0.2, 0.9]]).repeat(1000, 1)
    y = perturb(x, 0.05, boundary=boundary, bounds=(-1.0, 1.0), generator=gen(0))
    outside = x.abs() > 1
    assert bool((y[outside].abs() > 1.2).all())  # still far outside, just perturbed
    assert float((y[outside] - x[outside]).std()) == pytest.approx(0.05, rel=0.1)
    assert bool((y[~outside].abs() <= 1).all())  # the inside coordinates were folded


@pytest.mark.parametrize("sparse", [True, False], ids=["sparse-fold", "dense-fold"])
@pytest.mark.parametrize("box", ["cube", "non-cubic"])
def test_multi_sample_reflect_folds_each_draw_against_its_own_origin(sparse, box, monkeypatch):
    """K > 1 with reflect: ``[K, N, 3]`` draws folded against the ``[N, 3]`` origins (
    defect 1: the CPU's sparse fold indexed the origins with the draws' flat indices)."""
    import sp_plugins.core.boundary as boundary

    if box == "cube":
        lo, hi = torch.full((3,), -1.0), torch.ones(3)
    else:
        lo, hi = torch.tensor([-2.0, 0.5, 10.0]), torch.tensor([3.0, 0.7, 10.25])
    origin = lo + (hi - lo) * torch.rand(3000, 3, generator=gen(21))
    origin[:7] = hi + 0.5  # a few samples the host placed outside the box
    x = origin.clone().requires_grad_()
    real = boundary.reflect
    monkeypatch.setattr(boundary, "reflect", lambda *a, **k: real(*a, **dict(k, sparse=sparse)))
    y = perturb(x, 0.3, num_samples=4, boundary="reflect", bounds=(lo, hi), generator=gen(22))
    assert y.shape == (4, 3000, 3)
    raw = origin + 0.3 * sample_noise((4, 3000, 3), generator=gen(22))
    u = (raw - lo) / (hi - lo)
    wave = (u - 2 * torch.floor((u + 1) / 2)).abs() * (hi - lo) + lo
    inside = ((origin >= lo) & (origin <= hi)).expand_as(raw)
    assert torch.allclose(y, torch.where(inside, wave, raw), atol=1e-5)
    y.sum().backward()  # each origin gets the sum of its K draws' +-1 derivatives
    slope = torch.where(inside, torch.sign(u - 2 * torch.floor((u + 1) / 2)), torch.ones_like(u))
    assert torch.equal(x.grad, slope.sum(0))


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_positions_are_perturbed_in_float32(dtype):
    """A tiny alpha must move half-precision positions: fp16 has a spacing of 2^-11 on
    [0.5, 1] and bf16 2^-8, so rounding x + 1e-4 * eps back would undo the move."""
    x = (0.5 + 0.5 * torch.rand(20_000, 3, generator=gen(31))).to(dtype)
    y = perturb(x, 1e-4, generator=gen(32))
    assert y.dtype == torch.float32
    assert float((y != x.float()).float().mean()) >= 0.999
    # the offset is the float32 draw itself, not a rounded one
    expected = x.float() + 1e-4 * sample_noise((20_000, 3), generator=gen(32), dtype=torch.float32)
    assert torch.allclose(y, expected, atol=1e-7, rtol=0)
    alpha = torch.full((20_000, 1), 1e-4, dtype=dtype)  # a per-point alpha in half precision too
    y2 = perturb(x, alpha, boundary="reflect", bounds=(0.0, 1.0), num_samples=2, generator=gen(33))
    assert y2.dtype == torch.float32 and float((y2 != x.float()).float().mean()) >= 0.999
    assert bool(((y2 >= 0) & (y2 <= 1)).all())
