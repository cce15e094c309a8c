"""The stochastic preconditioner (sp_plugins.core.preconditioner), exactly: the seed of each noise generator
(``seed + rank``; a global draw plus the rank modulo 2**63 with ``seed=None``; ``(seed, rank, step)`` mixed by
SHA-256 after another process's checkpoint), compared through the generator's saved state (a CPU generator's noise
reads only the low 32 bits of its seed; its state holds all 64); the state dict's step, total and extra state,
and what a load does with each; the schedule's cache per total; the alpha grid's modes, default box and refusals;
``blurred`` / ``mean_over_draws`` with one and two samples; ``extra_repr``. Flag values come as parsed strings
(tyro hands over equal strings that are not the literals). The mutants each test kills are listed in
``bench/results/mutation_study/kills.json``."""

import hashlib

import pytest
import torch

import sp_plugins.core.preconditioner as pre
from sp_plugins import SPConfig, StochasticPreconditioner


def parsed(word: str) -> str:
    """An equal string that is not the literal (as tyro hands over a flag's value)."""
    return "".join(list(word))


def parsed_int(number: int) -> int:
    """An equal int that is not the same object (as a checkpoint or a flag hands one over)."""
    return int(str(number))


def build(total_steps=100, bounds=(-1.0, 1.0), **config):
    return SPConfig(**config).setup(total_steps=total_steps, bounds=bounds)


def noise_only(seed=None, **config):
    """A preconditioner whose output at zeros is ``alpha * eps`` itself (constant alpha, no box)."""
    return build(alpha0=0.1, schedule="constant", boundary="none", seed=seed, **config).train()


def assert_first_draw_seeded_with(sp, expected_seed: int, n: int = 8):
    """The first perturbation of ``n`` zeros is ``alpha * eps`` with ``eps`` the first draws of a CPU generator
    seeded with ``expected_seed``, and the generator's state after it (in the state dict) is that generator's."""
    y = sp(torch.zeros(n, 3))
    reference = torch.Generator().manual_seed(expected_seed)
    eps = torch.randn(n, 3, generator=reference)
    torch.testing.assert_close(y, sp.alpha * eps, rtol=1e-6, atol=0)
    saved = sp.state_dict()["_extra_state"]["generators"]["cpu"]
    assert torch.equal(saved, reference.get_state())


def mixed_seed(seed, rank, step) -> int:
    """The documented reseed after a checkpoint that is not this process's: 63 bits of SHA-256 of
    ``"seed:rank:step"`` (the first eight bytes, little-endian, shifted right once)."""
    digest = hashlib.sha256(f"{seed}:{rank}:{step}".encode()).digest()
    return int.from_bytes(digest[:8], "little") >> 1


# -- seeds -------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed, rank", [(7, 0), (7, 1), (5, 3), (2**40 + 3, 2)])
def test_a_seeded_generator_starts_at_seed_plus_rank(monkeypatch, seed, rank):
    """A seeded preconditioner's first draw comes from a generator seeded with ``seed + rank``."""
    monkeypatch.setattr(pre, "distributed_rank", lambda: rank)
    assert_first_draw_seeded_with(noise_only(seed), seed + rank)


def test_the_rank_is_the_process_groups_and_0_outside_one():
    """Outside a process group the rank is 0 (the seed itself seeds the noise); in one (torch's in-process fake
    backend, rank 2 of 4) it is the group's rank, in the noise and in the saved state."""
    dist = torch.distributed
    assert pre.distributed_rank() == 0
    sp = noise_only(7)
    assert_first_draw_seeded_with(sp, 7)
    assert sp.get_extra_state()["rank"] == 0
    fake_pg = pytest.importorskip("torch.testing._internal.distributed.fake_pg")
    dist.init_process_group("fake", store=fake_pg.FakeStore(), rank=2, world_size=4)
    try:
        assert pre.distributed_rank() == 2
        sp = noise_only(7)
        assert_first_draw_seeded_with(sp, 9)
        assert sp.get_extra_state()["rank"] == 2
    finally:
        dist.destroy_process_group()


