"""nerfbaselines front end: our nerfstudio methods as nerfbaselines method specs.

nerfbaselines (1.2.12) drives nerfstudio's own trainer in its ``python`` backend, so SP reaches it
through the nerfstudio seam unchanged; this package only says which methods exist
(:mod:`~sp_plugins.nerfbaselines.specs`, the ``nerfbaselines.specs`` entry point), and mends what
nerfbaselines' nerfstudio wrapper gets wrong for our methods (:mod:`~sp_plugins.nerfbaselines.method`):
``--set`` values typed to their field (:mod:`~sp_plugins.nerfbaselines.overrides`), the dataset's scene
box (:mod:`~sp_plugins.nerfbaselines.scene_box`), ``rgb_fine`` outputs, LPIPS offline (the registry's
``nerfbaselines_lpips`` patch), and checks that a run does what its id promises about SP
(:mod:`~sp_plugins.nerfbaselines.sp_state`). :mod:`~sp_plugins.nerfbaselines.sdfstudio_loader` loads our
SDFStudio layout, :mod:`~sp_plugins.nerfbaselines.blender_loader` a Blender-format folder of your own.
Importing this package imports neither host.
"""
