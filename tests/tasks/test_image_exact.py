"""Exact values of the image-fitting task: in one step with the learnable alpha map the
field is queried at ``p + alpha_map(p) * eps`` (K draws averaged) folded into the image square
``[0, 1]^2``, and the gradient reaching the alpha map is the reparameterised ``eps``-weighted value,
computed here by autograd through the paper's formula on copies of the field and the map.
Then, ahead of the mutation study of image.py, the rest of the task from first principles: its defaults
and bounds, the seeded field and batches, the alpha map's cells and box, phase 2 (its start, the frozen
map, inverse-alpha pixel sampling, per-pixel level masks from the map's quantiles), the lr decay,
resuming, render / PSNR, and the image loader's bit depths and transparency.
The mutation of ``sp_plugins/tasks/image.py`` / the core each test kills is listed in
``bench/results/mutation_study/kills.json``."""

from __future__ import annotations

import copy
import math
import re
import sys

import numpy as np
import pytest
import torch

from sp_plugins import SPConfig
from sp_plugins.tasks import image as image_task
from sp_plugins.tasks.fields import EncodingConfig, NeuralField
from sp_plugins.tasks.image import ImageFitConfig
from tests.helpers.exact import Recorder, assert_read_folded, sp_draws

H, W, SP_SEED = 6, 8, 9


def pixel_centres() -> torch.Tensor:
    """``(x, y)`` of the pixel centres in [0, 1]^2, row-major (written here, not the task's helper)."""
    return torch.tensor([[(j + 0.5) / W, (i + 0.5) / H] for i in range(H) for j in range(W)])


@pytest.mark.parametrize("k", [1, 2])
def test_one_step_queries_p_plus_the_maps_alpha_eps_and_the_map_gets_the_eps_weighted_gradient(k):
    """K = 1 and 2: the field reads ``fold(p + alpha_map(p) * eps_k)`` into [0, 1]^2 at every pixel
    centre, and d loss / d (alpha map) equals autograd through that formula with the mean colour
    over the K draws."""
    image = np.random.default_rng(0).random((H, W, 3)).astype(np.float32)
    config = ImageFitConfig(steps=10, batch=4096, hidden=(16,), adaptive_alpha=True, alpha_map_downscale=2,
                            encoding=EncodingConfig(levels=3, log2_table_size=8, base_resolution=2, max_resolution=8),
                            sp=SPConfig(alpha0=0.2, schedule="constant", seed=SP_SEED, num_samples=k))
    trainer = config.setup(image)
    with torch.no_grad():  # a map that is not constant: which cell a pixel reads matters
        values = 0.05 + 0.4 * torch.rand(trainer.sp.alpha_grid.values().shape, generator=torch.Generator().manual_seed(1))
        trainer.sp.alpha_grid.set_values(values)
    field, grid = copy.deepcopy(trainer.field), copy.deepcopy(trainer.sp.alpha_grid)
    trainer.field = Recorder(trainer.field)
    trainer.step()

    p = pixel_centres()
    q = assert_read_folded(trainer, p, grid(p), sp_draws(p, k, SP_SEED), 0.0, 1.0)

    rgb = torch.sigmoid(field(q.float()))
    rgb = rgb.mean(0) if k > 1 else rgb
    loss = (rgb - torch.from_numpy(image.reshape(-1, 3))).square().mean()
    loss.backward()
    assert grid.param.grad.abs().max() > 0
    torch.testing.assert_close(trainer.sp.alpha_grid.param.grad, grid.param.grad, rtol=1e-4, atol=1e-7)
    assert trainer.history["loss"][0] == pytest.approx(float(loss), rel=1e-5)


# --- ahead of the mutation study of image.py ---------------------------------------------

GRID = EncodingConfig(levels=3, log2_table_size=8, base_resolution=2, max_resolution=8)


def tiny(**kw) -> ImageFitConfig:
    base = dict(steps=4, batch=4096, hidden=(8,), encoding=GRID)
    base.update(kw)
    return ImageFitConfig(**base)


def picture(seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).random((H, W, 3)).astype(np.float32)


def adaptive(**kw) -> ImageFitConfig:
    """An adaptive-alpha fit whose SP (step schedule) ends at step 1: phase 2 from step 1 on."""
    base = dict(adaptive_alpha=True, alpha_map_downscale=2, sp=SPConfig(alpha0=0.05, schedule="step", end=0.25))
    base.update(kw)
    return tiny(**base)


def test_the_defaults_are_the_readmes_image_setting():
    """README's SP table for ``sp-fit image`` (on, alpha 0.01, exponential, end 0.2, gaussian, reflect), Instant-NGP's
    image field (16 levels, 2^14 rows, resolutions 8..512) and step (16384 pixels, lr 1e-2), the paper's alpha map
    (1/16 of the image, Adam lr 0.01), phase 2 off with its documented settings, no lr decay (x0.6 at 2/3 when
    asked)."""
    c = ImageFitConfig()
    assert (c.steps, c.seed, c.hidden) == (2000, 0, (64, 64))
    assert (c.batch, c.lr) == (16384, 1e-2)
    assert (c.adaptive_alpha, c.alpha_map_downscale, c.alpha_map_lr) == (False, 16, 1e-2)
    assert (c.importance_sampling, c.importance_uniform) == (False, 0.5)
    assert (c.level_masking, c.level_mask_min_levels, c.level_mask_quantiles) == (False, 8.0, (0.05, 0.95))
    assert c.lr_decay == 1.0 and c.lr_decay_at == pytest.approx(2 / 3, rel=1e-15)
    e = c.encoding
    assert (e.kind, e.levels, e.log2_table_size, e.base_resolution, e.max_resolution) == ("hashgrid", 16, 14, 8, 512)
    assert e.features_per_level == 2
    s = c.sp
    assert (s.enabled, s.alpha0, s.schedule, s.end, s.noise, s.boundary) == (True, 0.01, "exponential", 0.2, "gaussian", "reflect")
    assert (s.num_samples, s.alpha_grid, s.seed) == (1, False, None)
    assert c._target is image_task.ImageFitTrainer


POSITIVE = "steps, batch, lr and alpha_map_lr must be positive"
PHASE2 = dict(adaptive_alpha=True, importance_sampling=True, level_masking=True)


