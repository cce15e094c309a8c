"""Multi-process training: nerfstudio's own ``train_loop`` in two CPU processes over gloo.

``ns-train --machine.num-devices 2`` cannot run on a machine without CUDA (nerfstudio's launcher
asserts CUDA, and its pipeline asks DDP for ``device_ids=[local_rank]``, which a CPU module refuses).
``tests/helpers/ddp.py`` starts the two processes itself, initialises the process group as nerfstudio's
worker does and adapts only that ``device_ids`` argument, inside the test processes. One pair of
processes trains every family below for two steps on the tiny scene; then, per family:

- it trains (the pipeline's model is DDP's wrapper) or is refused in one line;
- the ranks drew different SP noise (the first values of the first draw, captured where every
  perturbation draws, and the generators' seeds), and SP reached a field through the wrapper;
- the ranks trained on different rays (different losses), and yet after each step every parameter
  and buffer (the alpha grid, the SP step and the ReLU grid included) is identical on both ranks;
- rank 0's checkpoint (written once, with DDP's ``module.`` prefix) holds those parameters, and
  loads in the real ``ns-eval`` (one family: the SDF one with a learnable alpha grid).
"""

from __future__ import annotations

import shutil

import pytest
import torch
from tests.helpers.ddp import run_ddp, step_state
from tests.helpers.ns_commands import ns_eval
from tests.helpers.ns_configs import tiny_sdf_config
from tests.helpers.ns_configs import tiny_radiance_config

pytest.importorskip("nerfstudio")

STEPS = 3

# family -> (build(scene, out), expected outcome); SP on in every step but the last (end=1.0)
FAMILIES = {
    # a learnable alpha grid: DDP must all-reduce its gradients too (coarse lr so it visibly moves)
    "sp-neus-hashgrid": (lambda scene, out: tiny_sdf_config(
        "sp-neus-hashgrid", scene, out, steps=STEPS, end=1.0, alpha_grid=True, alpha_grid_resolution=8,
        alpha_grid_lr=1e-2), "trained"),
    # coarse-to-fine levels and finite-difference step set by callbacks on the unwrapped model
    "sp-neuralangelo-lite": (lambda scene, out: tiny_sdf_config(
        "sp-neuralangelo-lite", scene, out, steps=STEPS, end=1.0), "trained"),
    # the generic route (with_sp on nerfacto: frustum offsets, proposal networks stay plain)
    "sp-nerfacto": (lambda scene, out: tiny_radiance_config("sp-nerfacto", scene, out, steps=STEPS), "trained"),
    # a fixed SP seed: each rank draws from seed + rank
    "sp-mipnerf": (lambda scene, out: tiny_radiance_config("sp-mipnerf", scene, out, steps=STEPS, seed=7), "trained"),
    "sp-relu-field": (lambda scene, out: tiny_radiance_config("sp-relu-field", scene, out, steps=STEPS), "trained"),
    # the coarse-to-fine hierarchy replaces its grid parameter per stage: refused on more than one device
    "relu-field": (lambda scene, out: tiny_radiance_config("relu-field", scene, out, steps=STEPS), "refused"),
}
EVAL_FAMILY = "sp-neus-hashgrid"
RESUMED = "sp-mipnerf-resumed"  # sp-mipnerf's two-process run resumed by two processes (--load-dir)
SCHEDULE_METRICS = ("sp_alpha", "active_levels", "fd_step", "grid_resolution")


@pytest.fixture(scope="module")
def ddp_runs(tiny_scene, tmp_path_factory):
    """Every family trained by one pair of processes: (results, workdir, configs)."""
    root = tmp_path_factory.mktemp("ddp")
    configs = {name: build(tiny_scene, root / "runs" / name) for name, (build, _) in FAMILIES.items()}
    # trained after sp-mipnerf by the same processes: steps 3..5, three more iterations; a constant alpha
    # keeps SP on there (a schedule of that length would have ended before the resumed steps)
    resumed = tiny_radiance_config("sp-mipnerf", tiny_scene, root / "runs" / RESUMED, steps=STEPS, seed=7, schedule="constant")
    resumed.load_dir = configs["sp-mipnerf"].get_checkpoint_dir()
    configs[RESUMED] = resumed
    results = run_ddp(configs, root / "record", world_size=2)
    yield results, root / "record", configs
    shutil.rmtree(root, ignore_errors=True)  # ~50 MB of per-step states and checkpoints per test session


@pytest.mark.parametrize("family", list(FAMILIES))
def test_each_family_trains_in_two_processes_or_is_refused_in_one_line(family, ddp_runs):
    results, _, _ = ddp_runs
    ranks = results[family]
    expected = FAMILIES[family][1]
    for rank, r in enumerate(ranks):
        assert r["status"] == expected, (rank, r.get("error") and r["error"]["traceback"])
    if expected == "refused":
        for r in ranks:
            assert r["error"]["type"] == "sp_plugins.adapter.errors.InputError", r["error"]["traceback"]
            message = r["error"]["message"]
            assert "\n" not in message and "cannot train on 2 devices" in message and "--machine.num-devices 1" in message, message
            assert r["steps"] == []  # refused at setup, before a step
        return
    for r in ranks:
        assert r["ddp"] is True and r["ddp_device_ids"] is None  # DDP's wrapper, the CPU form
        assert [s["step"] for s in r["steps"]] == list(range(STEPS))
        assert [s["alpha"] > 0 for s in r["steps"]] == [True] * (STEPS - 1) + [False]  # end 1.0: the last step is plain
        assert r["draws"] > 0 and r["perturbed_calls"] > 0  # SP reached a field through the wrapper


