import pytest
import torch

from sp_plugins import AlphaSchedule, SPConfig, StochasticPreconditioner


def make(**kw):
    total = kw.pop("total_steps", 1000)
    return SPConfig(**kw).setup(total_steps=total, bounds=(-1.0, 1.0))


def test_eval_mode_returns_the_input_tensor_itself():
    sp = make(alpha0=0.1)
    x = torch.rand(100, 3)
    sp.train()
    assert not torch.equal(sp(x), x)
    sp.eval()
    assert sp(x) is x


def test_no_perturbation_once_alpha_reaches_zero_or_when_disabled():
    sp = make(alpha0=0.1, schedule="step", end=0.5)
    x = torch.rand(10, 3)
    sp.set_step(499)
    assert sp.active and not torch.equal(sp(x), x)
    sp.set_step(500)
    assert sp.alpha == 0.0 and sp(x) is x
    off = make(alpha0=0.1, enabled=False)
    assert off.alpha == 0.0 and off(x) is x


def test_callback_alpha_follows_the_schedule():
    sp = make(alpha0=0.02, schedule="linear", end=0.5, total_steps=200)
    assert sp.set_step(0) == pytest.approx(0.02)
    assert sp.set_step(50) == pytest.approx(0.01)
    assert sp.set_step(100) == 0.0
    # a new total (resumed with a longer run) re-resolves the fractional end
    assert sp.set_step(100, total_steps=400) == pytest.approx(0.01)


def test_perturbation_scale_matches_alpha_and_stays_in_bounds():
    sp = make(alpha0=0.05, schedule="constant", seed=0)
    x = torch.zeros(200_000, 3)
    d = sp(x) - x
    assert float(d.std()) == pytest.approx(0.05, rel=0.01)
    big = make(alpha0=3.0, schedule="constant")
    y = big(torch.rand(1000, 3) * 2 - 1)
    assert float(y.abs().max()) <= 1.0


def test_state_dict_round_trip_resumes_at_the_same_alpha():
    sp = make(alpha0=0.013, schedule="exponential", end=0.2, total_steps=5000)
    sp.set_step(321)
    state = sp.state_dict()
    fresh = SPConfig(alpha0=0.013, schedule="exponential", end=0.2).setup(bounds=(-1.0, 1.0))
    assert fresh.alpha == 0.0
    fresh.load_state_dict(state)
    assert int(fresh.step) == 321 and int(fresh.total_steps) == 5000
    assert fresh.alpha == pytest.approx(sp.alpha) and fresh.alpha > 0


def test_state_dict_restores_the_alpha_grid():
    cfg = dict(alpha0=0.03, alpha_grid=True, alpha_grid_resolution=4, schedule="constant")
    sp = make(**cfg)
    with torch.no_grad():
        sp.alpha_grid.param.add_(torch.randn_like(sp.alpha_grid.param))
    other = make(**cfg)
    other.load_state_dict(sp.state_dict())
    x = torch.rand(20, 3) * 2 - 1
    assert torch.allclose(other.alpha_at(x), sp.alpha_at(x))


def test_seeded_preconditioner_is_reproducible():
    a, b = make(alpha0=0.1, seed=3), make(alpha0=0.1, seed=3)
    x = torch.rand(50, 3)
    assert torch.equal(a(x), b(x))


def test_multi_sample_blur_averages_draws():
    sp = make(alpha0=0.3, schedule="constant", num_samples=32, boundary="none")
    x = torch.zeros(1000, 1)
    sp1 = make(alpha0=0.3, schedule="constant", num_samples=1, boundary="none")
    fn = lambda p: torch.sin(5 * p)  # noqa: E731
    assert sp.blurred(fn, x).shape == x.shape
    assert float(sp.blurred(fn, x).var()) < float(sp1.blurred(fn, x).var()) / 10
    sp.eval()
    assert torch.equal(sp.blurred(fn, x), fn(x))


