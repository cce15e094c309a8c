"""The settings every ``sp-fit`` task shares (sp_plugins.tasks.settings), exactly: each default is the one
README and bench/RESULTS.md describe (2000 Adam steps at lr 1e-3, seed 0, a 64 x 64 MLP; objects of
diagonal 1.9 in [-1, 1]^3, meshed on 192^3 with 4 bisections, measured on 200k points at F-score 1%), and
the task configs inherit them. Each test names the mutants it kills (``bench/mutation_study.py``
``sp_plugins/tasks/settings.py``)."""

from __future__ import annotations

from dataclasses import fields

from sp_plugins.tasks.settings import FitSettings, MeshedFitSettings


def test_every_fit_defaults_to_2000_steps_seed_0_lr_1e_3_and_a_64_by_64_mlp():
    """Kills: steps 2000 -> 2001 / 1999, seed 0 -> 1 / -1, lr 1e-3 -> 1.001 / -0.999, either hidden
    width 64 -> 65 / 63."""
    s = FitSettings()
    assert (s.steps, s.seed, s.lr, s.hidden) == (2000, 0, 0.001, (64, 64))
    assert [f.name for f in fields(FitSettings)] == ["steps", "seed", "lr", "hidden"]


def test_a_meshed_fit_adds_the_frame_the_meshing_and_the_metrics():
    """Kills: frame_diagonal 1.9 -> 2.9 / 0.9, mesh_resolution 192 -> 193 / 191, refine 4 -> 5 / 3,
    metric_points 200_000 -> 200_001 / 199_999, fscore_threshold 0.01 -> 1.01 / -0.99 (and the shared
    defaults, inherited)."""
    m = MeshedFitSettings()
    assert (m.steps, m.seed, m.lr, m.hidden) == (2000, 0, 0.001, (64, 64))
    assert (m.frame_diagonal, m.mesh_resolution, m.refine, m.metric_points, m.fscore_threshold) == (1.9, 192, 4, 200_000, 0.01)
    assert isinstance(m, FitSettings)


def test_the_task_configs_keep_the_shared_defaults():
    """The three tasks' configs extend these settings without changing the shared defaults (bench/RESULTS.md's
    tables run them at 2000 steps, lr 1e-3, seed 0)."""
    from sp_plugins.tasks.image import ImageFitConfig
    from sp_plugins.tasks.pointcloud import PointCloudSDFConfig
    from sp_plugins.tasks.sdf import SDFFitConfig

    for config in (PointCloudSDFConfig(), SDFFitConfig()):
        assert isinstance(config, MeshedFitSettings)
        assert (config.steps, config.seed, config.lr, config.mesh_resolution, config.refine) == (2000, 0, 0.001, 192, 4)
    image = ImageFitConfig()
    assert isinstance(image, FitSettings) and (image.steps, image.seed) == (2000, 0)