def _global_seed_with_a_large_odd_draw():
    """A global seed whose first int64 draw is odd and at least 2**62 (so ``% (1 << 62)``, ``drawn ^ 1`` and
    ``drawn | 1`` each differ from the formula), and that draw."""
    for s in range(200):
        torch.manual_seed(s)
        drawn = int(torch.empty((), dtype=torch.int64).random_())
        if drawn >= 1 << 62 and drawn % 2 == 1:
            return s, drawn
    raise AssertionError("no such global seed in 0..199")


@pytest.mark.parametrize("rank", [0, 1, 3, (1 << 63) - 1])
def test_an_unseeded_generator_starts_at_the_global_draw_plus_rank_modulo_2_63(monkeypatch, rank):
    """``seed=None``: the generator's seed is ``(drawn + rank) % 2**63`` with ``drawn`` the global generator's next
    int64. The last rank stands in for a draw near 2**63 (the sum wraps the same way; such a draw cannot be
    reached by searching seeds)."""
    s, drawn = _global_seed_with_a_large_odd_draw()
    monkeypatch.setattr(pre, "distributed_rank", lambda: rank)
    sp = noise_only(None)
    torch.manual_seed(s)
    assert_first_draw_seeded_with(sp, (drawn + rank) % (1 << 63))


def _saved_at(step, seed=4, **config):
    sp = noise_only(seed, **config)
    sp.set_step(step)
    sp(torch.zeros(4, 3))  # a drawn generator: its state is in the checkpoint
    return sp.state_dict()


@pytest.mark.parametrize("saved_seed, saved_rank, seed, rank", [(4, 0, 5, 0), (4, 1, 4, 0), (4, 0, 4, 2), (4, 2, 4, 1)])
def test_a_checkpoint_of_another_seed_or_rank_reseeds_from_seed_rank_and_the_loaded_step(
        monkeypatch, saved_seed, saved_rank, seed, rank):
    """A module at step 3 loads a state saved at step 37 by another seed or rank (higher or lower): its generator
    is seeded with ``sha256("seed:rank:37")[:8] >> 1`` of its own seed and rank."""
    monkeypatch.setattr(pre, "distributed_rank", lambda: saved_rank)
    state = _saved_at(37, saved_seed)
    monkeypatch.setattr(pre, "distributed_rank", lambda: rank)
    sp = noise_only(seed)
    sp.set_step(3)
    sp.load_state_dict(state)
    assert int(sp.step) == 37
    assert_first_draw_seeded_with(sp, mixed_seed(seed, rank, 37))


def test_a_checkpoint_of_this_process_without_a_drawn_generator_keeps_seed_plus_rank():
    """A state saved before any draw (no generator state to restore) loaded by the same seed and rank: the
    generator starts at ``seed + rank`` as if never saved."""
    saved = noise_only(6)
    saved.set_step(12)
    state = saved.state_dict()
    assert state["_extra_state"]["generators"] == {}
    sp = noise_only(6)
    sp.load_state_dict(state)
    assert int(sp.step) == 12
    assert_first_draw_seeded_with(sp, 6)


def _continues(saved, loaded):
    """``loaded``'s first draw is ``saved``'s next one (the stream was restored)."""
    return torch.equal(loaded(torch.zeros(16, 3)), saved(torch.zeros(16, 3)))


def test_a_state_without_a_rank_entry_is_rank_zeros():
    """A hand-built or older extra state with no ``rank`` is rank 0's: rank 0 restores its stream."""
    saved = noise_only(8)
    saved(torch.zeros(4, 3))
    state = saved.state_dict()
    state["_extra_state"] = {k: v for k, v in state["_extra_state"].items() if k != "rank"}
    sp = noise_only(8)
    sp.load_state_dict(state)
    assert _continues(saved, sp)


