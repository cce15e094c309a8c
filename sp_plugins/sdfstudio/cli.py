"""Console entry points for sdfstudio.

- ``sp-sdfstudio-train``: sdfstudio's ``ns-train`` with our methods: applies the compatibility
  patches, adds the methods of our entry-point group and ``sp-<method>`` for every SDF method
  sdfstudio registers, rebuilds sdfstudio's tyro union (registry entry ``sdfstudio_methods``), then runs sdfstudio's own train ``main``.
  Same arguments as ``ns-train``; ``sp-<method>`` of a method SP does not apply to (nerfacto,
  mipnerf, ...) is refused in one line that says why.
- ``sp-sdfstudio-extract-mesh``: mesh of a trained checkpoint at any resolution (sdfstudio's
  ``ns-extract-mesh`` accepts only multiples of 512 for SDFs: minutes and GBs on a CPU). It loads
  the checkpoint with sdfstudio's ``eval_setup`` (the same loading as ns-eval) and runs our marching
  cubes on the plain field's SDF, saying on stderr what it does and how far (at 256, minutes of SDF
  queries on a CPU).

Both read a saved ``config.yml`` (``--load-config``, ``--trainer.load-config``) with the restricted
loader of :mod:`sp_plugins.adapter.safe_config`, first on their own (a refusal is one line naming the
file and the tag) and then wherever sdfstudio reads it again (``eval_setup``, ``scripts/train.py``'s
``main``); sdfstudio's own ``ns-*`` commands still read it with PyYAML's full loader.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Tuple

from sp_plugins.adapter.errors import describe_failure
from sp_plugins.adapter.safe_config import (
    ConfigRefused,
    load_run_config,
    reading_configs_safely,
    weights_only_checkpoints,
)
from sp_plugins.patches import registry
from sp_plugins.patches.sdfstudio_import_hook import install_all
from sp_plugins.sdfstudio.detect import require_sdfstudio


def _error(prog: str, message: str) -> "NoReturn":  # noqa: F821
    print(f"{prog}: error: {message}", file=sys.stderr)
    raise SystemExit(2)


def _say(prog: str, stage: str) -> None:
    """A stage line on stderr (stdout keeps the result line)."""
    print(f"{prog}: {stage} ...", file=sys.stderr, flush=True)


class _Lines:
    """tqdm's redraws (``\\r``-separated) as one line each, for a stderr that is a log, not a terminal."""

    def __init__(self, stream) -> None:
        self.stream = stream

    def write(self, text: str) -> None:
        text = text.replace("\r", "").strip("\n")
        if text.strip():
            self.stream.write(text + "\n")

    def flush(self) -> None:
        self.stream.flush()


def _bar(prog: str, stage: str, total: int):
    """A progress bar of ``total`` SDF points on stderr: redrawn each second on a terminal, a line
    every 30 s into a log (so a log file does not fill with redraws)."""
    from tqdm import tqdm

    tty = sys.stderr.isatty()
    return tqdm(total=total, desc=f"{prog}: {stage}", unit="pt", unit_scale=True, file=sys.stderr if tty else _Lines(sys.stderr),
                mininterval=1.0 if tty else 30.0, ascii=not tty, dynamic_ncols=tty)


def _prepare(prog: str) -> None:
    try:
        require_sdfstudio()
    except ImportError as err:
        _error(prog, str(err))
    install_all(command=prog)  # our command owns its process: the sdfstudio_* registry entries stay


def _check_saved_config(prog: str, path: Path, flag: str) -> str:
    """``path`` read with the restricted loader: an sdfstudio ``Config``, or one line and exit 2. Returns
    how a later refusal names it."""
    from nerfstudio.configs.base_config import Config

    try:
        load_run_config(path, flag, expect=Config)
    except ConfigRefused as refused:
        _error(prog, str(refused))
    return f"{flag} {path}"


def train(argv: Optional[list] = None) -> None:
    """``sp-sdfstudio-train METHOD [ns-train options]``."""
    prog = "sp-sdfstudio-train"
    _prepare(prog)
    import torch
    import tyro

    import scripts.train as host_train
    from nerfstudio.configs.config_utils import convert_markup_to_ansi

    from sp_plugins.sdfstudio.registration import REFUSED  # defers torch

    registry.install_for_process("sdfstudio_methods", command=prog)  # our methods in the list and the tyro union
    args = list(sys.argv[1:] if argv is None else argv)
    method = next((a for a in args if not a.startswith("-")), None)
    if method in REFUSED:
        _error(prog, f"SP cannot be put on {method[len('sp-'):]}: {REFUSED[method]}")
    tyro.extras.set_accent_color("bright_yellow")
    refused = ", ".join(sorted(REFUSED))
    description = (host_train.__doc__ or "") + (
        f"\n\nsp-<method>: any sdfstudio SDF method with stochastic preconditioning (--pipeline.model.sp.*). "
        f"Not offered (no SurfaceModel SDF field for SP to enter; sp-sdfstudio-train sp-<method> says why): {refused}."
    )
    config = tyro.cli(
        host_train.AnnotatedBaseConfigUnion, args=args, prog=prog, description=convert_markup_to_ansi(description)
    )
    if config.machine.num_gpus > 0 and not torch.cuda.is_available():
        _error(prog, f"--machine.num-gpus {config.machine.num_gpus} but no CUDA device is available; pass --machine.num-gpus 0")
    sp = getattr(config.pipeline.model, "sp", None)
    if sp is not None:
        from sp_plugins.adapter.callbacks import schedule_problem  # defers torch
        from sp_plugins.sdfstudio.model import unsupported_setting  # defers sdfstudio

        problem = schedule_problem(sp, config.trainer.max_num_iterations, "--trainer.max-num-iterations")
        problem = problem or unsupported_setting(sp)
        if problem:
            _error(prog, problem)
    if config.trainer.load_config is None:
        problem = _data_problem(config)
        if problem:
            _error(prog, problem)
        host_train.main(config)
        return
    where = _check_saved_config(prog, config.trainer.load_config, "--trainer.load-config")
    with reading_configs_safely(host_train, where):  # main reads it again: through the restricted loader too
        host_train.main(config)


