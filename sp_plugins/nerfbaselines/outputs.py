"""Output names: nerfbaselines' nerfstudio wrapper reads a model's ``rgb``, ``accumulation`` and
``depth``; vanilla-nerf and MipNeRF name their final pass ``rgb_fine`` (and ``accumulation_fine``,
``depth_fine``), so under nerfbaselines they had no image to render."""

from __future__ import annotations

from typing import Any

__all__ = ["ALIASES", "with_output_aliases"]

ALIASES = ("rgb", "accumulation", "depth")


def with_output_aliases(model_cls: type) -> type:
    """``model_cls`` whose camera outputs also carry ``rgb`` / ``accumulation`` / ``depth`` where the
    model only names them ``*_fine`` (nerfbaselines reads the plain names)."""

    class Aliased(model_cls):  # type: ignore[misc, valid-type]
        def get_outputs_for_camera_ray_bundle(self, *args: Any, **kwargs: Any):
            outputs = super().get_outputs_for_camera_ray_bundle(*args, **kwargs)
            for name in ALIASES:
                if name not in outputs and f"{name}_fine" in outputs:
                    outputs[name] = outputs[f"{name}_fine"]
            return outputs

    Aliased.__name__ = Aliased.__qualname__ = model_cls.__name__
    return Aliased