@pytest.mark.parametrize(
    "kwargs, word",
    [
        (dict(alpha0=-1.0), "alpha0"),
        (dict(noise="laplace"), "noise"),
        (dict(boundary="periodic"), "boundary"),
        (dict(schedule="cosine"), "schedule"),
        (dict(num_samples=0), "num_samples"),
        (dict(end=0.0), "end"),
        (dict(alpha_grid_mode="product"), "alpha_grid_mode"),
        (dict(alpha_grid_parameterization="sigmoid"), "alpha_grid_parameterization"),
        (dict(alpha_grid_lr=-1e-3), "alpha_grid_lr"),
    ],
)
def test_bad_config_raises(kwargs, word):
    with pytest.raises(ValueError, match=word):
        SPConfig(**kwargs)


def test_setup_errors_are_explicit():
    with pytest.raises(ValueError, match="after the end of training"):
        SPConfig(end=5000).setup(total_steps=1000, bounds=(-1, 1))
    with pytest.raises(ValueError, match="bounds"):
        SPConfig(boundary="reflect").setup(total_steps=10)
    with pytest.raises(ValueError, match="scene_diagonal"):
        SPConfig(relative_to_diagonal=True).setup(total_steps=10, bounds=(-1, 1))
    with pytest.raises(ValueError, match="empty"):
        SPConfig().setup(total_steps=10, bounds=(1.0, -1.0))
    assert isinstance(SPConfig(boundary="none").setup(total_steps=10), StochasticPreconditioner)


def test_alpha_grid_builds_before_the_total_is_known():
    # a fractional end cannot resolve without the total; the grid's initial alpha must not need it
    sp = SPConfig(alpha0=0.02, end=0.2, alpha_grid=True, alpha_grid_resolution=4).setup(bounds=(-1.0, 1.0))
    assert torch.allclose(sp.alpha_grid.values(), torch.tensor(0.02), atol=1e-6)
    rel = SPConfig(alpha0=0.01, end=0.2, alpha_grid=True, alpha_grid_resolution=4, relative_to_diagonal=True)
    assert torch.allclose(rel.setup(bounds=(-1.0, 1.0), scene_diagonal=3.0).alpha_grid.values(), torch.tensor(0.03), atol=1e-6)
    with pytest.raises(ValueError, match="alpha_grid_init"):
        SPConfig(alpha0=0.0, end=0.2, alpha_grid=True).setup(bounds=(-1.0, 1.0))


def test_every_attribute_reads_before_the_total_is_known():
    """nerfstudio's viewer getattr's every attribute of the pipeline before the trainer sets the step
    count (``schedule`` raised "end=0.2 is a fraction of training" and stopped ns-train).
    What is not known yet reads as unknown; once the total is set it resolves."""
    sp = SPConfig(alpha0=0.02, end=0.2).setup(bounds=(-1.0, 1.0))
    values = {name: getattr(sp, name) for name in dir(sp) if not name.startswith("__")}
    assert values["schedule"] is None and values["alpha"] == 0.0 and not values["active"]
    repr(sp)
    sp.set_step(0, 100)
    assert sp.schedule is not None and sp.schedule.end_step == 20 and sp.alpha == pytest.approx(0.02)
    with pytest.raises(ValueError, match="fraction of training"):  # stepping without a total still says why
        SPConfig(alpha0=0.02, end=0.2).setup(bounds=(-1.0, 1.0)).set_step(3)


def test_training_step_never_reads_a_buffer(monkeypatch):
    """Reading a buffer's value (int(), float(), .item()) syncs a GPU: a step must use Python mirrors."""
    from sp_plugins.core.boundary import reflect

    # boundary "clamp": the CPU's sparse reflect reads back on purpose (cheap there); accelerators
    # use the dense fold, checked on its own below
    sp = make(alpha0=0.05, alpha_grid=True, alpha_grid_resolution=4, seed=3, boundary="clamp")
    sp.train()
    sp.set_step(10)
    x = torch.rand(64, 3)
    lo, hi = torch.full((3,), -1.0), torch.ones(3)

    def forbidden(self, *args, **kwargs):
        raise AssertionError("a tensor was read back to the host during a training step")

    for name in ("__int__", "__float__", "item", "__bool__", "tolist"):
        monkeypatch.setattr(torch.Tensor, name, forbidden)
    sp.set_step(11)
    y = sp(x)
    z = sp.mean_over_draws(lambda: sp(x))
    folded = reflect(x * 3.0, lo, hi, origin=x, sparse=False)
    monkeypatch.undo()
    assert folded.abs().max() <= 1.0
    assert y.shape == x.shape and z.shape == x.shape and int(sp.step) == 11


