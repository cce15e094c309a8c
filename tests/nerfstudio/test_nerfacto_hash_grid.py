"""sp-nerfacto (and its baseline) run our HashGrid where tiny-cuda-nn cannot: the field and both
proposal networks, with the host's hyperparameters, said once; GPU-layout grid weights load."""

from __future__ import annotations

import pytest
import torch
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.field_components.encodings import HashEncoding
from tests.helpers.ns_configs import tiny_radiance_config

from sp_plugins.encodings import HashGrid, tcnn_usable
from sp_plugins.nerfstudio.components import hash_encoding
from sp_plugins.adapter.errors import InputError

BOX = SceneBox(aabb=torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))


def build(tiny_scene, tmp_path, **sp):
    config = tiny_radiance_config("sp-nerfacto", tiny_scene, tmp_path, **sp).pipeline.model
    torch.manual_seed(0)
    return config, config.setup(scene_box=BOX, num_train_data=8, metadata={}, device="cpu", grad_scaler=None)


def grids(model):
    return {name: m for name, m in model.named_modules(remove_duplicate=False) if isinstance(m, HashGrid)}


@pytest.mark.parametrize("enabled", [True, False], ids=["sp", "baseline"])
def test_every_hash_encoding_is_our_grid_with_the_hosts_settings(enabled, tiny_scene, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(hash_encoding, "_announced", set())
    config, model = build(tiny_scene, tmp_path, enabled=enabled)
    printed = capsys.readouterr().out
    assert not [m for m in model.modules() if isinstance(m, HashEncoding)]
    found = grids(model)
    assert set(found) == {"field.mlp_base.model.0", "proposal_networks.0.encoding", "proposal_networks.0.mlp_base.0",
                          "proposal_networks.1.encoding", "proposal_networks.1.mlp_base.0"}
    for i in range(2):  # one grid per proposal network, registered twice as in nerfstudio
        assert model.proposal_networks[i].encoding is model.proposal_networks[i].mlp_base[0]
    field_grid = model.field.mlp_base.model[0]
    host = HashEncoding.get_tcnn_encoding_config(  # what nerfstudio hands tcnn on a GPU
        num_levels=config.num_levels, features_per_level=config.features_per_level, log2_hashmap_size=config.log2_hashmap_size,
        min_res=config.base_res, growth_factor=(config.max_res / config.base_res) ** (1 / (config.num_levels - 1)))
    assert field_grid.levels == HashGrid.from_tcnn_config(3, host, backend="torch").levels
    # base_res * growth**(L-1) = max_res vertices (tcnn's float32 arithmetic may round the scale up a hair)
    assert field_grid.levels[-1].scale + 1 == pytest.approx(config.max_res, abs=1e-3) and field_grid.backend == "torch"
    assert field_grid.levels[0].scale + 1 == config.base_res
    prop = config.proposal_net_args_list[0]
    assert model.proposal_networks[0].encoding.levels[-1].scale + 1 == pytest.approx(prop["max_res"], abs=1e-3)
    assert model.proposal_networks[0].encoding.log2_hashmap_size == prop["log2_hashmap_size"]
    assert "slow implementation" not in printed.lower()
    assert printed.count("sp_plugins' HashGrid") == 1  # said once
    build(tiny_scene, tmp_path, enabled=enabled)
    assert "sp_plugins' HashGrid" not in capsys.readouterr().out


def test_gpu_layout_grid_weights_load_and_fused_tcnn_is_refused(tiny_scene, tmp_path):
    """A GPU run's state dict (tcnn's flat ``params`` per encoding, as our reading of tcnn's layout
    makes them: tests/encodings/test_hashgrid_backends.py, checked against our own stand-in, not
    tiny-cuda-nn) loads into the CPU model; a fused tcnn MLP is refused."""
    _, model = build(tiny_scene, tmp_path)
    state = model.state_dict()
    gpu_state = {}
    for key, value in state.items():  # a GPU run's keys: tcnn's flat params for every HashEncoding
        if key.endswith(".table") and key.startswith("proposal_networks"):
            key, value = key[: -len("table")] + "tcnn_encoding.params", value.reshape(-1)
        gpu_state[key] = value
    assert "proposal_networks.0.encoding.tcnn_encoding.params" in gpu_state
    _, fresh = build(tiny_scene, tmp_path)
    torch.manual_seed(5)
    with torch.no_grad():
        for grid in grids(model).values():
            grid.table.uniform_(-1, 1)
    gpu_state = {k: (model.state_dict()[k.replace("tcnn_encoding.params", "table")].reshape(-1) if "tcnn_encoding" in k else v)
                 for k, v in gpu_state.items()}
    fresh.load_state_dict(gpu_state)  # strict
    for i in range(2):
        assert torch.equal(fresh.proposal_networks[i].encoding.table, model.proposal_networks[i].encoding.table)
    fused = dict(gpu_state)
    fused["field.mlp_base.model.params"] = torch.zeros(10)
    with pytest.raises(InputError, match="fused MLP .*field.mlp_base.model.params.*CUDA machine with tinycudann"):
        fresh.load_state_dict(fused)


def test_the_decision_follows_device_and_tinycudann(monkeypatch):
    """Our grids exactly where tiny-cuda-nn cannot run: never on a CPU; on a CUDA device only when
    tinycudann does not import. Both sides of the real decision, on any machine: tinycudann's
    presence is the environment fact set here (an importable module), the decision is not touched."""
    import sys
    import types

    from sp_plugins.encodings.hashgrid import _import_tcnn

    real = _import_tcnn() is not None
    for present in (False, True):
        if present:
            monkeypatch.setitem(sys.modules, "tinycudann", types.ModuleType("tinycudann"))
        elif real:  # a machine with tinycudann: hide it (a None entry makes the import fail)
            monkeypatch.setitem(sys.modules, "tinycudann", None)
        assert hash_encoding.use_sp_hash_grids("cpu") is True
        assert hash_encoding.use_sp_hash_grids(torch.device("cpu")) is True
        for cuda in ("cuda", "cuda:0", "cuda:1", torch.device("cuda", 0)):
            assert hash_encoding.use_sp_hash_grids(cuda) is (not present), (cuda, present)
        assert hash_encoding.use_sp_hash_grids(None) is (not (present and torch.cuda.is_available()))
        monkeypatch.undo()


def test_where_the_decision_says_tcnn_runs_the_host_modules_stay(tiny_scene, tmp_path, monkeypatch):
    """A model for a CUDA device with tinycudann importable keeps nerfstudio's tcnn setting and its own
    encodings: populate_modules asks the real decision and swaps nothing. (Built on this machine's CPU:
    nerfstudio, which found no tinycudann when it was imported, builds its torch fallbacks, so the
    modules are nerfstudio's HashEncoding, not ours.)"""
    import sys
    import types

    if not tcnn_usable("cuda"):
        monkeypatch.setitem(sys.modules, "tinycudann", types.ModuleType("tinycudann"))
    assert hash_encoding.use_sp_hash_grids("cuda") is False
    config = tiny_radiance_config("sp-nerfacto", tiny_scene, tmp_path).pipeline.model
    model = config.setup(scene_box=BOX, num_train_data=8, metadata={}, device="cuda", grad_scaler=None)
    assert config.implementation == "tcnn"  # not switched to torch
    assert not grids(model)  # nothing swapped: nerfstudio's own modules
    encodings = {n for n, m in model.named_modules(remove_duplicate=False) if isinstance(m, HashEncoding)}
    assert {"proposal_networks.0.encoding", "proposal_networks.1.encoding"} <= encodings
    # and the same model for the CPU: our grids (the decision's other side, same config)
    config = tiny_radiance_config("sp-nerfacto", tiny_scene, tmp_path).pipeline.model
    model = config.setup(scene_box=BOX, num_train_data=8, metadata={}, device="cpu", grad_scaler=None)
    assert config.implementation == "torch" and "field.mlp_base.model.0" in grids(model)


@pytest.mark.skipif(not tcnn_usable("cuda"), reason="needs a CUDA device and tinycudann (tiny-cuda-nn's own modules)")
def test_on_a_cuda_machine_with_tinycudann_the_modules_are_tcnns(tiny_scene, tmp_path):
    config = tiny_radiance_config("sp-nerfacto", tiny_scene, tmp_path).pipeline.model
    model = config.setup(scene_box=BOX, num_train_data=8, metadata={}, device="cuda", grad_scaler=None)
    encodings = [m for m in model.modules() if isinstance(m, HashEncoding)]
    assert encodings and all(m.tcnn_encoding is not None for m in encodings) and not grids(model)
