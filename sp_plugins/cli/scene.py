"""``sp-scene MESH OUT``: render a mesh into a small multi-view dataset for nerfstudio.

MESH is a mesh file trimesh reads, ``spot`` (the bundled model) or a primitive (``sphere``,
``box``, ``torus``, ``capsule``). OUT receives ``blender/`` (for ``blender-data``),
``sdfstudio/`` (for ``sdfstudio-data``), ``gt_mesh.ply`` and ``scene.json``.
"""

from __future__ import annotations

import argparse
import math
import sys
from typing import List, Optional, Tuple, Union

from sp_plugins.data.scene import LAYOUTS, make_scene


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
    parser.add_argument("--views", type=int, default=24, help="training views (default: 24)")
    parser.add_argument("--val-views", type=int, default=4, help="validation views (default: 4)")
    parser.add_argument("--test-views", type=int, default=4, help="test views (default: 4)")
    parser.add_argument("--resolution", type=_resolution, default=64, help="N or WxH pixels (default: 64)")
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
    parser.add_argument("--quiet", action="store_true", help="no progress bar or summary")
    return parser


def main(argv: Optional[List[str]] = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        paths = make_scene(
            args.mesh,
            args.out,
            n_train=args.views,
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
    return 0


if __name__ == "__main__":
    sys.exit(main())
