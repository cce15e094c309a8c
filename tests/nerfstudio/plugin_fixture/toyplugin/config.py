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
from toyplugin.blob import ToyBlobModelConfig
from toyplugin.bypass import BypassModelConfig
from toyplugin.download import DownloadModelConfig
from toyplugin.nofield import NoFieldModelConfig
from toyplugin.model import ToyModelConfig
from toyplugin.sdf import ToySDFModelConfig


def _method(name, model_config, description):
    return MethodSpecification(
        config=TrainerConfig(
            method_name=name,
            max_num_iterations=1000,
            mixed_precision=False,
            pipeline=VanillaPipelineConfig(
                datamanager=VanillaDataManagerConfig(dataparser=BlenderDataParserConfig()),
                model=model_config,
            ),
            optimizers={
                "fields": {
                    "optimizer": AdamOptimizerConfig(lr=1e-2),
                    "scheduler": ExponentialDecaySchedulerConfig(lr_final=1e-3, max_steps=1000),
                }
            },
            viewer=ViewerConfig(num_rays_per_chunk=512),
            vis="viewer",  # as nerfstudio's own method configs (TrainerConfig's default is wandb)
        ),
        description=description,
    )


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
        vis="viewer",
    ),
    description="A toy third-party method.",
)

sp_toy_method = with_sp(toy_method, name="sp-toy-method")

toy_sdf = _method("toy-sdf", ToySDFModelConfig(eval_num_rays_per_chunk=512), "A toy SDF method (start positions, eikonal).")
toy_blob = _method("toy-blob", ToyBlobModelConfig(eval_num_rays_per_chunk=512), "A toy Gaussian-blob method.")
toy_bypass = _method("toy-bypass", BypassModelConfig(eval_num_rays_per_chunk=512), "A toy method whose field reads metadata positions.")
toy_download = _method("toy-download", DownloadModelConfig(eval_num_rays_per_chunk=512), "A toy method that downloads weights while its model is built.")
toy_nofield = _method("toy-nofield", NoFieldModelConfig(eval_num_rays_per_chunk=512), "A toy method with no field.")
