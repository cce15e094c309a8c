"""HashGrid backends: the choice follows the module's device, checkpoints move between the torch
``table`` and tcnn's flat ``params`` (checked against an independent tcnn-layout stand-in), and a
forward pass makes no tensor from Python values (a host sync on CUDA).

What the layout tests do NOT show: the stand-in (:mod:`sp_plugins.encodings.tcnn_layout`) is our own
reading of tiny-cuda-nn's ``grid.h``, written by us. ``table`` agreeing with it shows that two
independent implementations of that reading agree, not that tiny-cuda-nn lays its ``params`` out
that way; only a run against the real ``tinycudann`` on a GPU checks that (``sp-gpu-check`` and the
CUDA-only test in tests/nerfstudio/test_nerfacto_hash_grid.py, both skipped without one)."""

import copy
import logging
import sys
import types

import pytest
import torch

from sp_plugins.encodings import FrequencyEncoding, HashGrid
from sp_plugins.encodings import hashgrid as hashgrid_module
from sp_plugins.encodings.tcnn_layout import TcnnLayoutEncoding

CONFIGS = {
    "hash+dense": dict(num_levels=3, features_per_level=2, log2_hashmap_size=7, base_resolution=3, per_level_scale=1.6),
    "one-feature": dict(num_levels=4, features_per_level=1, log2_hashmap_size=6, base_resolution=2, per_level_scale=1.7),
    "four-smoothstep": dict(num_levels=2, features_per_level=4, log2_hashmap_size=8, base_resolution=5, per_level_scale=2.0, interpolation="Smoothstep"),
    "dense-grid": dict(num_levels=2, features_per_level=2, log2_hashmap_size=4, base_resolution=4, per_level_scale=1.5, grid_type="Dense"),
    "2d": dict(num_levels=3, features_per_level=2, log2_hashmap_size=6, base_resolution=4, per_level_scale=2.0, n_input_dims=2),
}


def torch_grid(name, **kw):
    torch.manual_seed(0)
    return HashGrid(**CONFIGS[name], backend="torch", init_scale=1.0, **kw)


@pytest.fixture
def fake_tcnn(monkeypatch):
    """``tinycudann`` is the stand-in, and "CPU" counts as a device tcnn runs on."""
    module = types.ModuleType("tinycudann")
    module.Encoding = TcnnLayoutEncoding
    monkeypatch.setitem(sys.modules, "tinycudann", module)
    monkeypatch.setattr(hashgrid_module, "TCNN_DEVICE_TYPES", ("cpu",))
    monkeypatch.setattr(hashgrid_module, "_logged_choices", set())
    return module


def _inputs(grid, n=300):
    torch.manual_seed(1)
    x = torch.rand(n, grid.n_input_dims) * 1.2 - 0.1  # some points outside [0, 1], as perturbed points are
    return x.requires_grad_(True)


def _output_and_input_grad(module, x):
    out = module(x)
    (g,) = torch.autograd.grad((out * torch.linspace(-1, 1, out.shape[-1])).sum(), x)
    return out.detach(), g


@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_table_is_tcnns_params_layout(name):
    """The stand-in reads tcnn's layout on its own; given ``table.reshape(-1)`` it computes our outputs
    (our reading of tcnn against our stand-in of it: see the module docstring)."""
    grid = torch_grid(name)
    standin = TcnnLayoutEncoding(grid.n_input_dims, grid.tcnn_config())
    assert standin.params.dtype == torch.float32 and standin.params.shape == (grid.table.numel(),)
    with torch.no_grad():
        standin.params.copy_(grid.table.reshape(-1))
    x = _inputs(grid)
    out, g = _output_and_input_grad(grid, x)
    out_s, g_s = _output_and_input_grad(standin, x)
    torch.testing.assert_close(out_s, out, rtol=1e-5, atol=2e-6)
    torch.testing.assert_close(g_s, g, rtol=1e-4, atol=2e-4)
    shuffled = grid.table.detach().view(grid.n_table_rows, -1).roll(1, 0).reshape(-1)  # rows off by one: the layout test can fail
    with torch.no_grad():
        standin.params.copy_(shuffled)
    assert (standin(x) - out).abs().max() > 1e-2


@pytest.mark.parametrize("name", ["hash+dense", "four-smoothstep"])
def test_torch_checkpoint_loads_into_the_tcnn_standin_and_back(name, fake_tcnn):
    grid = torch_grid(name)
    x = _inputs(grid)
    expected = grid(x).detach()
    parent = torch.nn.Sequential(grid)
    state = parent.state_dict()
    assert list(state) == ["0.table"]

    tcnn_side = torch.nn.Sequential(HashGrid(**CONFIGS[name], backend="auto"))
    assert tcnn_side[0].backend == "tcnn" and isinstance(tcnn_side[0].tcnn_encoding, TcnnLayoutEncoding)
    tcnn_side.load_state_dict(state)  # strict: the key is mapped, nothing left over
    tcnn_state = tcnn_side.state_dict()
    assert list(tcnn_state) == ["0.tcnn_encoding.params"] and tcnn_state["0.tcnn_encoding.params"].dim() == 1
    torch.testing.assert_close(tcnn_side(x).detach(), expected, rtol=1e-5, atol=2e-6)

    back = torch.nn.Sequential(HashGrid(**CONFIGS[name], backend="torch"))
    back.load_state_dict(tcnn_state)
    assert torch.equal(back[0].table, grid.table)
    assert torch.equal(back(x), grid(x))


