"""grid_sample under deterministic mode: its CUDA backward has no deterministic implementation, so
the alpha grid and the ReLU field interpolate by gathers then; the gathers are the same function."""

import pytest
import torch
import torch.nn.functional as F

from sp_plugins.encodings import grid_sample as module
from sp_plugins.encodings.grid_sample import deterministic_path_needed, grid_sample_gather


@pytest.mark.parametrize("dims", [2, 3])
@pytest.mark.parametrize("padding_mode", ["zeros", "border"])
@pytest.mark.parametrize("align_corners", [True, False])
def test_the_gather_path_is_grid_sample(dims, padding_mode, align_corners):
    torch.manual_seed(0)
    spatial = (4, 5, 3)[:dims]
    values = torch.randn(1, 2, *spatial, dtype=torch.float64, requires_grad=True)
    points = (torch.rand(1, *([1] * (dims - 1)), 200, dims, dtype=torch.float64) * 2.6 - 1.3).requires_grad_(True)  # some outside
    weights = torch.randn(1, 2, *([1] * (dims - 1)), 200, dtype=torch.float64)
    results = []
    for fn in (lambda *a, **k: F.grid_sample(*a, mode="bilinear", **k), grid_sample_gather):
        out = fn(values, points, padding_mode=padding_mode, align_corners=align_corners)
        results.append((out, *torch.autograd.grad((out * weights).sum(), (values, points))))
    for expected, got in zip(*results):
        torch.testing.assert_close(got, expected, rtol=1e-9, atol=1e-9)


def test_only_a_cuda_backward_in_deterministic_mode_takes_the_gathers():
    cuda, cpu = torch.device("cuda", 0), torch.device("cpu")
    assert not deterministic_path_needed(cuda, True)
    torch.use_deterministic_algorithms(True)
    try:
        assert deterministic_path_needed(cuda, True)
        assert not deterministic_path_needed(cpu, True)  # the CPU backward is deterministic
        assert not deterministic_path_needed(cuda, False)
        with torch.no_grad():
            assert not deterministic_path_needed(cuda, True)
    finally:
        torch.use_deterministic_algorithms(False)
    torch.use_deterministic_algorithms(True, warn_only=True)  # warned about, and avoidable: gathers too
    try:
        assert deterministic_path_needed(cuda, True)
    finally:
        torch.use_deterministic_algorithms(False)


def test_the_alpha_grid_and_the_relu_field_go_through_it(monkeypatch):
    from sp_plugins.core import AlphaGrid
    from sp_plugins.nerfstudio.relu_field.field import ReLUField

    torch.manual_seed(0)
    alpha = AlphaGrid(dim=3, resolution=4, init=0.02, bounds=(-1.0, 1.0))
    with torch.no_grad():
        alpha.param.add_(torch.randn_like(alpha.param) * 0.1)
    relu = ReLUField(torch.tensor([[-1.0] * 3, [1.0] * 3]), resolution=4, color_mode="rgb")
    x = torch.rand(50, 3) * 2.2 - 1.1
    runs = {}
    calls = []
    for path in ("grid_sample", "gathers"):
        monkeypatch.setattr(module, "deterministic_path_needed", lambda device, needs_grad: path == "gathers")
        monkeypatch.setattr(module, "grid_sample_gather", lambda *a, **k: calls.append(path) or grid_sample_gather(*a, **k))
        outs = [alpha(x), relu.lookup(x)]
        grads = torch.autograd.grad(sum(o.square().sum() for o in outs), [alpha.param, relu.grid])
        runs[path] = outs + list(grads)
    assert calls == ["gathers", "gathers"]
    for a, b in zip(runs["grid_sample"], runs["gathers"]):
        torch.testing.assert_close(b, a, rtol=1e-5, atol=1e-6)
