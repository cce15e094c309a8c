"""``sp-export-mesh``: the zero level set of a trained nerfstudio SDF model as a mesh, at any resolution.

    sp-export-mesh --load-config outputs/.../config.yml --output-dir mesh --resolution 256

``ns-export marching-cubes`` only takes resolutions divisible by 512 and then textures the mesh
by rendering it (slow on a CPU). This command meshes the SDF (``forward_geonetwork``, the same
callable nerfstudio meshes) coarse to fine, only near the surface
(:func:`sp_plugins.geometry.sparse_extract_mesh`), inside the model's scene box unless
``--box-min`` / ``--box-max`` are given, and writes ``mesh.ply``. A progress bar shows each level.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import List, Optional


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="sp-export-mesh", description=__doc__.split("\n")[0].split(": ", 1)[1])
    parser.add_argument("--load-config", type=Path, required=True, help="config.yml written by ns-train")
    parser.add_argument("--output-dir", type=Path, required=True, help="folder for mesh.ply")
    parser.add_argument("--resolution", type=int, default=256, help="cells along the box's longest side (default: 256)")
    parser.add_argument("--box-min", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                        help="lower corner of the meshed box (default: the model's scene box)")
    parser.add_argument("--box-max", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                        help="upper corner of the meshed box (default: the model's scene box)")
    parser.add_argument("--level", type=float, default=0.0, help="iso value (default: 0, the SDF's surface)")
    parser.add_argument("--margin", type=float, default=1.5,
                        help="refine cells whose corner values are within this many cell diagonals of the level (default: 1.5)")
    parser.add_argument("--coarse", type=int, default=32, help="cells per axis of the first, dense level (default: 32)")
    return parser


def main(argv: Optional[List[str]] = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not args.load_config.is_file():
        parser.error(f"{args.load_config}: config file not found; pass the config.yml that ns-train wrote")
    if args.resolution < 2:
        parser.error(f"--resolution {args.resolution}: need at least 2 cells per axis (128 and up for a useful mesh)")
    if (args.box_min is None) != (args.box_max is None):
        parser.error("give both --box-min and --box-max, or neither (the model's scene box)")

    import torch
    from nerfstudio.utils.eval_utils import eval_setup

    from sp_plugins.geometry import save_mesh, sparse_extract_mesh

    _, pipeline, _, _ = eval_setup(args.load_config, test_mode="inference")
    model = pipeline.model
    if not hasattr(model.config, "sdf_field") or not hasattr(model.field, "forward_geonetwork"):
        parser.error(f"{args.load_config}: {type(model).__name__} has no SDF field; sp-export-mesh meshes SDF methods "
                     "(for density fields use ns-export pointcloud or poisson)")
    if args.box_min is None:
        aabb = model.scene_box.aabb.detach().cpu().double().numpy()
        lo, hi = aabb[0], aabb[1]
    else:
        lo, hi = args.box_min, args.box_max
    model.eval()
    device = next(model.parameters()).device

    def sdf(points: torch.Tensor) -> torch.Tensor:
        return model.field.forward_geonetwork(points.to(device))[:, 0]

    start = time.perf_counter()
    try:
        mesh = sparse_extract_mesh(sdf, (lo, hi), args.resolution, level=args.level, margin=args.margin,
                                   coarse=args.coarse, device=device)
    except ValueError as err:
        print(f"sp-export-mesh: error: {err}", file=sys.stderr)
        return 2
    seconds = time.perf_counter() - start
    if len(mesh.faces) == 0:
        print(f"sp-export-mesh: error: the SDF does not cross {args.level} inside the box {list(lo)}..{list(hi)}: "
              "no surface (train longer, or check the box)", file=sys.stderr)
        return 2
    args.output_dir.mkdir(parents=True, exist_ok=True)
    out = args.output_dir / "mesh.ply"
    save_mesh(mesh, out)
    print(f"wrote {out}: {len(mesh.vertices)} vertices, {len(mesh.faces)} faces, {args.resolution}^3 in {seconds:.1f} s")
    return 0


def entrypoint() -> None:
    sys.exit(main())


if __name__ == "__main__":
    entrypoint()