@pytest.mark.parametrize("family", [f for f, (_, outcome) in FAMILIES.items() if outcome == "trained"])
def test_ranks_draw_different_noise_and_keep_identical_parameters(family, ddp_runs):
    results, workdir, _ = ddp_runs
    r0, r1 = results[family]
    # the noise each rank drew (captured at the draw), not the seed it is meant to have
    n = min(len(r0["noise"]), len(r1["noise"]))
    assert n >= 16
    first0, first1 = torch.tensor(r0["noise"][:n]), torch.tensor(r1["noise"][:n])
    assert first0.abs().sum() > 0 and first1.abs().sum() > 0
    assert not torch.allclose(first0, first1), "both ranks drew the same SP noise"
    assert r0["seeds"] and r1["seeds"] and r0["seeds"] != r1["seeds"]
    if family == "sp-mipnerf":  # SPConfig.seed 7: seed + rank
        assert (r0["seeds"], r1["seeds"]) == ([7], [8])
    # each rank trained on its own rays ...
    assert [s["loss"] for s in r0["steps"]] != [s["loss"] for s in r1["steps"]]
    # ... and after every step both hold the same parameters and buffers, to the bit
    for step in range(STEPS):
        s0, s1 = step_state(workdir, family, 0, step), step_state(workdir, family, 1, step)
        for kind in ("params", "buffers"):
            assert s0[kind].keys() == s1[kind].keys()
            differ = [k for k in s0[kind] if not torch.equal(s0[kind][k], s1[kind][k])]
            assert not differ, f"step {step}: {kind} differ across ranks: {differ}"
        assert int(s0["buffers"]["sp.step"]) == step
        for key in SCHEDULE_METRICS:  # schedules driven by callbacks on the unwrapped model
            assert r0["steps"][step]["metrics"].get(key) == r1["steps"][step]["metrics"].get(key), (step, key)
    # the parameters moved (the equality above is not that of an untrained model)
    start = step_state(workdir, family, 0, 0)["params"]
    end = step_state(workdir, family, 0, STEPS - 1)["params"]
    assert any(not torch.equal(start[k], end[k]) for k in start)
    if family == "sp-neus-hashgrid":
        grid = [k for k in end if k.startswith("sp.alpha_grid.")]
        assert grid, sorted(end)
        assert any(not torch.equal(start[k], end[k]) for k in grid), "the alpha grid did not train"


def test_rank0_checkpoint_holds_the_synchronised_parameters_and_loads_in_ns_eval(ddp_runs, ns_server, tmp_path):
    results, workdir, configs = ddp_runs
    config = configs[EVAL_FAMILY]
    (ckpt,) = config.get_checkpoint_dir().glob("*.ckpt")  # written once, by rank 0
    assert ckpt.name == f"step-{STEPS - 1:09d}.ckpt"
    state = torch.load(ckpt, map_location="cpu", weights_only=False)
    model = {k[len("_model.module."):]: v for k, v in state["pipeline"].items() if k.startswith("_model.module.")}
    assert model, "not a DDP checkpoint (no _model.module. prefix)"
    assert model["sp._extra_state"]["rank"] == 0
    final = step_state(workdir, EVAL_FAMILY, 1, STEPS - 1)["params"]  # rank 1's, equal to rank 0's
    for k, v in final.items():
        assert torch.equal(model[k], v), k
    results = ns_eval(config.get_base_dir() / "config.yml", tmp_path, server=ns_server)
    assert results["psnr"] > 0


def test_a_resumed_two_process_run_continues_rank0s_noise_and_gives_rank1_its_own(ddp_runs):
    """nerfstudio saves rank 0's checkpoint only; every rank loads it. Rank 0 continues the noise
    stream saved there; rank 1 must not take rank 0's stream (both ranks would then draw the same
    noise from the resume on), and the ranks stay in step."""
    results, workdir, configs = ddp_runs
    r0, r1 = results[RESUMED]
    assert r0["status"] == r1["status"] == "trained", r0["error"] or r1["error"]
    assert [s["step"] for s in r0["steps"]] == [STEPS, STEPS + 1, STEPS + 2]  # nerfstudio: checkpoint step + 1 on
    assert r0["steps"][0]["alpha"] > 0 and r0["draws"] > 0
    (ckpt,) = configs["sp-mipnerf"].get_checkpoint_dir().glob("*.ckpt")
    saved = torch.load(ckpt, map_location="cpu", weights_only=False)["pipeline"]["_model.module.sp._extra_state"]
    assert saved["rank"] == 0 and saved["seed"] == 7
    generator = torch.Generator().manual_seed(0)
    generator.set_state(saved["generators"]["cpu"])
    continued = torch.randn(r0["noise_shape"], generator=generator).flatten()[: len(r0["noise"])]
    assert torch.equal(torch.tensor(r0["noise"]), continued), "rank 0 did not continue its saved noise stream"
    n = min(len(r0["noise"]), len(r1["noise"]))
    assert not torch.allclose(torch.tensor(r0["noise"][:n]), torch.tensor(r1["noise"][:n])), "rank 1 took rank 0's noise"
    assert r1["seeds"] != r0["seeds"]
    for step in range(STEPS, STEPS + 3):
        s0, s1 = step_state(workdir, RESUMED, 0, step), step_state(workdir, RESUMED, 1, step)
        for kind in ("params", "buffers"):
            differ = [k for k in s0[kind] if not torch.equal(s0[kind][k], s1[kind][k])]
            assert not differ, f"step {step}: {kind} differ across ranks: {differ}"