def test_a_large_seed_and_rank_read_back_from_a_checkpoint_are_still_this_processs(monkeypatch):
    """Seed 123456789012 and rank 300 (a large job) as equal ints that are not the same objects (a flag's
    parse, a checkpoint's load, ``get_rank()`` per call): the state is this process's and restores its stream."""
    monkeypatch.setattr(pre, "distributed_rank", lambda: parsed_int(300))
    saved = noise_only(parsed_int(123456789012))
    saved(torch.zeros(4, 3))
    state = saved.state_dict()
    sp = noise_only(parsed_int(123456789012))
    assert sp.config.seed is not saved.config.seed
    sp.load_state_dict(state)
    assert _continues(saved, sp)


def test_the_extra_state_is_version_1_with_the_seed_the_rank_and_the_generators():
    """The extra state is version 1 with the seed, the rank and one generator per device drawn on."""
    sp = noise_only(3)
    assert sp.get_extra_state() == {"version": 1, "seed": 3, "rank": 0, "generators": {}}
    sp(torch.zeros(2, 3))
    state = sp.get_extra_state()
    assert state["version"] == 1 and set(state["generators"]) == {"cpu"}


@pytest.mark.parametrize("state", [{"version": 1, "seed": 3, "rank": 0}, {"version": 1, "seed": 3, "rank": 0, "generators": None}])
def test_an_extra_state_without_a_generators_dict_is_refused(state):
    """A dict whose ``generators`` is missing or not a dict (the seed and rank are this process's) is refused."""
    with pytest.raises(ValueError, match="not a generator state"):
        noise_only(3).set_extra_state(state)


# -- step and total ----------------------------------------------------------------------------------


def test_without_a_total_the_step_is_0_the_total_minus_1_and_a_grid_is_off():
    """Before any ``set_step`` (no total): the state dict holds step 0 and total -1 (unknown), the repr says
    ``step=0/-1``, and a grid's scale is 0 (alpha 0, inactive: the input comes back)."""
    sp = SPConfig(alpha0=0.02, end=0.2, alpha_grid=True, alpha_grid_resolution=3).setup(bounds=(-1.0, 1.0)).train()
    state = sp.state_dict()
    assert int(state["step"]) == 0 and int(state["total_steps"]) == -1
    assert "step=0/-1" in sp.extra_repr()
    assert sp.grid_scale == 0.0 and sp.alpha == 0.0 and not sp.active
    x = torch.rand(5, 3)
    assert sp(x) is x


def test_with_a_total_construction_moves_to_step_0():
    """Made with a total number of steps, the preconditioner starts at step 0 of it."""
    sp = build(alpha0=0.02, schedule="linear", end=0.5, total_steps=100)
    assert int(sp.step) == 0 and int(sp.total_steps) == 100 and "step=0/100" in sp.extra_repr()


def test_loading_a_state_without_a_total_leaves_a_fractional_schedule_unresolved():
    """A state saved before the total was known (total -1) loads into the same config without resolving the
    fractional end (which would raise); once the total is set it resolves."""
    cfg = dict(alpha0=0.02, end=0.2)
    saved = SPConfig(**cfg).setup(bounds=(-1.0, 1.0))
    sp = SPConfig(**cfg).setup(bounds=(-1.0, 1.0))
    sp.load_state_dict(saved.state_dict())
    assert int(sp.total_steps) == -1 and sp.schedule is None and sp.alpha == 0.0
    assert sp.set_step(0, 100) == pytest.approx(0.02, rel=1e-12)


def test_loading_a_constant_schedules_state_without_a_total_moves_to_its_step():
    """A constant schedule needs no total: a load moves to the loaded step, so its alpha is in force at once
    (before, the module had never been stepped: alpha 0). The config's kind is a parsed string."""
    saved = SPConfig(alpha0=0.03, schedule="constant", boundary="none").setup()
    saved.set_step(7)
    sp = SPConfig(alpha0=0.03, schedule=parsed("constant"), boundary="none").setup().train()
    assert sp.alpha == 0.0 and not sp.active
    sp.load_state_dict(saved.state_dict())
    assert int(sp.step) == 7 and sp.alpha == 0.03 and sp.active