def test_a_checkpoint_of_another_grid_is_refused_with_its_sizes(fake_tcnn):
    state = {"tcnn_encoding.params": torch.zeros(100)}
    grid = torch_grid("hash+dense")
    with pytest.raises(RuntimeError, match="holds 100 grid values, this grid 576"):
        grid.load_state_dict(state)


def test_auto_on_the_cpu_of_a_gpu_machine_uses_torch(monkeypatch, caplog):
    """tcnn importable and CUDA present: a module on the CPU still runs the torch backend."""
    module = types.ModuleType("tinycudann")
    module.Encoding = TcnnLayoutEncoding
    monkeypatch.setitem(sys.modules, "tinycudann", module)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(hashgrid_module, "_logged_choices", set())
    assert hashgrid_module.tcnn_available()
    with caplog.at_level(logging.INFO, logger=hashgrid_module.__name__):
        grids = [HashGrid(**CONFIGS["hash+dense"], backend="auto") for _ in range(2)]
    assert all(g.backend == "torch" and g.table is not None for g in grids)
    messages = [r.getMessage() for r in caplog.records]
    assert sum("'auto' -> 'torch'" in m and "on cpu" in m for m in messages) == 1  # once
    with pytest.raises(ValueError, match="cannot run on cpu"):
        grids[0].requested_backend = "tcnn"
        grids[0].cpu()  # an explicit tcnn grid moved off the GPU is refused, not silently slow


def test_torch_backend_only_keeps_auto_grids_on_torch_where_tcnn_runs(fake_tcnn):
    """The switch sp-gpu-check times our torch grid on a GPU with: inside it an ``auto`` grid takes the
    torch backend and an explicit ``tcnn`` one is refused; after it, tcnn is chosen again."""
    assert HashGrid(**CONFIGS["hash+dense"], backend="auto").backend == "tcnn"
    with hashgrid_module.torch_backend_only():
        assert not hashgrid_module.tcnn_usable("cpu")
        assert HashGrid(**CONFIGS["hash+dense"], backend="auto").backend == "torch"
        with pytest.raises(ValueError, match="backend='tcnn' cannot"):
            HashGrid(**CONFIGS["hash+dense"], backend="tcnn")
    assert HashGrid(**CONFIGS["hash+dense"], backend="auto").backend == "tcnn"


def test_moving_the_module_hands_the_values_over(fake_tcnn, monkeypatch):
    monkeypatch.setattr(hashgrid_module, "TCNN_DEVICE_TYPES", ("cuda",))
    grid = HashGrid(**CONFIGS["hash+dense"], backend="auto", init_scale=1.0)
    original = grid.table.detach().clone()
    x = _inputs(grid)
    expected = grid(x).detach()
    assert grid.backend == "torch"
    monkeypatch.setattr(hashgrid_module, "TCNN_DEVICE_TYPES", ("cpu",))  # "the module moved to a tcnn device"
    assert grid.to("cpu") is grid
    assert grid.backend == "tcnn" and grid.table is None
    assert torch.equal(grid.tcnn_encoding.params.detach(), original.reshape(-1))
    torch.testing.assert_close(grid(x).detach(), expected, rtol=1e-5, atol=2e-6)
    monkeypatch.setattr(hashgrid_module, "TCNN_DEVICE_TYPES", ("cuda",))  # "and back to the CPU"
    grid.cpu()
    assert grid.backend == "torch" and grid.tcnn_encoding is None
    assert torch.equal(grid.table.detach(), original)
    assert torch.equal(grid(x).detach(), expected)


def test_float64_tables_stay_on_the_torch_backend(fake_tcnn):
    grid = HashGrid(**CONFIGS["hash+dense"], backend="auto", dtype=torch.float64)
    assert grid.backend == "torch"
    assert HashGrid(**CONFIGS["hash+dense"], backend="auto").backend == "tcnn"
    assert HashGrid(**CONFIGS["hash+dense"], backend="torch").backend == "torch"


def test_constants_are_buffers_on_the_modules_device_and_survive_casts():
    grid = torch_grid("hash+dense")
    buffers = dict(grid.named_buffers())
    assert {"_const_scales", "_const_offsets", "_const_primes"} <= set(buffers)
    assert all(b.device == grid.table.device for b in buffers.values())
    assert "_const_scales" not in grid.state_dict()  # not persistent: checkpoints hold the table only
    x = torch.rand(20, 3)
    expected = grid(x)
    grid.half()
    assert grid._const_scales.dtype == torch.float32  # level scales are never rounded to half
    assert torch.equal(grid._const_scales, torch.tensor([lv.scale for lv in grid.levels]))
    torch.testing.assert_close(grid(x), expected, rtol=2e-3, atol=2e-3)


