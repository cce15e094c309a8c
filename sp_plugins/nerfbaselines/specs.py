"""The method, dataset and loader specs nerfbaselines finds through its ``nerfbaselines.specs``
entry point (pyproject.toml). Plain dicts: importing this module imports no host and changes
nothing but nerfbaselines' registry, which is what nerfbaselines imports it for.

Three kinds of method ids, one wrapper class (:class:`sp_plugins.nerfbaselines.method.SPNerfStudio`):

- our nerfstudio methods, under their ``ns-train`` names (``sp-nerfacto`` ...), and the baselines
  nerfbaselines lacks (``mipnerf``, ``vanilla-nerf``, ``neus-hashgrid`` ...);
- ``<id>+sp``: SP on a nerfstudio-backed method of nerfbaselines or of this list (``nerfacto+sp``,
  ``mipnerf+sp``, ``vanilla-nerf+sp``): the very config of ``<id>`` through ``with_sp``, with
  ``<id>``'s presets, so ``<id>`` against ``<id>+sp`` is a like-for-like table row;
- ``<id>+sp-off``: the same with SP switched off, the baseline row where ``<id>`` itself cannot be run
  at the settings you need (nerfbaselines' own ``nerfacto`` sets ``--set`` values as strings, so
  ``--set max_num_iterations=400`` or a smaller hash grid breaks it: no CPU budget from the command line).
"""

from __future__ import annotations

from typing import Dict, NamedTuple

from sp_plugins.nerfbaselines.blender_loader import LAYOUT, LAYOUT_KEY  # (json and os: the module imports no host)
from sp_plugins.nerfbaselines import table as nb_table  # the method names and presets of these specs
from sp_plugins.nerfstudio import table  # our method names (torch, no host)

WRAPPER = "sp_plugins.nerfbaselines.method:SPNerfStudio"
SP_SUFFIX = "+sp"
SP_OFF_SUFFIX = "+sp-off"
SP_SCENE = "sp-scene"
"""The dataset id of ``sp-scene`` folders (their ``nb-info.json`` names it and the Blender loader)."""


class Entry(NamedTuple):
    nerfstudio_name: str
    """The method in nerfstudio's ``all_methods`` (ns-train's name)."""
    add_sp: bool = False
    """Put SP on it with ``with_sp`` (the ``+sp`` ids)."""
    sdf: bool = False
    sp_off: bool = False
    """``with_sp``, then SP switched off (the ``+sp-off`` ids)."""


OURS = tuple(m for m in table.OUR_METHODS if m not in table.SP_OFF_METHODS)
"""Our radiance-field methods (the nerfstudio table's), less those that are no SP method's baseline
(freenerf-lite): a table row here is SP against its baseline."""
OURS_SDF = table.OUR_SDF_METHODS
NERFSTUDIO_BASELINES = nb_table.NERFSTUDIO_BASELINES
SP_ON = nb_table.SP_ON

ENTRIES: Dict[str, Entry] = {
    **{name: Entry(name) for name in OURS + NERFSTUDIO_BASELINES},
    **{name: Entry(name, sdf=True) for name in OURS_SDF},
    **{name + SP_SUFFIX: Entry(name, add_sp=True) for name in SP_ON},
    **{name + SP_OFF_SUFFIX: Entry(name, add_sp=True, sp_off=True) for name in SP_ON},
}