def test_loading_an_absolute_end_schedules_state_without_a_total_puts_its_alpha_in_force():
    """An absolute ``end`` (in steps) needs no total either: a checkpoint loads with the alpha of its step in
    force (it used to read alpha 0, inactive, until the next ``set_step``: a regression test for that defect,
    found by the mutation study's review)."""
    saved = SPConfig(alpha0=0.04, end=50, schedule="linear", boundary="none").setup()
    saved.set_step(5)
    sp = SPConfig(alpha0=0.04, end=50, schedule="linear", boundary="none").setup().train()
    sp.load_state_dict(saved.state_dict())
    assert int(sp.step) == 5 and int(sp.total_steps) == -1 and sp.active
    assert sp.alpha == pytest.approx(0.04 * (1 - 5 / 50), rel=1e-12)


def test_a_total_of_0_resolves_and_a_state_with_total_0_loads_to_its_alpha():
    """Total 0 is a known total: the fractional end resolves (to step 1, the earliest), and a state holding
    total 0 moves a module without a total to that schedule's alpha at step 0 (exponential: ``alpha0 * (r**0 -
    r) / (1 - r)``)."""
    saved = build(alpha0=0.02, end=0.2, total_steps=0)
    r = 1e-3
    expected = 0.02 * (r**0 - r) / (1 - r)
    assert saved.schedule.end_step == 1 and saved.alpha == pytest.approx(expected, rel=1e-12)
    sp = SPConfig(alpha0=0.02, end=0.2).setup(bounds=(-1.0, 1.0))
    assert sp.alpha == 0.0
    sp.load_state_dict(saved.state_dict())
    assert int(sp.total_steps) == 0 and sp.alpha == pytest.approx(expected, rel=1e-12)


def test_the_schedule_is_resolved_once_per_total_and_again_when_the_total_shrinks_or_grows():
    """The same total keeps the same schedule object; a shorter total (a resume with fewer steps) and a longer
    one each re-resolve the fractional end (linear: ``alpha0 * (1 - t / T)``)."""
    sp = build(alpha0=0.02, schedule="linear", end=0.5, total_steps=400)
    s = sp.schedule
    assert s.end_step == 200 and sp.schedule is s
    sp.set_step(10)
    assert sp.schedule is s
    sp.set_step(10, 400)
    assert sp.schedule is s
    assert sp.set_step(10, 100) == pytest.approx(0.02 * (1 - 10 / 50), rel=1e-12)
    assert sp.schedule.end_step == 50 and int(sp.total_steps) == 100 and "step=10/100" in sp.extra_repr()
    assert sp.set_step(10, 400) == pytest.approx(0.02 * (1 - 10 / 200), rel=1e-12)
    assert sp.schedule.end_step == 200 and int(sp.total_steps) == 400


# -- the alpha grid ----------------------------------------------------------------------------------


@pytest.mark.parametrize("mode", ["replace", "scaled"])
def test_the_grid_scale_and_alpha_at_follow_the_mode_and_are_0_after_the_end(mode):
    """Linear schedule ending at step 50 of 100, the mode a parsed string: ``replace`` scales the grid by 1
    before the end, ``scaled`` by the decay ``1 - t / 50``; after the end both by 0, and ``alpha_at`` is then 0
    too (not the grid)."""
    sp = build(alpha0=0.02, schedule="linear", end=50, alpha_grid=True, alpha_grid_mode=parsed(mode),
               alpha_grid_resolution=3).train()
    sp.alpha_grid.set_values(0.01 * torch.arange(1, 28, dtype=torch.float64).reshape(3, 3, 3))
    x = torch.rand(20, 3, generator=torch.Generator().manual_seed(0)) * 2 - 1
    grid = sp.alpha_grid(x).detach()
    for t in (0, 10, 25, 49, 50, 70):
        sp.set_step(t)
        decay = 1.0 - t / 50 if t < 50 else 0.0
        scale = decay if mode == "scaled" else (1.0 if t < 50 else 0.0)
        assert sp.grid_scale == pytest.approx(scale, rel=1e-12, abs=0)
        assert sp.alpha == pytest.approx(scale * 0.02, rel=1e-12, abs=0)
        assert sp.active == (t < 50)
        torch.testing.assert_close(sp.alpha_at(x), grid * scale, rtol=1e-6, atol=0)


