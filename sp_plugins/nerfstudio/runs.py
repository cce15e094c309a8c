"""Run our nerfstudio methods from Python (tests, benchmarks): the same configs ``ns-train`` uses.

    config = method_config("sp-neus-hashgrid")
    configure_run(config, data=scene / "blender", steps=200, output_dir=tmp)
    shrink(config, num_samples=16, field=dict(hidden_dim=32, max_res=64))   # CPU-sized (optional)
    trainer = train(config)
"""

from __future__ import annotations

import copy
from importlib.metadata import entry_points
from pathlib import Path
from typing import TYPE_CHECKING, Dict, Literal, Optional

from sp_plugins.patches import registry

if TYPE_CHECKING:  # host modules are imported where they are used: shrink() serves sdfstudio's configs too
    from nerfstudio.engine.trainer import Trainer, TrainerConfig
    from nerfstudio.plugins.types import MethodSpecification

ENTRY_POINT_GROUP = "nerfstudio.method_configs"
OUR_MODULES = ("sp_plugins.method_configs.nerfstudio", "sp_plugins.nerfstudio.methods")
"""Where our entry points point: ``method_configs/nerfstudio.py``, or its old home in an environment installed before
it moved (not yet reinstalled)."""


def our_methods() -> Dict[str, MethodSpecification]:
    """Every method sp-plugins registers, by name, loaded from its entry point."""
    specs = {}
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        if ep.value.partition(":")[0] in OUR_MODULES:
            specs[ep.name] = ep.load()
    return specs


def method_config(name: str) -> TrainerConfig:
    """A private copy of method ``name``'s trainer config."""
    specs = our_methods()
    if name not in specs:
        raise ValueError(f"method {name!r} is not an sp-plugins method; known: {', '.join(sorted(specs))}")
    return copy.deepcopy(specs[name].config)


def configure_run(
    config: TrainerConfig,
    data: Path,
    *,
    steps: int,
    output_dir: Path,
    layout: Optional[Literal["blender", "sdfstudio"]] = None,
    device: str = "cpu",
    rays_per_batch: Optional[int] = None,
    experiment_name: Optional[str] = None,
    timestamp: str = "run",
) -> TrainerConfig:
    """Point ``config`` at ``data`` (layout guessed from its files), shorten it to ``steps`` on
    ``device``, without viewer, periodic evals or checkpoints before the last step."""
    from nerfstudio.data.dataparsers.blender_dataparser import BlenderDataParserConfig
    from nerfstudio.data.dataparsers.sdfstudio_dataparser import SDFStudioDataParserConfig

    data = Path(data)
    if layout is None:
        layout = "sdfstudio" if (data / "meta_data.json").is_file() else "blender"
    dm = config.pipeline.datamanager
    dm.dataparser = SDFStudioDataParserConfig(data=data) if layout == "sdfstudio" else BlenderDataParserConfig(data=data)
    dm.data = data
    if rays_per_batch is not None:
        dm.train_num_rays_per_batch = rays_per_batch
        dm.eval_num_rays_per_batch = rays_per_batch
    config.data = data
    config.max_num_iterations = steps
    config.machine.device_type = device  # type: ignore[assignment]
    config.vis = "tensorboard"
    config.output_dir = Path(output_dir)
    config.experiment_name = experiment_name or f"{config.method_name}-{data.name}"
    config.timestamp = timestamp
    config.steps_per_save = steps
    config.steps_per_eval_batch = 10**9
    config.steps_per_eval_image = 10**9
    config.steps_per_eval_all_images = 10**9
    config.save_only_latest_checkpoint = True
    config.logging.local_writer.enable = False
    config.logging.steps_per_log = 10**9
    return config


def train(config: TrainerConfig) -> Trainer:
    """Set up and run the trainer in this process; returns it (pipeline, step, checkpoint dir).

    nerfstudio's event writers are module globals that its trainer adds and never removes: the writers this run
    added are closed and dropped at its end, or the next run trained in the same process would also write its
    scalars into this run's event file (two runs' curves interleaved in one file).

    Seeded as ``ns-train`` seeds (nerfstudio's own ``_set_random_seed`` with ``--machine.seed``) and trained with
    deterministic kernels (``patches/torch_deterministic.py``): the same config gives the same checkpoint, in this
    process or another (torch starts each process with a random seed)."""
    from nerfstudio.scripts.train import _set_random_seed
    from nerfstudio.utils import writer

    config.set_timestamp() if not config.timestamp else None
    config.save_config()
    before = len(writer.EVENT_WRITERS)
    try:
        with registry.scope("torch_deterministic"):
            _set_random_seed(config.machine.seed)
            trainer = config.setup(local_rank=0, world_size=1)
            trainer.setup()
            trainer.train()
    finally:
        for added in writer.EVENT_WRITERS[before:]:
            tb = getattr(added, "tb_writer", None)
            if tb is not None:
                tb.close()
        del writer.EVENT_WRITERS[before:]
    return trainer