def _no_tensor_from_python(monkeypatch):
    made = []
    real = torch.tensor

    def counting(*args, **kwargs):
        made.append(args[0] if args else kwargs)
        return real(*args, **kwargs)

    monkeypatch.setattr(torch, "tensor", counting)
    return made


def test_a_training_step_builds_no_tensor_from_python_values(monkeypatch):
    """``torch.tensor(list, device=cuda)`` is a blocking host-to-device copy; none per step."""
    grid = torch_grid("hash+dense")
    freq = FrequencyEncoding(n_input_dims=3, num_frequencies=4)
    x = torch.rand(64, 3, requires_grad=True)
    made = _no_tensor_from_python(monkeypatch)
    for active in (3, 2):  # coarse-to-fine slices the constants too
        grid.set_active_levels(active)
        y = grid(x).sum() + freq(x, variance=torch.full_like(x, 1e-3)).sum()
        (g,) = torch.autograd.grad(y, x, create_graph=True)  # the eikonal's double backward
        g.square().sum().backward()
    assert made == []
    monkeypatch.undo()
    torch.testing.assert_close(freq.frequencies(x), torch.tensor(freq.angular_frequencies, dtype=torch.float32))


def _model(name, backend):
    torch.manual_seed(0)
    grid = HashGrid(**CONFIGS[name], backend=backend, init_scale=1.0)
    return torch.nn.Sequential(grid, torch.nn.Linear(grid.n_output_dims, 1))


def _adam_steps(model, optimizer, x, n):
    for _ in range(n):
        optimizer.zero_grad()
        model(x).square().mean().backward()
        optimizer.step()


@pytest.mark.parametrize("first, then", [("torch", "tcnn"), ("tcnn", "torch")])
def test_a_run_resumed_under_the_other_backend_keeps_its_adam_moments(first, then, fake_tcnn):
    """Train, save weights and optimizer state, resume under the other backend (a CPU run resumed on
    a GPU with tcnn, or the reverse): Adam's moments fit the grid's parameter and carry on."""
    backends = {"torch": "torch", "tcnn": "auto"}  # auto: the stand-in on this "tcnn device"
    name = "hash+dense"
    model = _model(name, backends[first])
    assert model[0].backend == first
    x = _inputs(model[0]).detach()
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-2)
    _adam_steps(model, optimizer, x, 2)
    saved_model, saved_optimizer = copy.deepcopy((model.state_dict(), optimizer.state_dict()))  # a checkpoint
    _adam_steps(model, optimizer, x, 1)  # the uninterrupted run's next step

    resumed = _model(name, backends[then])
    assert resumed[0].backend == then
    resumed.load_state_dict(saved_model)
    resumed_optimizer = torch.optim.Adam(resumed.parameters(), lr=1e-2)
    resumed_optimizer.load_state_dict(saved_optimizer)
    _adam_steps(resumed, resumed_optimizer, x, 1)  # crashed here: the moments had the other layout
    grid_param = next(resumed[0].parameters())
    moments = resumed_optimizer.state[grid_param]["exp_avg"]
    assert moments.shape == grid_param.shape and moments.abs().sum() > 0
    for (key, a), b in zip(model.state_dict().items(), resumed.state_dict().values()):
        torch.testing.assert_close(b.reshape(-1), a.reshape(-1), rtol=1e-4, atol=1e-5)


def test_the_rows_by_features_table_of_0_1_is_refused():
    grid = torch_grid("hash+dense")
    old = {"table": grid.table.detach().view(grid.n_table_rows, -1).clone()}  # sp-plugins 0.1's layout
    fresh = HashGrid(**CONFIGS["hash+dense"], backend="torch")
    with pytest.raises(RuntimeError, match="size mismatch for table"):
        fresh.load_state_dict(old)


def test_tcnn_is_built_and_called_under_its_own_device(fake_tcnn, monkeypatch):
    """tcnn builds and launches on the current CUDA device: a grid on another rank's GPU must make
    that device current, or its module lands on cuda:0."""
    import contextlib

    current = []

    @contextlib.contextmanager
    def recording(device):
        current.append(torch.device(device))
        yield
        current.pop()

    seen = []

    class Recorder(TcnnLayoutEncoding):
        def __init__(self, *args, **kwargs):
            seen.append(("built", list(current)))
            super().__init__(*args, **kwargs)

        def forward(self, x):
            seen.append(("called", list(current)))
            return super().forward(x)

    real = hashgrid_module.on_device
    fake_tcnn.Encoding = Recorder
    monkeypatch.setattr(hashgrid_module, "on_device", recording)
    grid = HashGrid(**CONFIGS["hash+dense"], backend="auto")
    grid(torch.rand(8, 3))
    assert seen == [("built", [torch.device("cpu")]), ("called", [torch.device("cpu")])]
    on_gpu1 = real(torch.device("cuda", 1))  # not entered: no GPU here
    assert isinstance(on_gpu1, torch.cuda.device) and on_gpu1.idx == 1
