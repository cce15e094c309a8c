"""sp-fit: fit a neural field outside nerfstudio, with stochastic preconditioning on.

    sp-fit pointcloud bunny.ply --steps 2000 --out runs/bunny        # oriented points -> SDF
    sp-fit pointcloud bunny.ply --no-sp --out runs/bunny-baseline     # the baseline
    sp-fit image photo.png --adaptive-alpha --out runs/photo          # image + alpha map
    sp-fit sdf bunny.ply --out runs/bunny-sdf                         # direct SDF supervision
    sp-fit pointcloud bunny.ply --checkpoint-every 200 --out runs/b   # checkpoints in runs/b ...
    sp-fit pointcloud bunny.ply --resume --out runs/b                 # ... and a killed run continued

Every option of the fit is a flag (``--steps``, ``--lr``, ``--encoding.kind``, ...), and the SP
options are those of :class:`sp_plugins.SPConfig` under ``--sp.*`` (``--sp.alpha0``,
``--sp.schedule``, ``--sp.end``, ``--sp.noise``, ``--sp.boundary``, ``--sp.num-samples``,
``--sp.alpha-grid``...), the same names as in the nerfstudio methods.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import tyro

from sp_plugins.core import SPConfig
from sp_plugins.core.schedule import AlphaSchedule
from sp_plugins.geometry import load_mesh, load_oriented_points, save_mesh
from sp_plugins.geometry.io import mesh_topology
from sp_plugins.cli.fit_resume import Checkpoints, jsonable
from sp_plugins.tasks.common import StagedOutputs, plot_curves, resolve_device, smooth, stage
from sp_plugins.tasks.image import ImageFitConfig, _image_sp, load_image, psnr, save_image
from sp_plugins.tasks.pointcloud import PointCloudSDFConfig, _pointcloud_sp
from sp_plugins.tasks.sdf import SDFFitConfig, _sdf_sp

# A bool flag written only as ``--flag``. tyro < 0.9.2 (sdfstudio's environment pins 0.9.1) has no
# FlagCreatePairsOff: there the flag also gets its ``--no-flag`` twin, and ``--flag`` means the same.
Flag = tyro.conf.FlagCreatePairsOff[bool] if hasattr(tyro.conf, "FlagCreatePairsOff") else bool


@dataclass
class _SPFlags(SPConfig):
    """Stochastic preconditioning settings. Checked with the rest of the config (not while
    parsing), so a bad ``--sp.*`` value is one clean error line instead of a parser box."""

    def __post_init__(self) -> None:
        pass


def _sp_flags(default) -> Any:
    """A ``field`` whose default is the task's own SP default, as :class:`_SPFlags`."""
    return field(default_factory=lambda: _SPFlags(**{f.name: getattr(default(), f.name) for f in dataclasses.fields(SPConfig)}))


@dataclass(kw_only=True)
class _Output:
    out: Path = Path("outputs/sp-fit")
    """Folder for the results."""
    overwrite: bool = False
    """Replace results already in --out."""
    no_sp: Flag = False
    """Train the baseline: no stochastic preconditioning (same as --sp.no-enabled)."""
    quiet: Flag = False
    """No progress output."""
    device: str = "auto"
    """Where to train: auto (CUDA when available, else the CPU), cpu, cuda, cuda:N or mps. The hash
    grid runs tiny-cuda-nn on CUDA when it is installed, its torch backend elsewhere."""
    checkpoint_every: Optional[int] = None
    """Write --out/checkpoint.pt every N steps and after the last one (atomically: a killed run
    leaves the previous checkpoint intact), for --resume. Default: none for a new run; a resumed
    run keeps its checkpoint's interval. 0: none."""
    resume: Flag = False
    """Continue the run whose checkpoint is in --out, with the same settings (refused, naming the
    flag, when they differ); it ends as the uninterrupted run would have (on the CPU: the same
    parameters and losses, the same metrics.json apart from the timings)."""