def test_mean_over_draws_averages_num_samples_draws_of_dicts_and_tuples():
    sp = make(alpha0=0.5, boundary="none", num_samples=4, seed=0)
    sp.train()
    calls = []

    def once():
        calls.append(1)
        q = sp(torch.zeros(2000, 3))
        return {"q": q, "index": torch.arange(3)}, (q.square(),)

    (out, (sq,)) = sp.mean_over_draws(once)
    assert len(calls) == 4
    assert torch.equal(out["index"], torch.arange(3))  # integer entries pass through
    # each entry is a mean of 4 draws of N(0, 0.5^2): variance 0.25 / 4
    assert out["q"].var().item() == pytest.approx(0.25 / 4, rel=0.1)
    assert sq.mean().item() == pytest.approx(0.25, rel=0.1)
    sp.eval()
    calls.clear()
    sp.mean_over_draws(once)
    assert len(calls) == 1  # evaluation: one plain call


def test_seeded_noise_differs_per_distributed_rank(monkeypatch):
    import sp_plugins.core.preconditioner as pre

    x = torch.zeros(16, 3)
    draws = []
    for rank in (0, 0, 1):
        monkeypatch.setattr(pre, "distributed_rank", lambda rank=rank: rank)
        sp = make(alpha0=0.1, boundary="none", seed=7)
        sp.train()
        draws.append(sp(x))
    assert torch.equal(draws[0], draws[1]) and not torch.equal(draws[0], draws[2])


def _draws(sp, n=3, shape=(64, 3)):
    return [sp(torch.zeros(*shape)) for _ in range(n)]


@pytest.mark.parametrize("seed", [5, None])
def test_resumed_preconditioner_draws_the_noise_of_an_uninterrupted_one(seed):
    """The generator state is in the state dict: a run that saves after k draws and resumes in a fresh
    module (after unrelated use of the global generator) continues the same noise stream."""
    cfg = dict(alpha0=0.1, schedule="constant", boundary="none", seed=seed)
    torch.manual_seed(0)
    whole = make(**cfg).train()
    expected = _draws(whole, 5)
    torch.manual_seed(0)
    first = make(**cfg).train()
    assert all(torch.equal(a, b) for a, b in zip(_draws(first, 2), expected[:2]))
    state = first.state_dict()
    assert set(state["_extra_state"]["generators"]) == {"cpu"}
    torch.manual_seed(123)  # a resumed process: its global generator is somewhere else
    resumed = make(**cfg).train()
    resumed.load_state_dict(state)  # strict
    assert all(torch.equal(a, b) for a, b in zip(_draws(resumed, 3), expected[2:]))
    # the state survives torch.save / the weights-only torch.load that nerfstudio and ns-eval use
    import io

    buf = io.BytesIO()
    torch.save(state, buf)
    buf.seek(0)
    again = make(**cfg).train()
    again.load_state_dict(torch.load(buf, weights_only=True))
    assert torch.equal(again(torch.zeros(64, 3)), expected[2])
    # and without the restore the stream would differ (the check above is not vacuous)
    fresh = make(**cfg).train()
    fresh._generators.clear()
    assert not torch.equal(fresh(torch.zeros(64, 3)), expected[2])


def test_a_checkpoint_without_generator_state_is_refused_by_a_strict_load():
    """sp-plugins 0.1 saved no generator state (no ``_extra_state``): such a checkpoint is refused
    by a strict load (nerfstudio loads pipelines strictly) rather than resumed on a new noise stream."""
    sp = make(alpha0=0.1, schedule="exponential", end=0.5, total_steps=100, seed=2)
    sp.set_step(17)
    old = {k: v for k, v in sp.state_dict().items() if not k.endswith("_extra_state")}
    assert set(old) == {"step", "total_steps"}
    parent = torch.nn.Module()
    parent.sp = make(alpha0=0.1, schedule="exponential", end=0.5, total_steps=100, seed=2)
    with pytest.raises(RuntimeError, match="sp._extra_state"):
        parent.load_state_dict({f"sp.{k}": v for k, v in old.items()}, strict=True)
    # a genuinely missing buffer is reported too
    with pytest.raises(RuntimeError, match="total_steps"):
        make(alpha0=0.1, seed=2).load_state_dict({"step": old["step"], "_extra_state": sp.get_extra_state()}, strict=True)