# the Blender layout sp-scene writes: the world as the files give it (as `ns-train ... blender-data`)
_SP_SCENE_PRESET = {
    "@apply": [{"dataset": SP_SCENE}],
    "@description": "sp-scene folders: nerfstudio's blender-data parser (poses as given, white background).",
    "pipeline.datamanager.dataparser": "blender-data",
}
_NERFACTO_BLENDER = {  # nerfbaselines' own blender preset of nerfacto (less its @apply), for the same kind of scene
    "pipeline.datamanager.dataparser": "blender-data",
    "pipeline.model.near_plane": 2.0, "pipeline.model.far_plane": 6.0, "pipeline.model.use_appearance_embedding": False,
    "pipeline.model.background_color": "white", "pipeline.model.proposal_initial_sampler": "uniform",
    "pipeline.model.distortion_loss_mult": 0.0, "pipeline.model.disable_scene_contraction": True,
    "pipeline.model.average_init_density": 1.0, "pipeline.model.camera_optimizer.mode": "off",
}
_NERFACTO_SP_SCENE = {**_SP_SCENE_PRESET, **_NERFACTO_BLENDER}
BLENDER_LAYOUT = "blender-layout"
"""The loader of a Blender-format folder of your own (:mod:`~sp_plugins.nerfbaselines.blender_loader`),
and the preset every method of ours applies to what it loads."""
_BLENDER_LAYOUT_PRESET = {  # what `ns-train <method> blender-data --data DIR` trains with
    "@apply": [{LAYOUT_KEY: LAYOUT}],
    "@description": "A Blender-format folder (our blender-layout loader): nerfstudio's blender-data parser (poses as "
                    "given, white background), as ns-train ... blender-data --data DIR.",
    "pipeline.datamanager.dataparser": "blender-data",
}


def method_spec(method_id: str) -> dict:
    entry = ENTRIES[method_id]
    kind = ("SP off (baseline of +sp), " if entry.sp_off else "SP on ") if entry.add_sp else ""
    nerfacto = entry.nerfstudio_name in nb_table.NERFACTO_FAMILY
    presets: Dict[str, dict] = {SP_SCENE: _NERFACTO_SP_SCENE if nerfacto else _SP_SCENE_PRESET,
                                 BLENDER_LAYOUT: _BLENDER_LAYOUT_PRESET}
    sizes = nb_table.SIZE_PRESETS.get(entry.nerfstudio_name) if entry.add_sp else None
    if sizes:  # nerfbaselines' own presets of the method, under its +sp id
        presets["blender"] = {"@apply": [{"dataset": "blender"}], **_NERFACTO_BLENDER}
        presets.update({name: {"method": method} for name, method in sizes.items()})
    return {
        "id": method_id,
        "method_class": WRAPPER,
        "backends_order": ["python"],
        "presets": presets,
        "metadata": {
            "name": method_id,
            "description": f"{kind}nerfstudio's `{entry.nerfstudio_name}` (sp-plugins); python backend, in the "
                           "environment where nerfstudio 1.1.5 and sp-plugins are installed.",
            "link": "https://github.com/",
        },
        "implementation_status": {},
        # what nerfbaselines' NerfStudio.get_method_info says; the results tooling reads it from the spec
        "required_features": ["color"],
        "supported_camera_models": ["pinhole", "opencv", "opencv_fisheye"],
        "supported_outputs": ["color", "depth", "accumulation"],
    }


def _register() -> None:
    from nerfbaselines import register

    for method_id in ENTRIES:
        register(method_spec(method_id))
    register({
        "id": "sdfstudio-layout",
        "load_dataset_function": "sp_plugins.nerfbaselines.sdfstudio_loader:load_sdfstudio_dataset",
    })
    register({
        "id": BLENDER_LAYOUT,
        "load_dataset_function": "sp_plugins.nerfbaselines.blender_loader:load_blender_folder",
    })
    register({"id": SP_SCENE, "evaluation_protocol_class": "sp_plugins.nerfbaselines.protocol:SceneProtocol"})
    register({
        "id": SP_SCENE,
        "download_dataset_function": "sp_plugins.nerfbaselines.sdfstudio_loader:refuse_download",
        "evaluation_protocol": SP_SCENE,
        "metadata": {
            "id": SP_SCENE, "name": "sp-scene", "description": "Synthetic scenes rendered by sp-plugins' sp-scene.",
            "metrics": ["psnr", "ssim", "lpips"], "default_metric": "psnr", "scenes": [],
        },
    })


_register()