@pytest.mark.parametrize("options, refused, accepted, message", [
    (dict(), dict(steps=0), dict(steps=1), POSITIVE),
    (dict(), dict(batch=0), dict(batch=1), POSITIVE),
    (dict(), dict(lr=0.0), dict(lr=1e-12), POSITIVE),
    (dict(), dict(lr=-1e-2), dict(lr=1e-12), POSITIVE),
    (dict(), dict(alpha_map_lr=0.0), dict(alpha_map_lr=1e-12), POSITIVE),
    (dict(), dict(alpha_map_lr=-1e-2), dict(alpha_map_lr=1e-12), POSITIVE),
    (dict(), dict(lr=float("nan")), dict(lr=1e-12), POSITIVE),
    (dict(), dict(alpha_map_lr=float("nan")), dict(alpha_map_lr=1e-12), POSITIVE),
    (dict(), dict(alpha_map_downscale=0), dict(alpha_map_downscale=1), "alpha_map_downscale=0: must be >= 1"),
    (PHASE2, dict(level_mask_min_levels=0.0), dict(level_mask_min_levels=1e-6),
     "level_mask_min_levels=0.0: must be in (0, encoding.levels=16]"),
    (PHASE2, dict(level_mask_min_levels=16.5), dict(level_mask_min_levels=16.0),
     "level_mask_min_levels=16.5: must be in (0, encoding.levels=16]"),
    (PHASE2, dict(level_mask_min_levels=-1.0), dict(level_mask_min_levels=1.0),
     "level_mask_min_levels=-1.0: must be in (0, encoding.levels=16]"),
    (PHASE2, dict(level_mask_quantiles=(0.6, 0.4)), dict(level_mask_quantiles=(0.4, 0.6)),
     "level_mask_quantiles=(0.6, 0.4): need 0 <= low < high <= 1"),
    (PHASE2, dict(level_mask_quantiles=(-0.01, 0.5)), dict(level_mask_quantiles=(0.0, 0.5)),
     "level_mask_quantiles=(-0.01, 0.5): need 0 <= low < high <= 1"),
    (PHASE2, dict(level_mask_quantiles=(0.5, 0.5)), dict(level_mask_quantiles=(0.49, 0.5)),
     "level_mask_quantiles=(0.5, 0.5): need 0 <= low < high <= 1"),
    (PHASE2, dict(level_mask_quantiles=(0.5, 1.01)), dict(level_mask_quantiles=(0.5, 1.0)),
     "level_mask_quantiles=(0.5, 1.01): need 0 <= low < high <= 1"),
    (PHASE2, dict(importance_uniform=-0.01), dict(importance_uniform=0.0), "importance_uniform=-0.01: must be in [0, 1]"),
    (PHASE2, dict(importance_uniform=1.01), dict(importance_uniform=1.0), "importance_uniform=1.01: must be in [0, 1]"),
    (dict(), dict(lr_decay=0.0), dict(lr_decay=1e-9), "lr_decay=0.0, lr_decay_at=0.6666666666666666: need lr_decay > 0 and 0 < lr_decay_at < 1"),
    (dict(), dict(lr_decay=-0.5), dict(lr_decay=0.5), "lr_decay=-0.5, lr_decay_at=0.6666666666666666: need lr_decay > 0 and 0 < lr_decay_at < 1"),
    (dict(), dict(lr_decay_at=0.0), dict(lr_decay_at=1e-9), "lr_decay=1.0, lr_decay_at=0.0: need lr_decay > 0 and 0 < lr_decay_at < 1"),
    (dict(), dict(lr_decay_at=-0.5), dict(lr_decay_at=0.5), "lr_decay=1.0, lr_decay_at=-0.5: need lr_decay > 0 and 0 < lr_decay_at < 1"),
    (dict(), dict(lr_decay_at=1.0), dict(lr_decay_at=0.999), "lr_decay=1.0, lr_decay_at=1.0: need lr_decay > 0 and 0 < lr_decay_at < 1"),
    (dict(), dict(lr_decay_at=1.5), dict(lr_decay_at=0.5), "lr_decay=1.0, lr_decay_at=1.5: need lr_decay > 0 and 0 < lr_decay_at < 1"),
    (dict(steps=10, lr_decay=0.6), dict(lr_decay_at=0.95), dict(lr_decay_at=0.94),
     "lr_decay_at=0.95 with steps=10: the decay would come at step 10, after the last (9); lower --lr-decay-at"),
    (dict(steps=10, lr_decay=0.6), dict(lr_decay_at=0.99), dict(lr_decay=1.0, lr_decay_at=0.99),
     "lr_decay_at=0.99 with steps=10: the decay would come at step 10, after the last (9); lower --lr-decay-at"),
    (dict(steps=10, lr_decay=1.5), dict(lr_decay_at=0.95), dict(lr_decay_at=0.94),
     "lr_decay_at=0.95 with steps=10: the decay would come at step 10, after the last (9); lower --lr-decay-at"),
    (dict(steps=1000, lr_decay=0.6), dict(lr_decay_at=0.9996), dict(lr_decay_at=0.9994),
     "lr_decay_at=0.9996 with steps=1000: the decay would come at step 1000, after the last (999); lower --lr-decay-at"),
    (dict(), dict(encoding=EncodingConfig(kind="".join(["tri", "plane"]))), dict(encoding=EncodingConfig(kind="finer")),
     "encoding kind='triplane' is 3D only; use hashgrid, fourier or finer for images"),
    (dict(), dict(sp=SPConfig(alpha_grid=True)), dict(sp=SPConfig(alpha_grid=False)),
     "alpha_grid: --sp.alpha-grid is the 3D methods' alpha grid; for an image use --adaptive-alpha"),
])
def test_validation_refuses_exactly_the_documented_values_in_one_line(options, refused, accepted, message):
    """Each bound at its edge: the first refused value gives the one line ``sp-fit`` prints, the value at the edge
    is accepted; negative values and a low quantile above the high one are refused. (The triplane kind is built at
    run time, as a parsed flag is: equal to the literal, not the same object.) A NaN ``--lr`` or ``--alpha-map-lr``
    passed ``lr <= 0`` and trained into a NaN loss (or torch's "Invalid learning rate: nan"); it is refused now.
    ``--lr-decay-at 1.0`` (or one whose step ``round(lr_decay_at * steps)`` is ``steps``) was accepted and never
    applied (no step has that index); both are refused now, a decay-free fit (``lr_decay`` 1) keeps any
    ``lr_decay_at`` in (0, 1)."""
    with pytest.raises(ValueError) as refused_error:
        ImageFitConfig(**dict(options, **refused)).validate()
    assert str(refused_error.value) == message
    ImageFitConfig(**dict(options, **accepted)).validate()


