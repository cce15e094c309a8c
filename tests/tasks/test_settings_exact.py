"""The settings every ``sp-fit`` task shares (sp_plugins.tasks.settings), exactly: each default is the one
README and docs/results/pointcloud-sdf.md describe (2000 Adam steps at lr 1e-3, seed 0, a 64 x 64 MLP; objects of
diagonal 1.9 in [-1, 1]^3, meshed on 192^3 with 4 bisections, measured on 200k points at F-score 1%), and
the task configs inherit them. The mutants each test kills are listed in
``bench/results/mutation_study/kills.json``."""

from __future__ import annotations

from dataclasses import fields

from sp_plugins.tasks.settings import FitSettings, MeshedFitSettings


def test_every_fit_defaults_to_2000_steps_seed_0_lr_1e_3_and_a_64_by_64_mlp():
    """Every fit defaults to 2000 steps, seed 0, lr 1e-3 and a 64 x 64 MLP, in that order."""
    s = FitSettings()
    assert (s.steps, s.seed, s.lr, s.hidden) == (2000, 0, 0.001, (64, 64))
    assert [f.name for f in fields(FitSettings)] == ["steps", "seed", "lr", "hidden"]


def test_a_meshed_fit_adds_the_frame_the_meshing_and_the_metrics():
    """A meshed fit inherits the shared defaults and adds the frame's diagonal (1.9), the meshing (resolution 192, 4
    bisection steps) and the metrics (200 000 points, F-score at 0.01)."""
    m = MeshedFitSettings()
    assert (m.steps, m.seed, m.lr, m.hidden) == (2000, 0, 0.001, (64, 64))
    assert (m.frame_diagonal, m.mesh_resolution, m.refine, m.metric_points, m.fscore_threshold) == (1.9, 192, 4, 200_000, 0.01)
    assert isinstance(m, FitSettings)


def test_the_task_configs_keep_the_shared_defaults():
    """The three tasks' configs extend these settings without changing the shared defaults (docs/results/pointcloud-sdf.md's
    tables run them at 2000 steps, lr 1e-3, seed 0)."""
    from sp_plugins.tasks.image import ImageFitConfig
    from sp_plugins.tasks.pointcloud import PointCloudSDFConfig
    from sp_plugins.tasks.sdf import SDFFitConfig

    for config in (PointCloudSDFConfig(), SDFFitConfig()):
        assert isinstance(config, MeshedFitSettings)
        assert (config.steps, config.seed, config.lr, config.mesh_resolution, config.refine) == (2000, 0, 0.001, 192, 4)
    image = ImageFitConfig()
    assert isinstance(image, FitSettings) and (image.steps, image.seed) == (2000, 0)