def test_generator_state_is_keyed_by_device_type_and_applied_at_the_first_draw_there():
    sp = make(alpha0=0.1, schedule="constant", boundary="none", seed=9).train()
    sp(torch.zeros(4, 3))
    state = sp.state_dict()
    fake = {"cuda": torch.zeros(16, dtype=torch.uint8)}
    state["_extra_state"] = dict(state["_extra_state"], generators={**state["_extra_state"]["generators"], **fake})
    other = make(alpha0=0.1, schedule="constant", boundary="none", seed=9).train()
    other.load_state_dict(state)
    assert set(other._saved_generator_states) == {"cpu", "cuda"}  # nothing built yet: kept until used
    assert set(other.state_dict()["_extra_state"]["generators"]) == {"cpu", "cuda"}  # and saved again
    assert torch.equal(other(torch.zeros(4, 3)), sp(torch.zeros(4, 3)))
    assert set(other._saved_generator_states) == {"cuda"}  # the CPU's went to the CPU generator
    # a module that already drew takes the loaded state at once
    third = make(alpha0=0.1, schedule="constant", boundary="none", seed=9).train()
    third(torch.zeros(50, 3))
    third.load_state_dict(sp.state_dict())
    assert torch.equal(third(torch.zeros(4, 3)), sp(torch.zeros(4, 3)))


def test_another_ranks_or_seeds_state_starts_a_new_stream(monkeypatch):
    """A multi-process run saves rank 0's state: rank 1 must not take it (the ranks would then draw the
    same noise); nor does a resume with another seed keep the old seed's stream."""
    import sp_plugins.core.preconditioner as pre

    cfg = dict(alpha0=0.1, schedule="constant", boundary="none", seed=4)
    saved = make(**cfg).train()
    saved(torch.zeros(4, 3))
    state = saved.state_dict()
    expected = saved(torch.zeros(32, 3))
    monkeypatch.setattr(pre, "distributed_rank", lambda: 1)
    rank1 = make(**cfg).train()
    rank1.load_state_dict(state)
    draw1 = rank1(torch.zeros(32, 3))
    assert not torch.equal(draw1, expected)
    plain1 = make(**cfg).train()
    assert not torch.equal(draw1, plain1(torch.zeros(32, 3)))  # nor a replay of rank 1's first draws
    monkeypatch.setattr(pre, "distributed_rank", lambda: 0)
    other_seed = make(**dict(cfg, seed=5)).train()
    other_seed.load_state_dict(state)
    assert not torch.equal(other_seed(torch.zeros(32, 3)), expected)


def test_unseeded_noise_is_seeded_from_the_global_generator():
    cfg = dict(alpha0=0.1, schedule="constant", boundary="none")
    torch.manual_seed(11)
    a = make(**cfg).train()(torch.zeros(16, 3))
    torch.manual_seed(11)
    b = make(**cfg).train()(torch.zeros(16, 3))
    torch.manual_seed(12)
    c = make(**cfg).train()(torch.zeros(16, 3))
    assert torch.equal(a, b) and not torch.equal(a, c)


def test_alpha_grid_with_alpha0_zero_is_active_at_its_own_init():
    """alpha0 = 0 with alpha_grid_init set: the grid alone gives alpha (the
    preconditioner was silently inactive)."""
    sp = make(alpha0=0.0, schedule="constant", alpha_grid=True, alpha_grid_init=0.03, alpha_grid_resolution=4, seed=0)
    sp.train()
    assert sp.active
    x = torch.rand(50_000, 3) * 0.5 - 0.25  # well away from the walls
    assert float((sp(x) - x).detach().std()) == pytest.approx(0.03, rel=0.03)
    timed = make(alpha0=0.0, schedule="exponential", end=0.5, alpha_grid=True, alpha_grid_init=0.03, alpha_grid_resolution=4)
    timed.train()
    assert timed.active and float((timed(x) - x).detach().std()) == pytest.approx(0.03, rel=0.03)
    timed.set_step(500)
    assert not timed.active and timed(x) is x