LAYOUTS = {"SDFStudioDataParserConfig": ("meta_data.json", "sdfstudio-data: meta_data.json + images"),
           "BlenderDataParserConfig": ("transforms_train.json", "blender-data: transforms_train.json + images")}
"""sdfstudio dataparsers (by config class name) whose index file is checked before training: the
file each reads first and the layout it expects."""


def _data_problem(config) -> str:
    """Why the run's ``--data`` cannot be read, or ``""``: the folder must exist and, for the layouts
    of :data:`LAYOUTS`, hold its index file (sdfstudio stops with a traceback otherwise)."""
    parser = getattr(getattr(config.pipeline, "datamanager", None), "dataparser", None)
    data = getattr(parser, "data", None)
    if data is None:
        return ""
    data = Path(data)
    index, layout = LAYOUTS.get(type(parser).__name__, ("", "the layout its dataparser reads"))
    if not data.is_dir():
        return f"{data}: data folder not found; pass --data DIR pointing at a scene ({layout})"
    if index and not (data / index).is_file():
        return f"{data / index}: file not found; expected a scene in the {layout} layout (sp-scene MESH OUT writes one)"
    return ""


@dataclass
class ExtractMesh:
    """Load an sdfstudio checkpoint and write the zero level set of its SDF as a mesh."""

    load_config: Path
    """config.yml of the training run."""
    output_path: Path = Path("mesh.ply")
    """Where the mesh goes (.ply, .obj, .stl ...)."""
    resolution: int = 256
    """Grid points per axis."""
    bounding_box_min: Tuple[float, float, float] = (-1.0, -1.0, -1.0)
    bounding_box_max: Tuple[float, float, float] = (1.0, 1.0, 1.0)
    refine: int = 0
    """Bisection steps per vertex along its grid edge (0: plain marching cubes)."""


def extract_mesh(argv: Optional[list] = None) -> None:
    """``sp-sdfstudio-extract-mesh --load-config RUN/config.yml [--resolution 128] [--output-path m.ply]``."""
    prog = "sp-sdfstudio-extract-mesh"
    _prepare(prog)
    import torch
    import tyro

    from sp_plugins.geometry.marching_cubes import evaluate_grid, mesh_from_grid  # defers torch, trimesh, scikit-image

    args = tyro.cli(ExtractMesh, args=argv, prog=prog)
    if not args.load_config.is_file():
        _error(prog, f"--load-config {args.load_config}: no such file; give the config.yml of a training run")
    if args.resolution < 2:
        _error(prog, f"--resolution {args.resolution}: need at least 2 grid points per axis")
    from nerfstudio.utils import eval_utils

    where = _check_saved_config(prog, args.load_config, "--load-config")
    _say(prog, f"loading {args.load_config}")
    try:  # eval_setup reads the config.yml again: through the restricted loader too; its checkpoint weights-only
        with reading_configs_safely(eval_utils, where), weights_only_checkpoints():
            _, pipeline, _ = eval_utils.eval_setup(args.load_config)
    except Exception as exc:  # noqa: BLE001  (only the failures describe_failure knows become one line)
        message = describe_failure(exc)
        if message is None:
            raise
        _error(prog, message)
    field = pipeline.model.field
    field.eval()
    device = next(field.parameters()).device

    def sdf(x: torch.Tensor) -> torch.Tensor:
        return field.forward_geonetwork(x)[:, 0]

    box = (args.bounding_box_min, args.bounding_box_max)
    with torch.no_grad():
        with _bar(prog, f"SDF on a {args.resolution}^3 grid", args.resolution**3) as bar:

            def counted(x: torch.Tensor) -> torch.Tensor:
                values = sdf(x)
                bar.update(len(x))
                return values

            volume = evaluate_grid(counted, box, args.resolution, device=device)
        refine = f", then {args.refine} bisection steps per vertex" if args.refine else ""
        _say(prog, f"marching cubes{refine}")
        mesh = mesh_from_grid(volume, box, sdf, refine=args.refine, device=device)
    if len(mesh.faces) == 0:
        _error(prog, "the SDF has no zero crossing inside the box; check --bounding-box-min/max or train longer")
    args.output_path.parent.mkdir(parents=True, exist_ok=True)
    mesh.export(args.output_path)
    print(f"{prog}: {len(mesh.vertices)} vertices, {len(mesh.faces)} faces -> {args.output_path}")
