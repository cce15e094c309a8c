"""Fitting tasks outside nerfstudio (the ``sp-fit`` commands), each a config dataclass whose
``setup()`` builds a trainer with ``step()`` / ``fit()`` so that several fits can be interleaved
step by step in one process:

    from sp_plugins.tasks import PointCloudSDFConfig, ImageFitConfig, SDFFitConfig

- :class:`PointCloudSDFConfig`: oriented point cloud -> SDF (SIREN loss).
- :class:`ImageFitConfig`: 2D image fitting, optionally with a learned alpha map.
- :class:`SDFFitConfig`: direct SDF supervision from a mesh (MAPE).
"""

from sp_plugins.tasks.fields import ENCODING_KINDS, EncodingConfig, NeuralField
from sp_plugins.tasks.image import ImageFitConfig, ImageFitTrainer
from sp_plugins.tasks.pointcloud import PointCloudSDFConfig, PointCloudSDFTrainer, siren_sdf_losses
from sp_plugins.tasks.sdf import SDFFitConfig, SDFFitTrainer, signed_distance

__all__ = [
    "ENCODING_KINDS",
    "EncodingConfig",
    "ImageFitConfig",
    "ImageFitTrainer",
    "NeuralField",
    "PointCloudSDFConfig",
    "PointCloudSDFTrainer",
    "SDFFitConfig",
    "SDFFitTrainer",
    "siren_sdf_losses",
    "signed_distance",
]