@pytest.mark.parametrize("schedule", ["exponential", "linear", "step"])
def test_alpha_grid_replaces_the_schedule_during_the_sp_phase_then_is_off(schedule):
    """The paper's variant: alpha(x) from the grid alone while the SP phase runs (not times the
    annealed scalar), exactly 0 from the end step on."""
    sp = make(alpha0=0.03, schedule=schedule, end=0.5, alpha_grid=True, alpha_grid_resolution=4, total_steps=1000, seed=1)
    sp.train()
    with torch.no_grad():
        sp.alpha_grid.set_values(torch.rand(4, 4, 4) * 0.05 + 0.01)
    x = torch.rand(64, 3) * 2 - 1
    for step in (0, 100, 250, 499):
        sp.set_step(step)
        assert sp.active and sp.grid_scale == 1.0
        assert torch.equal(sp.alpha_at(x), sp.alpha_grid(x))
    sp.set_step(500)
    assert not sp.active and sp.alpha == 0.0 and sp(x) is x
    scaled = make(alpha0=0.03, schedule=schedule, end=0.5, alpha_grid=True, alpha_grid_mode="scaled", alpha_grid_resolution=4,
                  total_steps=1000)
    scaled.set_step(250)
    decay = AlphaSchedule.resolve(schedule, 1.0, end=0.5, total_steps=1000)(250)
    assert scaled.grid_scale == pytest.approx(decay)
    assert torch.allclose(scaled.alpha_at(x), scaled.alpha_grid(x) * decay)


def test_scaled_grid_mode_works_with_alpha0_zero():
    sp = make(alpha0=0.0, schedule="linear", end=0.5, alpha_grid=True, alpha_grid_mode="scaled", alpha_grid_init=0.02,
              alpha_grid_resolution=4, total_steps=100)
    sp.train()
    assert sp.active and sp.grid_scale == 1.0
    sp.set_step(25)
    assert sp.grid_scale == pytest.approx(0.5) and sp.alpha == pytest.approx(0.01)
    with pytest.raises(ValueError, match="alpha_grid_mode"):
        SPConfig(alpha_grid_mode="product")


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
@pytest.mark.parametrize("grid", [False, True])
def test_preconditioner_returns_float32_for_half_positions(dtype, grid):
    """half-precision positions come back in float32, moved by a tiny alpha."""
    kw = dict(alpha_grid=True, alpha_grid_resolution=4) if grid else {}
    sp = SPConfig(alpha0=1e-4, schedule="constant", boundary="reflect", seed=0, **kw).setup(total_steps=10, bounds=(0.0, 1.0))
    sp.train()
    x = (0.5 + 0.5 * torch.rand(20_000, 3)).to(dtype)
    y = sp(x)
    assert y.dtype == torch.float32
    assert float((y != x.float()).float().mean()) >= 0.999
    assert float((y - x.float()).detach().std()) == pytest.approx(1e-4, rel=0.05)
    sp.config.num_samples = 2
    z = sp.blurred(lambda p: p, x)
    assert z.dtype == torch.float32 and float((z != x.float()).float().mean()) >= 0.999


def test_a_softplus_grid_checkpoint_of_version_0_1_0_loads_into_the_log_grid():
    """sp-plugins 0.1.0 stored the grid as softplus logits (``alpha_grid.logits``): such a
    checkpoint loads strictly into today's log-alpha grid, to the same alpha."""
    import torch.nn.functional as F

    cfg = dict(alpha0=0.03, alpha_grid=True, alpha_grid_resolution=4, schedule="constant")
    sp = make(**cfg)
    assert sp.alpha_grid.parameterization == "log" and "alpha_grid.log_alpha" in sp.state_dict()
    old = {k: v for k, v in sp.state_dict().items() if not k.startswith("alpha_grid.")}
    logits = torch.randn(1, 1, 4, 4, 4) - 3.0
    old["alpha_grid.logits"] = logits
    sp.load_state_dict(old, strict=True)
    assert torch.allclose(sp.alpha_grid.values(), F.softplus(logits)[0, 0], rtol=1e-5)
    assert set(sp.state_dict()) >= {"alpha_grid.log_alpha"} and "alpha_grid.logits" not in sp.state_dict()