@dataclass(kw_only=True)
class PointCloudCommand(PointCloudSDFConfig, _Output):
    """Fit a signed distance field to an oriented point cloud (SIREN loss), then mesh it and
    measure it. Writes mesh.ply, metrics.json and loss.png to --out."""

    input: tyro.conf.Positional[Path]
    """A mesh (sampled into oriented points) or a PLY point cloud with normals (nx, ny, nz)."""
    sp: _SPFlags = _sp_flags(_pointcloud_sp)
    """Stochastic preconditioning (as in the nerfstudio methods' ``--pipeline.model.sp.*``)."""
    gt: Optional[Path] = None
    """Ground-truth mesh for the metrics (default: the input, when it is a mesh)."""
    estimate_normals: Flag = False
    """Estimate missing normals of a point cloud (PCA, oriented away from the centroid)."""


@dataclass(kw_only=True)
class ImageCommand(ImageFitConfig, _Output):
    """Fit an image with a 2D hash grid. Writes fitted.png, metrics.json (PSNR), loss.png and,
    with --adaptive-alpha, alpha_map.png."""

    input: tyro.conf.Positional[Path]
    """An image file (PNG, JPEG, ...)."""
    sp: _SPFlags = _sp_flags(_image_sp)
    """Stochastic preconditioning (as in the nerfstudio methods' ``--pipeline.model.sp.*``)."""


@dataclass(kw_only=True)
class SDFCommand(SDFFitConfig, _Output):
    """Fit a field to a mesh's signed distance (MAPE loss). Writes mesh.ply, metrics.json and
    loss.png."""

    input: tyro.conf.Positional[Path]
    """A triangle mesh."""
    sp: _SPFlags = _sp_flags(_sdf_sp)
    """Stochastic preconditioning (as in the nerfstudio methods' ``--pipeline.model.sp.*``)."""


def _task_config(cmd, cls):
    """The task config inside a command (drops the command's own flags)."""
    kwargs = {f.name: getattr(cmd, f.name) for f in dataclasses.fields(cls) if f.init}
    config = cls(**kwargs)
    if cmd.no_sp:
        config.sp = dataclasses.replace(config.sp, enabled=False)
    _check_sp(config.sp, config.steps)
    config.sp = SPConfig(**{f.name: getattr(config.sp, f.name) for f in dataclasses.fields(SPConfig)})  # the plain class downstream
    config.validate()
    return config


def _check_sp(sp: SPConfig, steps: int) -> None:
    """The SP settings, including an end after the last step, before any data is loaded; the
    message names the flag (``--sp.alpha0=-1.0: must be ...``)."""
    try:
        sp.validate()
        if sp.enabled and sp.schedule != "constant":
            AlphaSchedule.resolve(sp.schedule, sp.alpha0, end=sp.end, total_steps=steps, final_ratio=sp.final_ratio)
    except ValueError as exc:
        name, sep, rest = str(exc).partition("=")
        if sep and name.isidentifier():
            raise ValueError(f"--sp.{name.replace('_', '-')}={rest}") from None
        raise


def _sp_summary(sp) -> dict:
    return {"enabled": sp.enabled, "alpha0": sp.alpha0, "schedule": sp.schedule, "end": sp.end,
            "alpha_grid": sp.alpha_grid}