def test_an_unknown_encoding_kind_gets_the_encodings_own_line_not_the_triplane_one():
    """Kinds that sort after "triplane" are not the triplane: ``kind == "triplane"`` -> ``>=`` gave them the
    triplane line; they get the encoding's list of kinds."""
    with pytest.raises(ValueError) as refused:
        ImageFitConfig(encoding=EncodingConfig(kind="wavelet")).validate()
    assert str(refused.value) == "encoding kind='wavelet' is not known; allowed values: hashgrid, fourier, triplane, finer"


@pytest.mark.parametrize("flag", ["importance_sampling", "level_masking"])
def test_a_phase_2_technique_needs_the_map_and_its_options_need_the_technique(flag):
    """``--importance-sampling`` / ``--level-masking`` alone are refused naming ``--adaptive-alpha``; each phase-2
    option set to another value without its technique is refused naming both; the documented defaults given
    explicitly (equal values, not the dataclass's objects, as from the command line) are accepted; values on both
    sides of a default are refused."""
    dashed = flag.replace("_", "-")
    with pytest.raises(ValueError) as refused:
        ImageFitConfig(**{flag: True}).validate()
    assert str(refused.value) == f"--{dashed} uses the learned alpha map: add --adaptive-alpha (or drop --{dashed})"
    ImageFitConfig(adaptive_alpha=True, **{flag: True}).validate()
    ImageFitConfig(adaptive_alpha=True).validate()
    explicit = dict(importance_uniform=float("0.5"), level_mask_min_levels=float("8"),
                    level_mask_quantiles=(float("0.05"), float("0.95")))
    ImageFitConfig(**explicit).validate()
    for name, value, needs in (("importance_uniform", 0.25, "importance-sampling"),
                               ("importance_uniform", 0.75, "importance-sampling"),
                               ("level_mask_min_levels", 4.0, "level-masking"),
                               ("level_mask_min_levels", 12.0, "level-masking"),
                               ("level_mask_quantiles", (0.1, 0.9), "level-masking"),
                               ("level_mask_quantiles", (0.01, 0.99), "level-masking")):
        with pytest.raises(ValueError) as refused:
            ImageFitConfig(adaptive_alpha=True, **{name: value}).validate()
        assert str(refused.value) == f"--{name.replace('_', '-')} applies with --{needs}: add it or drop the option"


def test_level_masking_needs_a_hash_grid():
    """Any other kind, also one that sorts after "hashgrid", is refused naming it; "hashgrid" given at run time (equal
    to the literal, not the same object) is accepted."""
    for kind in ("fourier", "wavelet"):
        with pytest.raises(ValueError) as refused:
            ImageFitConfig(adaptive_alpha=True, level_masking=True, encoding=EncodingConfig(kind=kind)).validate()
        assert str(refused.value) == f"--level-masking masks hash-grid levels: use --encoding.kind hashgrid (got {kind!r})"
    ImageFitConfig(encoding=EncodingConfig(kind="fourier")).validate()
    ImageFitConfig(adaptive_alpha=True, level_masking=True, encoding=EncodingConfig(kind="".join(["hash", "grid"]))).validate()


def test_a_folder_or_a_missing_file_is_refused_saying_which(tmp_path):
    """A folder, or a missing file, given as the image is refused in one line saying which."""
    with pytest.raises(ValueError) as refused:
        image_task.load_image(tmp_path)
    assert str(refused.value) == f"{tmp_path}: is a folder; give a file inside it"
    with pytest.raises(ValueError) as refused:
        image_task.load_image(tmp_path / "missing.png")
    assert str(refused.value) == f"{tmp_path / 'missing.png'}: no such file"


@pytest.mark.parametrize("bad", [np.zeros((H, W)), np.zeros((H, W, 4)), np.zeros((H, W, 2)), np.zeros((2, 3, 3, 3)),
                                 np.full((H, W, 3), np.nan), np.full((H, W, 3), np.inf)])
def test_the_trainer_refuses_an_image_that_is_not_a_finite_h_w_3_array(bad):
    """(A 4-D array whose third axis is 3 passes the channel test; a 2-channel one passes ``> 3``.)"""
    with pytest.raises(ValueError) as refused:
        tiny().setup(bad)
    assert str(refused.value) == "image: need a finite [H, W, 3] array"
    trainer = tiny().setup(picture())
    assert (trainer.height, trainer.width) == (H, W)


def test_the_device_is_keyword_only_and_setup_passes_it_on():
    """``ImageFitTrainer(config, image, *, device)``; ``config.setup(image, device=...)``."""
    with pytest.raises(TypeError):
        image_task.ImageFitTrainer(tiny(), picture(), "cpu")
    trainer = tiny().setup(picture(), device="cpu")
    assert trainer.device == torch.device("cpu") and trainer.positions.device.type == "cpu"


def test_the_field_is_the_seeded_2d_rgb_field_on_the_image_square_and_adam_is_instant_ngps():
    """The field is ``NeuralField(encoding, dim=2, out_dim=3, relu, features only, bounds (0, 1))`` initialised
    from ``config.seed`` (built here independently: the same parameters and the same outputs), with
    ``sigmoid`` on top; Adam has Instant-NGP's betas (0.9, 0.99) and eps 1e-15, the field's lr, and the fused
    kernel on a CPU."""
    config = tiny(seed=3, hidden=(8, 8))
    trainer = config.setup(picture())
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(3)
        reference = NeuralField(GRID, dim=2, out_dim=3, hidden=(8, 8), activation="relu", include_input=False,
                                bounds=(0.0, 1.0))
    assert trainer.field.mlp[0].in_features == GRID.levels * GRID.features_per_level
    own, ref = trainer.field.state_dict(), reference.state_dict()
    assert own.keys() == ref.keys() and all(torch.equal(own[k], ref[k]) for k in own)
    p = pixel_centres()
    assert torch.equal(trainer.positions, p)
    assert torch.equal(trainer.colours, torch.from_numpy(picture().reshape(-1, 3)))
    with torch.no_grad():
        assert torch.equal(trainer.rgb(p), torch.sigmoid(reference(p)))
    (group,) = trainer.optimizer.param_groups
    assert (group["betas"], group["eps"], group["lr"], group["fused"]) == ((0.9, 0.99), 1e-15, config.lr, True)
    assert [id(q) for q in group["params"]] == [id(q) for q in trainer.field.parameters()]


