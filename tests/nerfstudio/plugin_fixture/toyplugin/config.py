"""The plugin's method, and its SP variant registered with one call to ``with_sp``."""

from nerfstudio.configs.base_config import ViewerConfig
from nerfstudio.data.datamanagers.base_datamanager import VanillaDataManagerConfig
from nerfstudio.data.dataparsers.blender_dataparser import BlenderDataParserConfig
from nerfstudio.engine.optimizers import AdamOptimizerConfig
from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig
from nerfstudio.engine.trainer import TrainerConfig
from nerfstudio.pipelines.base_pipeline import VanillaPipelineConfig
from nerfstudio.plugins.types import MethodSpecification

from sp_plugins.nerfstudio import with_sp
from toyplugin.model import ToyModelConfig

toy_method = MethodSpecification(
    config=TrainerConfig(
        method_name="toy-method",
        max_num_iterations=1000,
        mixed_precision=False,
        pipeline=VanillaPipelineConfig(
            datamanager=VanillaDataManagerConfig(dataparser=BlenderDataParserConfig()),
            model=ToyModelConfig(eval_num_rays_per_chunk=512),
        ),
        optimizers={
            "fields": {
                "optimizer": AdamOptimizerConfig(lr=1e-2),
                "scheduler": ExponentialDecaySchedulerConfig(lr_final=1e-3, max_steps=1000),
            }
        },
        viewer=ViewerConfig(num_rays_per_chunk=512),
    ),
    description="A toy third-party method.",
)

sp_toy_method = with_sp(toy_method, name="sp-toy-method")