def _finite_or_none(obj: Any) -> Any:
    """Strict JSON has no inf / NaN: write them as null (e.g. the Chamfer of an empty mesh)."""
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, dict):
        return {k: _finite_or_none(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite_or_none(v) for v in obj]
    return obj


def _write_json(path: Path, data: dict) -> None:
    path.write_text(json.dumps(_finite_or_none(data), indent=2, allow_nan=False) + "\n")


def _loss_plot(trainer, path: Path, terms: tuple[str, ...]) -> None:
    n = len(trainer.history["loss"])
    window = max(1, n // 100)
    curves = {k: smooth(trainer.history[k], window) for k in terms if k in trainer.history}
    alpha = trainer.history["alpha"]
    end = next((i for i, a in enumerate(alpha) if a == 0.0), None)
    marks = [(end, "SP off")] if end not in (None, 0) else []
    plot_curves(curves, path, title=f"training loss (running mean over {window} steps)", marks=marks)


def _warn_about_topology(path: Path, mesh, task: str) -> None:
    """The input mesh is used as it is; say what its shape means for this task (stderr, one line each)."""
    topo = mesh_topology(mesh)
    notes = []
    if not topo.closed:
        holes = []
        if topo.boundary_edges:
            holes.append(f"{topo.boundary_edges} boundary edges: it is open")
        if topo.nonmanifold_edges:
            holes.append(f"{topo.nonmanifold_edges} edges shared by more than two faces: it is non-manifold")
        if task == "sdf":
            notes.append(f"not watertight ({'; '.join(holes)}): the sign of each distance comes from the closest face's "
                         "normal, which is unreliable near the holes; close them for exact signs")
        else:
            notes.append(f"not watertight ({'; '.join(holes)}): an SDF's zero set is closed, so expect the fit to close or "
                         "thicken the surface there; the metrics compare with the mesh as it is")
    if not topo.consistent_winding:
        notes.append("its faces are not consistently oriented: the face normals flip between neighbours, so "
                     f"{'the normals sampled for the fit' if task == 'pointcloud' else 'the signs of the distances'} disagree; "
                     "re-orient the faces coherently first (e.g. trimesh.repair.fix_normals, or MeshLab)")
    if topo.parts > 1:
        notes.append(f"{topo.parts} separate parts: all are fitted; the clean_* metrics keep only the largest part of the result")
    for note in notes:
        print(f"sp-fit: warning: {path}: {note}", file=sys.stderr)


def _warn_if_empty(mesh) -> None:
    if len(mesh.faces) == 0:
        print("sp-fit: warning: the field has no zero crossing in the domain: the mesh is empty (train longer "
              "or check the input)", file=sys.stderr)


def run_pointcloud(cmd: PointCloudCommand) -> dict:
    outputs = ("mesh.ply", "metrics.json", "loss.png")
    config = _task_config(cmd, PointCloudSDFConfig)
    device = resolve_device(cmd.device)
    checkpoints = Checkpoints(cmd, "pointcloud", config, device, {"estimate_normals": cmd.estimate_normals},
                               {"input": cmd.input, "gt": cmd.gt})
    data = load_oriented_points(cmd.input, config.n_points, config.seed, cmd.estimate_normals)
    gt = load_mesh(cmd.gt) if cmd.gt is not None else data.mesh
    if data.mesh is not None:
        _warn_about_topology(cmd.input, data.mesh, "pointcloud")
    trainer, out, seconds = checkpoints.train(outputs, lambda: config.setup(data, device=device))
    if gt is not None:
        mesh, metrics = trainer.evaluate(gt, progress=not cmd.quiet)
    else:
        mesh, info = trainer.mesh(progress=not cmd.quiet)
        metrics = dict(info, chamfer=None, normal_consistency=None, fscore=None,
                       note="no ground-truth mesh: pass --gt MESH for chamfer, normal consistency and F-score")
    _warn_if_empty(mesh)
    metrics.update(
        steps=trainer.step_index, seconds=seconds, seconds_per_step=trainer.timer.total / max(trainer.step_index, 1),
        device=str(device), sp=_sp_summary(config.sp), normals=data.source, input=str(cmd.input),
        gt=str(cmd.gt) if cmd.gt is not None else (str(cmd.input) if gt is not None else None),
        final_loss=trainer.history["loss"][-1], config=jsonable(config),
    )
    with StagedOutputs(out) as staged, stage(f"writing {out / 'mesh.ply'}", not cmd.quiet):
        save_mesh(trainer.frame.mesh_from_frame(mesh), staged.path("mesh.ply"))
        _write_json(staged.path("metrics.json"), metrics)
        _loss_plot(trainer, staged.path("loss.png"), ("loss", "surface", "normal", "eikonal", "offsurface"))
    if metrics.get("chamfer") is not None:
        print(f"chamfer {metrics['chamfer']:.5f} (clean {metrics['clean_chamfer']:.5f})  normal consistency "
              f"{metrics['normal_consistency']:.4f}  F-score {metrics['fscore']:.4f}  ({seconds:.0f} s) -> {out}")
    else:
        print(f"mesh written ({seconds:.0f} s) -> {out}; {metrics['note']}")
    return metrics


def run_image(cmd: ImageCommand) -> dict:
    outputs = ("fitted.png", "metrics.json", "loss.png", "alpha_map.png")
    config = _task_config(cmd, ImageFitConfig)
    device = resolve_device(cmd.device)
    checkpoints = Checkpoints(cmd, "image", config, device, {}, {"input": cmd.input})
    image = load_image(cmd.input)
    trainer, out, seconds = checkpoints.train(outputs, lambda: config.setup(image, device=device))
    fitted = trainer.render()
    metrics = dict(
        psnr=psnr(fitted, image), steps=trainer.step_index, seconds=seconds, device=str(device),
        seconds_per_step=trainer.timer.total / max(trainer.step_index, 1),
        sp=dict(_sp_summary(config.sp), alpha_grid=trainer.sp.alpha_grid is not None),  # the image's map is --adaptive-alpha
        adaptive_alpha=config.adaptive_alpha, importance_sampling=config.importance_sampling,
        level_masking=config.level_masking, phase2_step=trainer.phase2_step, width=trainer.width, height=trainer.height,
        input=str(cmd.input), final_loss=trainer.history["loss"][-1], config=jsonable(config),
    )
    with StagedOutputs(out) as staged:
        save_image(fitted, staged.path("fitted.png"))
        if trainer.sp.alpha_grid is not None:
            trainer.sp.alpha_grid.export(staged.path("alpha_map.png"))
            values = trainer.sp.alpha_grid.values()
            metrics.update(alpha_map="alpha_map.png", alpha_map_min=float(values.min()), alpha_map_max=float(values.max()),
                           alpha_map_resolution=list(values.shape[::-1]))
        else:
            staged.remove("alpha_map.png")  # an earlier --adaptive-alpha run's map would mislead
        _write_json(staged.path("metrics.json"), metrics)
        _loss_plot(trainer, staged.path("loss.png"), ("loss",))
    print(f"PSNR {metrics['psnr']:.2f} dB ({seconds:.0f} s) -> {out}")
    return metrics


def run_sdf(cmd: SDFCommand) -> dict:
    outputs = ("mesh.ply", "metrics.json", "loss.png")
    config = _task_config(cmd, SDFFitConfig)
    device = resolve_device(cmd.device)
    checkpoints = Checkpoints(cmd, "sdf", config, device, {}, {"input": cmd.input})
    gt = load_mesh(cmd.input)
    _warn_about_topology(cmd.input, gt, "sdf")
    trainer, out, seconds = checkpoints.train(outputs, lambda: config.setup(gt, device=device))
    mesh, metrics = trainer.evaluate(progress=not cmd.quiet)
    _warn_if_empty(mesh)
    metrics.update(
        steps=trainer.step_index, seconds=seconds, seconds_per_step=trainer.timer.total / max(trainer.step_index, 1),
        device=str(device), sp=_sp_summary(config.sp), input=str(cmd.input), final_loss=trainer.history["loss"][-1], config=jsonable(config),
    )
    with StagedOutputs(out) as staged:
        save_mesh(trainer.frame.mesh_from_frame(mesh), staged.path("mesh.ply"))
        _write_json(staged.path("metrics.json"), metrics)
        _loss_plot(trainer, staged.path("loss.png"), ("loss",))
    print(f"chamfer {metrics['chamfer']:.5f} (clean {metrics['clean_chamfer']:.5f})  F-score {metrics['fscore']:.4f} "
          f"({seconds:.0f} s) -> {out}")
    return metrics


COMMANDS = {
    "pointcloud": (PointCloudCommand, run_pointcloud),
    "image": (ImageCommand, run_image),
    "sdf": (SDFCommand, run_sdf),
}


def main(argv: Optional[list[str]] = None) -> int:
    import logging

    logging.basicConfig(level=logging.WARNING, format="sp-fit: %(message)s")
    cmd = tyro.extras.subcommand_cli_from_dict(
        {name: tyro.conf.SuppressFixed[cls] for name, (cls, _) in COMMANDS.items()},
        prog="sp-fit",
        description=__doc__.split("\n\n")[0],
        args=argv,
    )
    run = next(fn for cls, fn in COMMANDS.values() if isinstance(cmd, cls))
    created = not cmd.out.exists()
    try:
        run(cmd)
    except (ValueError, FloatingPointError) as exc:
        if created and cmd.out.is_dir() and not any(cmd.out.iterdir()):
            cmd.out.rmdir()  # a refused or diverged run leaves nothing behind, not even the --out it made
        print(f"sp-fit: error: {exc}", file=sys.stderr)
        return 2
    return 0


def entrypoint() -> None:
    sys.exit(main())


if __name__ == "__main__":
    entrypoint()