def test_the_alpha_map_has_one_cell_per_downscale_pixels_at_least_two_starts_at_alpha0_and_has_its_own_lr():
    """6x8 pixels: ``alpha_map_downscale`` 2 -> a 4 (x) by 3 (y) map, 4 -> 2 by 2 (8 // 4 = 2, 6 // 4 = 1 raised to
    the grid's minimum 2), every cell at ``sp.alpha0``; the map is SP's alpha grid over the image square and
    its Adam group runs at ``alpha_map_lr``, the field's at ``lr``."""
    for downscale, shape in ((2, (3, 4)), (4, (2, 2))):
        trainer = tiny(lr=0.02, adaptive_alpha=True, alpha_map_downscale=downscale, alpha_map_lr=0.03,
                       sp=SPConfig(alpha0=0.07, schedule="constant")).setup(picture())
        values = trainer.sp.alpha_grid.values()
        assert tuple(values.shape) == shape
        torch.testing.assert_close(values, torch.full(shape, 0.07), rtol=1e-6, atol=0)
        field_group, map_group = trainer.optimizer.param_groups
        assert (field_group["lr"], map_group["lr"]) == (0.02, 0.03)
        assert [id(q) for q in map_group["params"]] == [id(q) for q in trainer.sp.alpha_grid.parameters()]
    assert tiny().setup(picture()).sp.alpha_grid is None


