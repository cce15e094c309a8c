"""The lockstep driver for sdfstudio (its own ``nerfstudio`` 0.1.x package; run in ``.venv-sdfstudio``).

:func:`prepare` readies the host once per process (our compatibility patches, sdfstudio's import
order, our methods added); :func:`configure` points one of its method configs at a scene at a
benchmark's size (then ``sp_plugins.adapter.shrink``, which imports no host, shrinks it);
:class:`Run` is its trainer driven step by step.
"""

from __future__ import annotations

import copy
from pathlib import Path

from bench.harness import lockstep, metrics
from bench.harness.lockstep import run_summary, step_stats, time_ratio, train_together  # noqa: F401
from sp_plugins.adapter.shrink import shrink  # noqa: F401


def prepare() -> None:
    from sp_plugins.patches.sdfstudio_import_hook import install_all

    install_all()
    import scripts.train  # noqa: F401  (sdfstudio's import order)

    from sp_plugins.sdfstudio.registration import add_methods

    add_methods()


def configure(name: str, data: Path, out: Path, *, steps: int, seed: int, rays: int, experiment: str, **parser):
    """A copy of sdfstudio's method ``name`` on CPU, reading the SDFStudio layout at ``data`` (``parser``:
    more data parser settings), ``steps`` long, without saves or periodic evaluations."""
    import nerfstudio.configs.method_configs as host
    from nerfstudio.data.dataparsers.sdfstudio_dataparser import SDFStudioDataParserConfig

    config = copy.deepcopy(host.method_configs[name])
    config.machine.num_gpus = 0
    config.machine.seed = seed
    config.vis = "tensorboard"
    config.output_dir = out
    config.experiment_name = experiment
    config.timestamp = "bench"
    config.trainer.max_num_iterations = steps
    config.trainer.steps_per_save = 10**9
    config.trainer.steps_per_eval_batch = config.trainer.steps_per_eval_image = 10**9
    dm = config.pipeline.datamanager
    dm.dataparser = SDFStudioDataParserConfig(data=data, **parser)
    dm.train_num_rays_per_batch = rays
    dm.eval_num_rays_per_batch = 1024
    config.pipeline.model.eval_num_rays_per_chunk = 1024
    if hasattr(config.pipeline.model, "sp"):
        config.pipeline.model.sp.seed = seed
    return config


def _trainer(config):
    from nerfstudio.engine.trainer import Trainer

    trainer = Trainer(config, local_rank=0, world_size=0)
    trainer.setup(test_mode="val")
    return trainer


class Run(lockstep.Run):
    """One sdfstudio trainer (its validation split for evaluation) driven step by step."""

    def __init__(self, name: str, config, seed: int) -> None:
        super().__init__(name, lambda: _trainer(config), seed)

    def evaluate_sdf(self, gt_mesh: Path, resolution: int, mesh_out: Path) -> dict:
        """sdfstudio's own eval PSNR (on the views its parser holds out of training) and the mesh of the
        SDF in [-1, 1]^3 against the true mesh (sdfstudio's parser does not move the world)."""
        import trimesh

        pipeline = self.trainer.pipeline
        pipeline.eval()
        images, _ = pipeline.get_average_eval_image_metrics()  # sdfstudio returns (metrics, images)
        mesh = metrics.sdf_mesh(pipeline.model.field, (-1.0, 1.0), resolution)
        mesh.export(mesh_out)
        return {"psnr_train_views": float(images["psnr"]), **metrics.geometry(mesh, trimesh.load(gt_mesh, force="mesh"), 100_000)}