@pytest.mark.parametrize("mode", ["replace", "scaled"])
def test_a_disabled_preconditioner_with_a_grid_has_scale_0(mode):
    """``enabled=False``: the grid's scale is 0 in either mode (alpha 0, inactive, ``alpha_at`` 0)."""
    sp = build(alpha0=0.02, enabled=False, alpha_grid=True, alpha_grid_mode=mode, alpha_grid_resolution=3).train()
    assert sp.grid_scale == 0.0 and sp.alpha == 0.0 and not sp.active
    x = torch.rand(4, 3)
    assert sp(x) is x and torch.equal(sp.alpha_at(x), torch.zeros(4, 1))


def test_a_grid_without_bounds_covers_minus_one_to_one():
    """No bounds (boundary none): the grid spans [-1, 1]^3, so at the 27 positions with coordinates -1, 0, 1 it
    gives its 27 node values (index 0, 1, 2 per axis, the last axis x)."""
    sp = SPConfig(alpha0=0.02, boundary="none", alpha_grid=True, alpha_grid_resolution=3).setup(total_steps=100)
    values = 0.01 * torch.arange(1, 28, dtype=torch.float64).reshape(3, 3, 3)
    sp.alpha_grid.set_values(values)
    nodes = torch.tensor([-1.0, 0.0, 1.0])
    index = torch.cartesian_prod(torch.arange(3), torch.arange(3), torch.arange(3))  # (ix, iy, iz)
    expected = values[index[:, 2], index[:, 1], index[:, 0]].float()[:, None]
    torch.testing.assert_close(sp.alpha_at(nodes[index]), expected, rtol=1e-5, atol=0)


@pytest.mark.parametrize("diagonal", [-2.0, float("nan")])
def test_a_grid_whose_alpha0_in_scene_units_is_not_positive_is_refused_by_the_preconditioner(diagonal):
    """``relative_to_diagonal`` with a negative or NaN diagonal makes the grid's initial alpha ``alpha0 *
    diagonal`` negative or NaN: the preconditioner's own check refuses it (not the grid's)."""
    cfg = SPConfig(alpha0=0.01, relative_to_diagonal=True, alpha_grid=True, alpha_grid_resolution=3)
    with pytest.raises(ValueError, match="alpha_grid=True needs a positive initial alpha"):
        cfg.setup(bounds=(-1.0, 1.0), scene_diagonal=diagonal)


# -- construction ------------------------------------------------------------------------------------


def test_clamp_without_bounds_is_refused_and_a_parsed_none_needs_none():
    """``clamp`` without the scene bounds is refused; a boundary named by a parsed "none" needs no bounds."""
    with pytest.raises(ValueError, match="boundary='clamp' needs the scene bounds"):
        SPConfig(boundary="clamp").setup(total_steps=10)
    sp = SPConfig(boundary=parsed("none"), alpha0=0.1, schedule="constant", seed=1).setup(total_steps=10).train()
    assert_first_draw_seeded_with(sp, 1)


def test_only_the_config_is_positional():
    """Only the config is positional; the total number of steps is keyword-only."""
    cfg = SPConfig(boundary="none")
    with pytest.raises(TypeError):
        StochasticPreconditioner(cfg, 10)
    sp = StochasticPreconditioner(config=cfg, total_steps=10)
    assert int(sp.total_steps) == 10


def test_with_boundary_none_the_box_is_not_handed_to_perturb():
    """Boundary a parsed "none" with bounds given: the box plays no part, so positions of another dimension
    than the module's (2-D positions, the default ``dim=3``), outside the box, come back as ``x + alpha * eps``."""
    sp = build(alpha0=0.1, schedule="constant", boundary=parsed("none"), seed=3).train()
    x = torch.full((5, 2), 4.0)
    eps = torch.randn(5, 2, generator=torch.Generator().manual_seed(3))
    torch.testing.assert_close(sp(x), x + 0.1 * eps, rtol=1e-6, atol=1e-6)


# -- several draws -----------------------------------------------------------------------------------