def alpha_at(values: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """The map's alpha at points of [0, 1]^2: cell centres at the grid's corners (cell ``i`` of ``R`` at
    ``i / (R - 1)``), bilinear in log alpha between them (the log parameterisation), in float64."""
    rows, cols = values.shape
    logs = values.double().log()
    gx, gy = p[:, 0].double() * (cols - 1), p[:, 1].double() * (rows - 1)
    x0, y0 = gx.floor().long().clamp(max=cols - 2), gy.floor().long().clamp(max=rows - 2)
    fx, fy = gx - x0, gy - y0
    top = logs[y0, x0] * (1 - fx) + logs[y0, x0 + 1] * fx
    bottom = logs[y0 + 1, x0] * (1 - fx) + logs[y0 + 1, x0 + 1] * fx
    return (top * (1 - fy) + bottom * fy).exp()


def test_the_alpha_map_covers_the_image_square():
    """A map that is not constant, read at the pixel centres, equals the bilinear (log) interpolation over
    [0, 1]^2 computed here; ``pixel_alpha`` reads it without a gradient even while the map learns."""
    trainer = tiny(adaptive_alpha=True, alpha_map_downscale=2, sp=SPConfig(alpha0=0.1, schedule="constant")).setup(picture())
    values = 0.01 + 0.2 * torch.rand(3, 4, generator=torch.Generator().manual_seed(2))
    trainer.sp.alpha_grid.set_values(values)
    read = trainer.pixel_alpha()
    assert trainer.sp.alpha_grid.param.requires_grad and not read.requires_grad
    assert read.shape == (H * W,)
    torch.testing.assert_close(read.double(), alpha_at(values, pixel_centres()), rtol=1e-5, atol=0)


@pytest.mark.parametrize("sp, refused", [
    (SPConfig(enabled=False), True), (SPConfig(alpha0=0.0, schedule="constant"), True),
    (SPConfig(alpha0=1e-9, schedule="constant"), False),
])
def test_the_alpha_map_needs_sp_on_with_a_positive_alpha0(sp, refused):
    """The adaptive alpha map needs SP on with alpha0 > 0 and is refused in one line otherwise."""
    config = tiny(adaptive_alpha=True, sp=sp)
    if not refused:
        assert config.setup(picture()).sp.alpha_grid is not None
        return
    with pytest.raises(ValueError) as refused_error:
        config.setup(picture())
    assert str(refused_error.value) == "adaptive_alpha needs SP on with alpha0 > 0 (its initial value)"


@pytest.mark.parametrize("technique", ["importance_sampling", "level_masking"])
def test_phase_2_needs_sp_to_end_before_the_last_step(technique):
    """10 steps: SP ending at step 8 leaves phase 2 two steps, accepted; ending at step 9 (the last) or never
    (constant) is refused in one line naming the schedule, its end and the last step."""
    def config(sp, steps=10):
        masking = dict(level_mask_min_levels=2.0) if technique == "level_masking" else {}
        return tiny(steps=steps, adaptive_alpha=True, **{technique: True}, **masking, sp=sp)

    assert config(SPConfig(alpha0=0.05, schedule="step", end=0.8)).setup(picture()).sp.end_step == 8
    for sp, described in ((SPConfig(alpha0=0.05, schedule="step", end=0.9), "step, end=0.9"),
                          (SPConfig(alpha0=0.05, schedule="constant"), "constant, end=0.2")):
        with pytest.raises(ValueError) as refused:
            config(sp).setup(picture())
        assert str(refused.value) == (
            "--importance-sampling / --level-masking start when SP ends, but the SP schedule "
            f"({described}) never ends before the last step (9): give --sp.end < 1")
    tiny(steps=10, adaptive_alpha=True, sp=SPConfig(alpha0=0.05, schedule="constant")).setup(picture())  # no phase 2 asked
    with pytest.raises(ValueError, match=r"never ends before the last step \(299\)"):  # ints past Python's small-int cache
        config(SPConfig(alpha0=0.05, schedule="step", end=1.0), steps=300).setup(picture())


def test_level_masking_wraps_the_encoding_inactive_until_phase_2():
    """With ``--level-masking`` the encoding is a :class:`PerPointLevelMask` with no levels function yet (the
    field as without it); without it, the plain encoding."""
    from sp_plugins.encodings.level_mask import PerPointLevelMask

    plain = adaptive().setup(picture())
    masked = adaptive(level_masking=True, level_mask_min_levels=2.0).setup(picture())
    assert not isinstance(plain.field.encoding, PerPointLevelMask)
    assert isinstance(masked.field.encoding, PerPointLevelMask) and masked.field.encoding.levels_fn is None
    with torch.no_grad():
        assert torch.equal(masked.rgb(masked.positions), plain.rgb(plain.positions))


def test_one_step_without_sp_reads_every_pixel_in_order_or_a_seeded_batch_and_fits_the_mean_squared_error():
    """SP off: a batch of at least the image reads every pixel centre in order; a smaller one reads
    ``randint(n, (batch,))`` from the batch generator seeded ``config.seed``; the loss is the mean squared
    error of ``sigmoid(field)`` against those pixels' colours."""
    n = H * W
    for batch, seed in ((n, 0), (n - 1, 5)):
        trainer = tiny(batch=batch, seed=seed, sp=SPConfig(enabled=False)).setup(picture())
        field = copy.deepcopy(trainer.field)
        trainer.field = Recorder(trainer.field)
        trainer.step()
        idx = torch.arange(n) if batch == n else torch.randint(n, (batch,), generator=torch.Generator().manual_seed(seed))
        (read,) = trainer.field.inputs
        assert torch.equal(read, pixel_centres()[idx])
        with torch.no_grad():
            loss = (torch.sigmoid(field(pixel_centres()[idx])) - torch.from_numpy(picture().reshape(-1, 3))[idx]).square().mean()
        assert trainer.history["loss"][0] == pytest.approx(float(loss), rel=1e-6)
        assert trainer.history["alpha"] == [0.0]


def lrs_of_a_fit(config) -> list:
    """Each group's learning rate at each optimizer step of a whole fit."""
    trainer = config.setup(picture())
    lrs = []
    trainer.optimizer.register_step_pre_hook(lambda opt, args, kwargs: lrs.append([g["lr"] for g in opt.param_groups]))
    trainer.fit()
    return lrs


@pytest.mark.parametrize("decay", [0.5, 2.0])
def test_the_field_lr_is_multiplied_by_lr_decay_once_at_round_lr_decay_at_times_steps(decay):
    """7 steps, ``lr_decay_at`` 0.5: steps 0-3 at lr (round(3.5) = 4), steps 4-6 at exactly ``lr * lr_decay`` (also a
    factor of 2, above 1), the alpha map's group untouched; by default (2/3 of 9 steps) from step 6."""
    sp = SPConfig(alpha0=0.05, schedule="constant")
    lrs = lrs_of_a_fit(tiny(steps=7, lr=0.02, lr_decay=decay, lr_decay_at=0.5, adaptive_alpha=True, alpha_map_lr=0.03, sp=sp))
    assert lrs == [[0.02, 0.03]] * 4 + [[0.02 * decay, 0.03]] * 3
    assert lrs_of_a_fit(tiny(steps=9, lr=0.02, lr_decay=0.6)) == [[0.02]] * 6 + [[0.02 * 0.6]] * 3


def test_the_lr_decay_step_is_compared_by_value_past_pythons_cached_small_ints():
    """300 steps, decay at 0.9: step 270 (an int above 256, so the step counter and ``round``'s result are distinct
    objects)."""
    trainer = tiny(steps=300, lr=0.02, lr_decay=0.5, lr_decay_at=0.9).setup(picture())
    lrs = []
    trainer.optimizer.register_step_pre_hook(lambda opt, args, kwargs: lrs.append(opt.param_groups[0]["lr"]))
    trainer.step_index = 268
    for _ in range(3):
        trainer.step()
    assert lrs == [0.02, 0.02, 0.01]


def test_phase_2_starts_at_the_first_step_at_alpha_0_and_freezes_the_map():
    """SP (step schedule) ends at step 1: step 0 is phase 1 (alpha0, the map learns), step 1 starts phase 2 and
    it stays the step it started (not restarted); the map no longer requires a gradient and no later step moves
    it (``zero_grad(set_to_none=True)``: Adam skips it); each step records the map's mean. Without the map the
    same schedule has no phase 2; SP ending at step 2 starts it at step 2."""
    trainer = adaptive(steps=4).setup(picture())
    start = trainer.sp.alpha_grid.values().clone()
    trainer.step()
    assert trainer.phase2_step is None and trainer.sp.alpha_grid.param.requires_grad
    learned = trainer.sp.alpha_grid.values().clone()
    assert not torch.equal(learned, start)
    means = [float(learned.mean())]
    for step in (1, 2, 3):
        trainer.step()
        assert trainer.phase2_step == 1 and not trainer.sp.alpha_grid.param.requires_grad
        assert torch.equal(trainer.sp.alpha_grid.values(), learned)
        means.append(float(learned.mean()))
    assert trainer.history["alpha"] == [0.05, 0.0, 0.0, 0.0]
    assert trainer.history["alpha_map_mean"] == pytest.approx(means, rel=1e-6)
    later = adaptive(steps=4, sp=SPConfig(alpha0=0.05, schedule="step", end=0.5)).setup(picture())  # SP ends at step 2
    later.step()
    later.step()
    assert later.phase2_step is None
    later.step()
    assert later.phase2_step == 2
    plain = tiny(steps=4, sp=SPConfig(alpha0=0.05, schedule="step", end=0.25)).setup(picture())
    plain.fit()
    assert plain.phase2_step is None and "alpha_map_mean" not in plain.history


def draws(cdf: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """Inverse-CDF draws: pixel ``i`` owns ``[cdf[i-1], cdf[i])``, so ``u`` draws the number of entries ``<= u``."""
    return (cdf[None, :] <= u[:, None]).sum(1)


def test_importance_weights_are_the_mixture_of_inverse_alpha_and_uniform():
    """``(1 - u) * (1/alpha) / sum(1/alpha) + u / n``, alpha clamped at 1e-12 (a zero alpha takes all the inverse
    share)."""
    alpha = torch.tensor([0.1, 0.2, 0.4, 0.5], dtype=torch.float64)
    inv = torch.tensor([10.0, 5.0, 2.5, 2.0], dtype=torch.float64)
    expected = 0.7 * inv / 19.5 + 0.3 / 4
    torch.testing.assert_close(image_task.importance_weights(alpha, 0.3), expected, rtol=1e-14, atol=0)
    assert float(image_task.importance_weights(alpha, 0.3).sum()) == pytest.approx(1.0, rel=1e-14)
    zero = image_task.importance_weights(torch.tensor([0.0, 0.5], dtype=torch.float64), 0.2)
    torch.testing.assert_close(zero, torch.tensor([0.8 * 1e12 / (1e12 + 2) + 0.1, 0.8 * 2 / (1e12 + 2) + 0.1],
                                                  dtype=torch.float64), rtol=1e-14, atol=0)


def test_draw_pixels_is_inverse_cdf_sampling_of_the_cdfs_total_that_skips_zero_weight_pixels():
    """``u = rand * cdf[-1]`` (a total that is not 1), pixel ``i`` drawn for ``u`` in ``[cdf[i-1], cdf[i])``: a
    pixel of zero weight (cdf[2] = cdf[1]) is never drawn, even for a ``u`` exactly at its edge (here the first
    draw, put there); the last pixel is drawn."""
    r = torch.rand(64, generator=torch.Generator().manual_seed(7), dtype=torch.float64)
    cdf = torch.tensor([r[0] / 2, r[0], r[0], 0.9, 1.0], dtype=torch.float64) * 3.0
    idx = image_task.draw_pixels(cdf, 64, torch.Generator().manual_seed(7))
    expected = draws(cdf, r * 3.0)
    assert expected[0] == 3 and (expected == 4).any() and not (expected == 2).any()
    assert torch.equal(idx, expected)


def test_a_draw_of_exactly_the_cdfs_total_is_the_last_pixel(monkeypatch):
    """torch's CPU ``rand`` is below 1 (and below 1 no product rounds up to the total), but a generator whose range
    includes 1 (curand's uniform is (0, 1]) puts ``u`` at ``cdf[-1]``, where ``searchsorted`` answers ``len(cdf)``,
    one past the last pixel: the clamp makes it the last pixel. The stand-in ``rand`` returns exactly 1."""
    monkeypatch.setattr(image_task.torch, "rand", lambda n, **kw: torch.ones(n, dtype=kw["dtype"], device=kw["device"]))
    cdf = torch.tensor([0.25, 0.5, 1.5], dtype=torch.float64)
    assert image_task.draw_pixels(cdf, 4, torch.Generator()).tolist() == [2, 2, 2, 2]


def test_phase_2_draws_pixels_from_the_frozen_maps_inverse_alpha_mixture():
    """At phase 2 the pixel CDF is the cumulative ``importance_weights`` of the map's alpha at every pixel centre
    (computed here from the map's values); the step then reads ``positions[idx]`` (SP is off) for ``idx`` drawn
    by inverse CDF from the batch generator after step 0's ``randint``."""
    n, batch = H * W, 20
    trainer = adaptive(batch=batch, seed=4, importance_sampling=True, importance_uniform=0.3).setup(picture())
    trainer.step()  # phase 1: randint(n, (batch,)) from the batch generator
    assert trainer._pixel_cdf is None
    values = 0.01 + 0.2 * torch.rand(3, 4, generator=torch.Generator().manual_seed(2))
    trainer.sp.alpha_grid.set_values(values)
    trainer.field = Recorder(trainer.field)
    trainer.step()
    a = alpha_at(values, pixel_centres())
    weights = 0.7 * (1 / a) / (1 / a).sum() + 0.3 / n
    torch.testing.assert_close(trainer._pixel_cdf, weights.cumsum(0), rtol=1e-5, atol=0)
    g = torch.Generator().manual_seed(4)
    torch.randint(n, (batch,), generator=g)
    idx = draws(trainer._pixel_cdf, torch.rand(batch, generator=g, dtype=torch.float64) * trainer._pixel_cdf[-1])
    (read,) = trainer.field.inputs
    assert torch.equal(read, pixel_centres()[idx])
    assert len(set(idx.tolist())) > 1


def masked_rgb(trainer, p: torch.Tensor, alpha: torch.Tensor, lo: float, hi: float, min_levels: float) -> torch.Tensor:
    """The field with level masking, from its parts: levels ``L - t (L - m)`` with ``t`` the clamped position of
    log alpha between log lo and log hi, level ``l`` weighted ``clamp(levels - l, 0, 1)`` (coarsest first, 2
    features each), then the MLP and a sigmoid. The hash grid reads [0, 1]^2 as given."""
    levels_n = GRID.levels
    t = ((alpha.log() - math.log(lo)) / (math.log(hi) - math.log(lo))).clamp(0.0, 1.0)
    levels = levels_n - t * (levels_n - min_levels)
    weights = (levels[:, None] - torch.arange(levels_n, dtype=torch.float64)).clamp(0.0, 1.0).repeat_interleave(2, dim=1)
    grid = trainer.field.encoding.encoding
    with torch.no_grad():
        feats = grid(p) * weights.float()
        return torch.sigmoid(trainer.field.mlp(feats)).double()


def quantile(values: torch.Tensor, q: float) -> float:
    """Linear interpolation between order statistics (torch's and numpy's default)."""
    v = sorted(values.reshape(-1).double().tolist())
    pos = q * (len(v) - 1)
    i = min(int(math.floor(pos)), len(v) - 2)
    return v[i] + (pos - i) * (v[i + 1] - v[i])


def test_phase_2_masks_levels_per_pixel_from_the_maps_quantiles_and_render_uses_the_mask():
    """At phase 2 the map's ``level_mask_quantiles`` (0.3, 0.7) give its low and high ends; each query then uses all
    3 levels at alpha <= low, 1.5 at alpha >= high, log-linear between: ``render`` equals the field built here
    from its parts with that mask, at every pixel (some pixels at each end, some between)."""
    config = adaptive(level_masking=True, level_mask_min_levels=1.5, level_mask_quantiles=(0.3, 0.7))
    trainer = config.setup(picture())
    trainer.step()
    values = torch.tensor([[0.01, 0.02, 0.04, 0.08], [0.16, 0.32, 0.64, 0.05], [0.03, 0.5, 0.015, 0.2]])
    trainer.sp.alpha_grid.set_values(values)
    trainer.step()
    float_values = trainer.sp.alpha_grid.values()
    lo, hi = quantile(float_values, 0.3), quantile(float_values, 0.7)
    assert trainer.level_mask_alpha_range == pytest.approx((lo, hi), rel=1e-6)
    with torch.no_grad():  # features of order 1 (not the initial 1e-4): the mask's effect well above float error
        table = trainer.field.encoding.encoding.table
        table.copy_(torch.rand(table.shape, generator=torch.Generator().manual_seed(3)) * 2 - 1)
    p = pixel_centres()
    a = alpha_at(values, p)
    assert (a <= lo).any() and (a >= hi).any() and ((a > lo) & (a < hi)).any()
    expected = masked_rgb(trainer, p, a, lo, hi, 1.5)
    torch.testing.assert_close(torch.from_numpy(trainer.render()).double(), expected.reshape(H, W, 3), rtol=1e-5, atol=1e-6)
    with torch.no_grad():
        plain = torch.sigmoid(trainer.field.mlp(trainer.field.encoding.encoding(p))).double()
    assert (plain - expected).abs().max() > 0.01  # the mask changes what is rendered


def test_a_constant_map_gives_a_level_range_just_above_its_value():
    """All quantiles of a constant map are its value: the high end is put a relative 1e-6 above the low one (a
    span for the log-linear levels)."""
    trainer = adaptive(level_masking=True, level_mask_min_levels=1.5).setup(picture())
    trainer.step()
    trainer.sp.alpha_grid.set_values(torch.full((3, 4), 0.03))
    trainer.step()
    a = float(trainer.sp.alpha_grid.values()[0, 0])
    assert trainer.level_mask_alpha_range == (a, a * (1 + 1e-6))


def test_a_resumed_fit_restarts_phase_2_at_its_saved_step_on_the_saved_map():
    """A state saved in phase 2 (started at step 1, saved at step 2) loads into a fresh trainer with phase 2 at
    step 1, the map frozen and the same pixel CDF; a state saved before phase 2 loads without it."""
    config = adaptive(importance_sampling=True, batch=20)
    trainer = config.setup(picture())
    trainer.step()
    before = trainer.state_dict()
    trainer.step()
    trainer.step()
    during = trainer.state_dict()
    assert (during["step"], during["phase2_step"]) == (3, 1)
    resumed = config.setup(picture())
    resumed.load_state_dict(during)
    assert (resumed.step_index, resumed.phase2_step) == (3, 1)
    assert not resumed.sp.alpha_grid.param.requires_grad
    assert torch.equal(resumed._pixel_cdf, trainer._pixel_cdf)
    early = config.setup(picture())
    early.load_state_dict(before)
    assert (early.step_index, early.phase2_step, early._pixel_cdf) == (1, None, None)
    assert early.sp.alpha_grid.param.requires_grad


def test_render_is_the_plain_field_at_every_pixel_in_chunks_and_psnr_compares_it_with_the_image():
    """``render`` (any chunk size) is ``sigmoid(field)`` at the pixel centres as an [H, W, 3] array, the field left in
    training mode; ``psnr()`` is ``-10 log10(mse)`` of it against the image."""
    trainer = tiny().setup(picture())
    with torch.no_grad():
        expected = torch.sigmoid(trainer.field(pixel_centres())).reshape(H, W, 3).numpy()
    for chunk in (5, 48, 65536):
        np.testing.assert_allclose(trainer.render(chunk=chunk) if chunk != 65536 else trainer.render(), expected,
                                   rtol=0, atol=1e-6)  # the matmul's rounding may depend on the chunk's size
    assert trainer.field.training
    mse = float(np.mean((expected.astype(np.float64) - picture().astype(np.float64)) ** 2))
    assert trainer.psnr() == pytest.approx(-10.0 * math.log10(mse), rel=1e-6)


def test_psnr_is_minus_ten_log10_of_the_mean_squared_error_and_infinite_for_equal_images():
    """Squared differences 0.01 and 0.04, mean 0.025."""
    assert image_task.psnr(np.array([0.0, 0.5]), np.array([0.1, 0.3])) == pytest.approx(-10.0 * math.log10(0.025), rel=1e-12)
    assert image_task.psnr(np.full((2, 2, 3), 0.25, np.float32), np.full((2, 2, 3), 0.5, np.float32)) == pytest.approx(
        -10.0 * math.log10(0.0625), rel=1e-12)
    assert image_task.psnr(picture(), picture()) == float("inf")


def test_save_image_rounds_to_the_nearest_8_bit_value_and_clips(tmp_path):
    """``[0, 1]`` -> round(255 v) (0.5 -> 127.5 -> 128, 0.1 -> 25.5 -> 26, 0.2 -> 51), values outside clipped to 0 and
    255; the path written is returned."""
    from PIL import Image

    rgb = np.array([[[0.0, 1.0, 0.5], [0.1, 0.2, -0.3]], [[1.7, 0.25, 0.75], [2.0, -1.0, 0.004]]], dtype=np.float32)
    path = image_task.save_image(rgb, str(tmp_path / "out.png"))
    assert path == tmp_path / "out.png"
    with Image.open(path) as im:
        assert np.asarray(im).tolist() == [[[0, 255, 128], [26, 51, 0]], [[255, 64, 191], [255, 0, 1]]]


def test_a_diverged_fit_stops_in_one_line_naming_lr_and_with_the_map_its_lr():
    """An absurd lr: the README's one line for a diverged ``sp-fit``, plus ``or --alpha-map-lr`` with the map
    (only then)."""
    for config, tail in ((tiny(lr=1e30, steps=6), ""), (adaptive(lr=1e30, steps=6), " or --alpha-map-lr")):
        trainer = config.setup(picture())
        with pytest.raises(FloatingPointError) as stopped:
            trainer.fit()
        assert re.fullmatch(r"step [1-5]: the loss became (nan|inf); the fit diverged: lower --lr \(now 1e\+30, e\.g\. "
                            r"10x smaller\)" + re.escape(tail), str(stopped.value)), str(stopped.value)


def test_fit_runs_the_remaining_steps_quietly_calling_back_after_each(capfd):
    """``fit`` runs the remaining steps without printing anything, calling back after each step."""
    trainer = tiny(steps=3).setup(picture())
    trainer.step()
    seen = []
    trainer.fit(lambda t, record: seen.append((t.step_index, record["loss"])))
    assert [s for s, _ in seen] == [2, 3] and trainer.done
    assert capfd.readouterr() == ("", "")


@pytest.mark.parametrize("size", [(3, 1), (1, 3)])
def test_an_image_one_pixel_wide_or_high_is_refused_naming_its_size(tmp_path, size):
    """3x1 and 1x3 (width x height): refused, as 1x1 is; 2x3 and 3x2 accepted."""
    from PIL import Image

    Image.new("RGB", size, (10, 20, 30)).save(tmp_path / "thin.png")
    with pytest.raises(ValueError) as refused:
        image_task.load_image(tmp_path / "thin.png")
    assert str(refused.value) == f"{tmp_path / 'thin.png'}: the image is {size[0]}x{size[1]}; need at least 2x2 pixels"
    wider = tuple(3 if side == 1 else 2 for side in size)  # 2x3 or 3x2: accepted
    Image.new("RGB", wider, (10, 20, 30)).save(tmp_path / "two.png")
    assert image_task.load_image(tmp_path / "two.png").shape == (wider[1], wider[0], 3)


@pytest.mark.filterwarnings("ignore:IM image format is deprecated:DeprecationWarning")  # Pillow 13; gone in Pillow 15
@pytest.mark.parametrize("name, fmt", [("i32.tif", "TIFF"), ("i32.im", "IM")])
def test_a_32_bit_integer_image_is_refused_even_with_16_bit_values(tmp_path, name, fmt):
    """PIL's mode ``I`` is 16-bit grey only when read from a PNG; from a TIFF or PIL's own IM format (which sorts before
    "PNG") it is 32-bit integers, refused whatever its values."""
    from PIL import Image

    if fmt not in Image.registered_extensions().values():
        pytest.skip(f"this Pillow has no {fmt} format")
    Image.fromarray(np.array([[5, 1000], [0, 65535]], dtype=np.int32), "I").save(tmp_path / name)
    with pytest.raises(ValueError) as refused:
        image_task.load_image(tmp_path / name)
    assert str(refused.value) == f"{tmp_path / name}: a I image ({fmt}); expected 8- or 16-bit grey, palette, RGB or RGBA"


def test_without_opencv_a_16_bit_colour_png_is_read_to_its_high_byte_with_a_warning_at_the_caller(tmp_path, monkeypatch):
    """No OpenCV (``import cv2`` fails): a 16-bit RGB or RGBA PNG is read to 1/255, its high byte, alpha composited on
    white (transparent: white), with a warning attributed to the caller of ``load_image``."""
    from tests.tasks.test_image_modes import write_png16

    monkeypatch.setitem(sys.modules, "cv2", None)
    rgb16 = np.array([[[65535, 0, 30000], [1000, 1001, 40000]], [[12345, 54321, 256], [0, 0, 0]]], dtype=np.uint16)
    high = (rgb16 >> 8) / 255.0
    for name, pixels, expected in (
        ("rgb.png", rgb16, high),
        ("rgba.png", np.concatenate([rgb16, np.array([[65535, 0], [65535, 65535]], np.uint16)[..., None]], axis=2),
         np.where(np.array([[1, 0], [1, 1]], bool)[..., None], high, 1.0)),
    ):
        path = write_png16(tmp_path / name, pixels)
        with pytest.warns(UserWarning) as caught:
            rgb = image_task.load_image(path)
        (warning,) = caught
        assert str(warning.message) == (f"{path}: a 16-bit colour PNG, read to 1/255 (its high byte): install "
                                        "opencv-python-headless to read all 16 bits")
        assert warning.filename == __file__
        np.testing.assert_allclose(rgb, expected, rtol=0, atol=1e-7)


def test_a_16_bit_grey_and_alpha_png_loads_all_16_bits(tmp_path):
    """A 16-bit grey + alpha PNG (colour type 4) was read by PIL to its high byte (1000 and 1001 both 3/255), without
    the warning the 16-bit colour PNGs get; it is read with OpenCV as they are: grey replicated, alpha composited on
    white."""
    from tests.tasks.test_image_modes import write_png16

    grey = np.array([[1000, 1001], [30000, 65535]], dtype=np.uint16)
    alpha = np.array([[65535, 65535], [0, 32768]], dtype=np.uint16)
    rgb = image_task.load_image(write_png16(tmp_path / "la.png", np.stack([grey, alpha], axis=2)))
    a = alpha / 65535.0
    np.testing.assert_allclose(rgb, np.repeat((grey / 65535.0 * a + (1 - a))[..., None], 3, axis=2), rtol=0, atol=1e-6)
    assert rgb[0, 1, 0] > rgb[0, 0, 0]


def test_a_truncated_png_is_refused_in_one_line_naming_the_file(tmp_path):
    """A PNG cut short opens but fails to load with a plain OSError (not PIL's UnidentifiedImageError, which the
    bytes of a non-image raise): both are the one line."""
    from PIL import Image

    Image.fromarray(np.random.default_rng(0).integers(0, 256, (32, 32, 3), dtype=np.uint8)).save(tmp_path / "full.png")
    data = (tmp_path / "full.png").read_bytes()
    (tmp_path / "cut.png").write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError) as refused:
        image_task.load_image(tmp_path / "cut.png")
    assert re.fullmatch(re.escape(f"{tmp_path / 'cut.png'}: cannot be read as an image (") + r".+\)", str(refused.value))


@pytest.mark.parametrize("mode, colour, other", [("RGB", (10, 20, 30), (1, 2, 3)), ("L", 10, 1)])
def test_a_transparent_colour_key_of_an_rgb_or_grey_png_is_white(tmp_path, mode, colour, other):
    """An RGB or grey PNG with a transparent colour (tRNS, ``im.info["transparency"]``; not a mode with alpha): that
    colour's pixels are composited on white, the others kept."""
    from PIL import Image

    im = Image.new(mode, (2, 2), colour)
    im.putpixel((1, 0), other)
    im.save(tmp_path / "key.png", transparency=colour)
    rgb = image_task.load_image(tmp_path / "key.png")
    other_rgb = np.array(other if mode == "RGB" else (other,) * 3) / 255.0
    expected = np.ones((2, 2, 3))
    expected[0, 1] = other_rgb
    np.testing.assert_allclose(rgb, expected, rtol=0, atol=1e-7)


# (colour, alpha) of 8-bit pixels where alpha compositing on white (exact value c a / 255 + 255 (1 - a / 255)) gives a
# value 0.66-0.69 from the nearest level when the background's own alpha is 254 instead of 255 (PIL's compositing is
# otherwise within 0.5 of the exact value everywhere: checked over all 256 x 256 pairs).
PARTIAL = [(3, 56), (6, 72), (9, 76)]


def on_white(colour, alpha) -> float:
    return (colour * alpha / 255 + 255 * (1 - alpha / 255)) / 255


def test_partly_transparent_pixels_are_composited_on_an_opaque_white(tmp_path, monkeypatch):
    """8-bit RGBA, and a 16-bit RGBA PNG read without OpenCV (its high bytes): each partly transparent pixel is within
    half a level of ``c a + 1 - a`` on white."""
    from PIL import Image

    from tests.tasks.test_image_modes import write_png16

    pixels = np.array([[[c, c, c, a] for c, a in PARTIAL]], dtype=np.uint8)
    expected = np.array([[[on_white(c, a)] * 3 for c, a in PARTIAL]])
    Image.fromarray(pixels, "RGBA").save(tmp_path / "rgba8.png")
    Image.fromarray(np.concatenate([pixels, pixels]), "RGBA").save(tmp_path / "rgba8.png")  # 2 rows: at least 2x2
    np.testing.assert_allclose(image_task.load_image(tmp_path / "rgba8.png"), np.concatenate([expected, expected]),
                               rtol=0, atol=0.5 / 255)
    monkeypatch.setitem(sys.modules, "cv2", None)
    sixteen = np.concatenate([pixels, pixels]).astype(np.uint16) * 256 + 17  # high bytes as above
    with pytest.warns(UserWarning):
        rgb = image_task.load_image(write_png16(tmp_path / "rgba16.png", sixteen))
    np.testing.assert_allclose(rgb, np.concatenate([expected, expected]), rtol=0, atol=0.5 / 255)
