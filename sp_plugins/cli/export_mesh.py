"""``sp-export-mesh``: the zero level set of a trained nerfstudio SDF model as a mesh, at any resolution.

    sp-export-mesh --load-config outputs/.../config.yml --output-dir mesh --resolution 256

``ns-export marching-cubes`` only takes resolutions divisible by 512 and then textures the mesh
by rendering it (slow on a CPU). This command meshes the SDF (``forward_geonetwork``, the same
callable nerfstudio meshes) coarse to fine, only near the surface
(:func:`sp_plugins.geometry.sparse_extract_mesh`), inside the model's scene box unless
``--box-min`` / ``--box-max`` are given, and writes ``mesh.ply``. A progress bar shows each level.

The run is opened as :mod:`sp_plugins.cli.run_folder` opens one: its ``config.yml`` read with the
restricted loader, refused in one line before anything is built when it names anything but what a
training run writes; the checkpoint read weights-only.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import List, Optional

from sp_plugins.adapter.checks import check_writable_dir
from sp_plugins.adapter.errors import InputError, write_failure
from sp_plugins.cli.run_folder import Refused as _Refused  # one line for the user; exit status 2
from sp_plugins.cli.run_folder import answer, load_saved_config, model_sdf, setup_pipeline
from sp_plugins.patches import registry


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
    return answer("sp-export-mesh", _export, args)


def _export(args) -> int:
    if args.resolution < 2:
        raise _Refused(f"--resolution {args.resolution}: need at least 2 cells per axis (128 and up for a useful mesh)")
    if (args.box_min is None) != (args.box_max is None):
        raise _Refused("give both --box-min and --box-max, or neither (the model's scene box)")
    config = load_saved_config(args.load_config)

    try:
        check_writable_dir(args.output_dir, "--output-dir")  # before minutes of meshing
    except InputError as err:
        raise _Refused(str(err)) from None
    # our command: our models' input errors print as one line here too
    registry.install_for_process("input_error_hook", command="sp-export-mesh")

    from sp_plugins.geometry import save_mesh, sparse_extract_mesh  # defers torch, trimesh, scikit-image

    pipeline, _ = setup_pipeline(args.load_config, config)
    model = pipeline.model
    found = model_sdf(model)
    if found is None:
        raise _Refused(f"--load-config {args.load_config}: {type(model).__name__} has no SDF field; sp-export-mesh meshes "
                       "SDF methods (for density fields use ns-export pointcloud or poisson)")
    sdf, aabb, device = found
    lo, hi = (aabb[0], aabb[1]) if args.box_min is None else (args.box_min, args.box_max)
    model.eval()

    start = time.perf_counter()
    try:
        mesh = sparse_extract_mesh(sdf, (lo, hi), args.resolution, level=args.level, margin=args.margin,
                                   coarse=args.coarse, device=device)
    except ValueError as err:
        raise _Refused(str(err)) from None
    seconds = time.perf_counter() - start
    if len(mesh.faces) == 0:
        raise _Refused(f"the SDF does not cross {args.level} inside the box {list(lo)}..{list(hi)}: no surface (train "
                       "longer, or check the box)")
    out = args.output_dir / "mesh.ply"
    tmp = args.output_dir / f".tmp-{os.getpid()}-mesh.ply"  # the suffix picks the format
    try:  # a complete mesh.ply or none: an earlier one is replaced only by a finished file
        args.output_dir.mkdir(parents=True, exist_ok=True)
        save_mesh(mesh, tmp)
        os.replace(tmp, out)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise _Refused(write_failure(exc, f"--output-dir {args.output_dir}")) from None
    print(f"wrote {out}: {len(mesh.vertices)} vertices, {len(mesh.faces)} faces, {args.resolution}^3 in {seconds:.1f} s")
    return 0


def entrypoint() -> None:
    sys.exit(main())


if __name__ == "__main__":
    entrypoint()
