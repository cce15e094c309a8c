"""``sp-scene MESH OUT``: render a mesh into a small multi-view dataset for nerfstudio.

MESH is a mesh file trimesh reads, ``spot`` (the bundled model) or a primitive (``sphere``,
``box``, ``torus``, ``capsule``). OUT receives ``blender/`` (for ``blender-data``),
``sdfstudio/`` (for ``sdfstudio-data``), ``gt_mesh.ply`` and ``scene.json``.

``--dtu-like``: the object stands on a textured ground inside a textured backdrop, seen by 49
cameras on a frontal cap, opaque 96x72 images without training masks (as DTU), and an
``object_mask/`` beside each layout's images for metrics.
"""

from __future__ import annotations

import argparse
import math
import sys
from typing import List, Optional, Tuple, Union

from sp_plugins.data.dtu_like import CapCameras
from sp_plugins.data.scene import LAYOUTS, make_scene

DTU_VIEWS = 49
"""DTU's smaller camera set (its full set has 64)."""


def _resolution(text: str) -> Union[int, Tuple[int, int]]:
    try:
        if "x" in text.lower():
            width, height = text.lower().split("x")
            return int(width), int(height)
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"resolution must be N or WxH (e.g. 64 or 96x64), got {text!r}") from None


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="sp-scene",
        description="Render a mesh into a small multi-view dataset (Blender and SDFStudio layouts) with its true mesh.",
    )
    parser.add_argument("mesh", help="mesh file, 'spot' (bundled), or a primitive: sphere, box, torus, capsule")
    parser.add_argument("out", help="output directory")
    parser.add_argument("--views", type=int, default=None, help="training views (default: 24, or 49 with --dtu-like)")
    parser.add_argument("--val-views", type=int, default=4, help="validation views (default: 4)")
    parser.add_argument("--test-views", type=int, default=4, help="test views (default: 4)")
    parser.add_argument("--resolution", type=_resolution, default=None, help="N or WxH pixels (default: 64, or 96x72 with --dtu-like)")
    parser.add_argument("--layouts", nargs="+", choices=LAYOUTS, default=list(LAYOUTS), help="layouts to write (default: both)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the camera positions (default: 0)")
    parser.add_argument("--hemisphere", action="store_true", help="cameras above the horizon only")
    parser.add_argument("--up-axis", choices=("x", "y", "z"), default="z", help="mesh axis that points up (default: z)")
    parser.add_argument("--radius", type=float, default=0.85, help="radius of the sphere the mesh is scaled into (default: 0.85)")
    parser.add_argument("--distance", type=float, default=4.0, help="camera distance from the origin (default: 4.0)")
    parser.add_argument("--fov", type=float, default=None, help="horizontal field of view in degrees (default: frames the mesh)")
    parser.add_argument("--supersample", type=int, default=2, help="s: s*s rays per pixel (default: 2)")
    parser.add_argument("--backend", choices=("auto", "embree", "triangle"), default="auto", help="trimesh ray caster")
    parser.add_argument("--overwrite", action="store_true", help="replace a scene already in OUT")
    dtu = parser.add_argument_group("DTU-like scenes")
    dtu.add_argument("--dtu-like", action="store_true",
                     help="textured ground and backdrop, cameras on a frontal cap, opaque images, object masks for metrics")
    dtu.add_argument("--cap-azimuth", type=float, default=None, metavar="DEG",
                     help=f"azimuth span of the camera cap in degrees (default: {CapCameras.azimuth_span:g})")
    dtu.add_argument("--cap-elevation", type=float, nargs=2, default=None, metavar=("LOW", "HIGH"),
                     help="elevation range of the camera cap in degrees (default: %g %g)" % CapCameras.elevation)
    parser.add_argument("--quiet", action="store_true", help="no progress bar or summary")
    return parser


def main(argv: Optional[List[str]] = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    cap = None
    if args.cap_azimuth is not None or args.cap_elevation is not None:
        if not args.dtu_like:
            parser.error("--cap-azimuth / --cap-elevation apply only with --dtu-like")
        defaults = CapCameras()
        try:
            cap = CapCameras(
                azimuth_span=defaults.azimuth_span if args.cap_azimuth is None else args.cap_azimuth,
                elevation=defaults.elevation if args.cap_elevation is None else tuple(args.cap_elevation),
            )
        except ValueError as error:
            parser.error(str(error))
    views = args.views if args.views is not None else (DTU_VIEWS if args.dtu_like else 24)
    try:
        paths = make_scene(
            args.mesh,
            args.out,
            n_train=views,
            n_val=args.val_views,
            n_test=args.test_views,
            resolution=args.resolution,
            layouts=args.layouts,
            seed=args.seed,
            hemisphere=args.hemisphere,
            up_axis=args.up_axis,
            radius=args.radius,
            camera_distance=args.distance,
            fov_x=None if args.fov is None else math.radians(args.fov),
            supersample=args.supersample,
            backend=args.backend,
            overwrite=args.overwrite,
            progress=not args.quiet,
            dtu_like=args.dtu_like,
            cap=cap,
        )
    except ValueError as error:  # includes SceneExistsError
        print(f"sp-scene: error: {error}", file=sys.stderr)
        return 2
    if not args.quiet:
        print(f"wrote {paths.root}: {paths.gt_mesh.name}, {paths.scene_json.name}")
        if paths.blender is not None:
            print(f"  {paths.blender}  (nerfstudio dataparser: blender-data)")
        if paths.sdfstudio is not None:
            print(f"  {paths.sdfstudio}  (nerfstudio dataparser: sdfstudio-data)")
        if args.dtu_like:
            print("  DTU-like: opaque images (no training masks); object masks for metrics in each layout's object_mask/")
    return 0


if __name__ == "__main__":
    sys.exit(main())
