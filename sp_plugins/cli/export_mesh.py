"""``sp-export-mesh``: the zero level set of a trained nerfstudio SDF model as a mesh, at any resolution.

    sp-export-mesh --load-config outputs/.../config.yml --output-dir mesh --resolution 256

``ns-export marching-cubes`` only takes resolutions divisible by 512 and then textures the mesh
by rendering it (slow on a CPU). This command meshes the SDF (``forward_geonetwork``, the same
callable nerfstudio meshes) coarse to fine, only near the surface
(:func:`sp_plugins.geometry.sparse_extract_mesh`), inside the model's scene box unless
``--box-min`` / ``--box-max`` are given, and writes ``mesh.ply``. A progress bar shows each level.

The ``config.yml`` is read with the restricted loader of :mod:`sp_plugins.adapter.safe_config`
(also where nerfstudio's ``eval_setup`` reads it again), so a file naming anything but what a
training run writes is refused in one line before anything is built; the checkpoint is read
weights-only.
"""

from __future__ import annotations

import argparse
import os
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


class _Refused(Exception):
    """One line for the user; exit status 2."""


def _load_saved_config(path: Path):
    """The ``TrainerConfig`` in ``path``, read with the restricted loader
    (:mod:`sp_plugins.adapter.safe_config`: nothing the file names is run), or :class:`_Refused`
    naming the file and why (a tag no training run writes, a class this installation lacks, not YAML)."""
    from sp_plugins.adapter.safe_config import ConfigRefused, load_run_config

    try:  # before nerfstudio is imported: a refused file is answered at once (a real one imports it by naming its classes)
        config = load_run_config(path, "--load-config", versions=_versions())
    except ConfigRefused as refused:
        raise _Refused(str(refused)) from None
    from nerfstudio.engine.trainer import TrainerConfig

    if not isinstance(config, TrainerConfig):
        raise _Refused(f"--load-config {path}: holds a {type(config).__name__}, not the TrainerConfig ns-train writes "
                       "(config.yml in the run folder)")
    return config


def _raised_in(exc: BaseException, function: str) -> bool:
    """``exc`` passed through a frame of ``function`` (by name)."""
    tb = exc.__traceback__
    while tb is not None:
        if tb.tb_frame.f_code.co_name == function:
            return True
        tb = tb.tb_next
    return False


def _versions() -> str:
    from sp_plugins.adapter.checks import _versions as versions

    return versions()


def main(argv: Optional[List[str]] = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return _export(args)
    except _Refused as refused:
        print(f"sp-export-mesh: error: {refused}", file=sys.stderr)
        return 2


def _export(args) -> int:
    if not args.load_config.is_file():
        raise _Refused(f"--load-config {args.load_config}: config file not found; pass the config.yml that ns-train wrote")
    if args.resolution < 2:
        raise _Refused(f"--resolution {args.resolution}: need at least 2 cells per axis (128 and up for a useful mesh)")
    if (args.box_min is None) != (args.box_max is None):
        raise _Refused("give both --box-min and --box-max, or neither (the model's scene box)")
    config = _load_saved_config(args.load_config)

    from sp_plugins.adapter.checks import check_checkpoint_file, check_writable_dir
    from sp_plugins.adapter.errors import InputError, describe_failure, first_line, write_failure

    try:
        check_writable_dir(args.output_dir, "--output-dir")  # before minutes of meshing
    except InputError as err:
        raise _Refused(str(err)) from None
    from sp_plugins.patches import registry

    # our command: our models' input errors print as one line here too
    registry.install_for_process("input_error_hook", command="sp-export-mesh")
    import torch
    from nerfstudio.utils import eval_utils

    from sp_plugins.adapter.safe_config import reading_configs_safely, weights_only_checkpoints
    from sp_plugins.geometry import save_mesh, sparse_extract_mesh
    from sp_plugins.nerfstudio.components.trainer import checkpoint_to_load

    target = None
    try:
        config.load_dir, config.load_checkpoint = config.get_checkpoint_dir(), None
        target = checkpoint_to_load(config, dir_flag=f"--load-config {args.load_config}: its checkpoint folder")
        if target is not None:
            check_checkpoint_file(*target)
        # eval_setup reads the config.yml again itself: through the restricted loader too; its checkpoint weights-only
        where = f"--load-config {args.load_config}"
        with reading_configs_safely(eval_utils, where, _versions()), weights_only_checkpoints():
            _, pipeline, _, _ = eval_utils.eval_setup(args.load_config, test_mode="inference")
    except Exception as exc:  # noqa: BLE001  (a run folder the model cannot be set up from is answered in one line)
        message = describe_failure(exc)
        if message is None:
            detail = first_line(exc, 160)
            detail = detail if detail.startswith(type(exc).__name__) else f"{type(exc).__name__}: {detail}"
            if target is not None and _raised_in(exc, "eval_load_checkpoint"):
                message = (f"{target[0]}: not a checkpoint of this run ({detail}); it holds other contents than the "
                           "training run saved: copy it again, load another step, or retrain")
            else:
                message = (f"--load-config {args.load_config}: the model cannot be set up from this run ({detail}); its "
                           "config.yml was edited or written by another version: load it with the version that wrote it, "
                           "or retrain")
        raise _Refused(message) from None
    model = pipeline.model
    if not hasattr(model.config, "sdf_field") or not hasattr(model.field, "forward_geonetwork"):
        raise _Refused(f"--load-config {args.load_config}: {type(model).__name__} has no SDF field; sp-export-mesh meshes "
                       "SDF methods (for density fields use ns-export pointcloud or poisson)")
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