def test_mean_over_draws_with_one_sample_returns_the_call_itself_and_with_two_the_mean_of_two():
    """One sample (active): one call, whose result comes back itself. Two: two calls, averaged; integer
    entries from the first."""
    one = noise_only(0)
    assert one.active
    out = {"rgb": torch.ones(3), "index": torch.arange(3)}
    assert one.mean_over_draws(lambda: out) is out
    two = noise_only(0, num_samples=2)
    calls = []

    def once():
        value = torch.full((3,), float(len(calls) + 1))
        calls.append(value)
        return {"rgb": value, "index": torch.arange(3) + len(calls)}

    mean = two.mean_over_draws(once)
    assert len(calls) == 2
    assert torch.equal(mean["rgb"], (calls[0] + calls[1]) * 0.5) and torch.equal(mean["index"], torch.arange(3) + 1)


def test_mean_over_draws_averages_a_named_tuple_and_a_list_and_keeps_their_types():
    """A field may return a named tuple (its outputs by name): two draws average it field by field, and
    it comes back as that named tuple (it used to raise ``TypeError: __new__() missing ...``: a regression
    test for that defect, found by the mutation study's review)."""
    import collections

    Outputs = collections.namedtuple("Outputs", ["density", "rgb", "index"])
    sp = noise_only(0, num_samples=2)
    draws = iter([(1.0, 4.0), (3.0, 8.0)])

    def once():
        d, c = next(draws)
        return Outputs(torch.full((2,), d), [torch.full((3,), c), 7], torch.arange(2))

    out = sp.mean_over_draws(once)
    assert type(out) is Outputs and type(out.rgb) is list
    assert out.density.tolist() == [2.0, 2.0] and out.rgb[0].tolist() == [6.0] * 3 and out.rgb[1] == 7
    assert out.index.tolist() == [0, 1]


def test_blurred_with_two_samples_is_the_mean_of_fn_over_two_draws():
    """``blurred`` with K = 2 (seed 2, constant alpha 0.1, no box): ``mean_k fn(x + 0.1 eps_k)`` with ``eps``
    the generator's ``[2, N, 3]`` draws."""
    sp = noise_only(2, num_samples=2)
    x = torch.rand(6, 3, generator=torch.Generator().manual_seed(1))
    fn = lambda p: torch.sin(3.0 * p).sum(-1)  # noqa: E731
    eps = torch.randn(2, 6, 3, generator=torch.Generator().manual_seed(2))
    torch.testing.assert_close(sp.blurred(fn, x), fn(x + 0.1 * eps).mean(0), rtol=1e-5, atol=1e-6)


def test_blurred_with_one_sample_is_fn_of_the_modules_own_call():
    """K = 1: ``fn`` of one perturbation, drawn through the module's own call (its forward hooks see it)."""
    sp = noise_only(2)
    seen = []
    sp.register_forward_hook(lambda module, args, output: seen.append(output))
    x = torch.rand(6, 3, generator=torch.Generator().manual_seed(1))
    fn = lambda p: torch.sin(3.0 * p).sum(-1)  # noqa: E731
    y = sp.blurred(fn, x)
    eps = torch.randn(6, 3, generator=torch.Generator().manual_seed(2))
    assert len(seen) == 1
    torch.testing.assert_close(seen[0], x + 0.1 * eps, rtol=1e-6, atol=1e-7)
    assert torch.equal(y, fn(seen[0]))


# -- repr --------------------------------------------------------------------------------------------


def test_extra_repr_names_the_state_and_the_grid_only_with_one():
    """The repr names the state, and the alpha grid's mode and factor only when there is a grid."""
    plain = build(alpha0=0.02, schedule="linear", end=50)
    assert plain.extra_repr() == "enabled=True, alpha=0.02, step=0/100, noise=gaussian, boundary=reflect"
    scaled = build(alpha0=0.02, schedule="linear", end=50, alpha_grid=True, alpha_grid_mode="scaled",
                   alpha_grid_resolution=3, noise="uniform", boundary="clamp")
    scaled.set_step(25)
    assert scaled.extra_repr() == (
        "enabled=True, alpha=0.01, alpha_grid=scaled x0.5, step=25/100, noise=uniform, boundary=clamp"
    )
