"""The failure search of `bench.failure_regime` in sdfstudio, the host the paper used for NeuS.

Run it in the sdfstudio environment::

    .venv-sdfstudio/bin/python -m bench.sdfstudio_failure_regime --settings dtu-paper
    .venv-sdfstudio/bin/python -m bench.sdfstudio_failure_regime --list

sdfstudio's own ``neus`` with a hash encoding (``use_grid_feature``, the paper's grid unless the
setting says otherwise) against our ``sp-neus`` at the same settings, on the same DTU-like scenes
(SDFStudio layout; no masks), trained side by side in one process from the same weights on the
same rays (`bench.harness.lockstep`). Test PSNR (whole image and object mask) is computed
on the scene's held-out test views (``meta_data_test.json``; sdfstudio's parser has no test
split); Chamfer as in `bench.failure_regime`.

Both runs' NeRF++ background MLPs are built at the setting's size (4 x 64 by default) while the
trainers are set up: a benchmark-only substitution of sdfstudio's ``NeRFField`` defaults, the same
for both runs, because its 8 x 256 background dominated a CPU step.

A real capture (``fox-q``, ``fox-lr1``: the instant-ngp fox) is converted with sdfstudio's own
``scripts/datasets/process_nerfstudio_to_sdfstudio.py`` (images, OpenCV poses, intrinsics; like
that script, sdfstudio has no lens distortion, and the fox's k1/k2 are dropped), then re-centred
here: the script's ``object`` recipe centres the box of camera *positions*, which puts the fox --
seen from an arc of cameras on one side -- outside the unit sphere (their optical axes meet at
about 1.1 from its origin). :func:`capture_scene` centres on the point the cameras look at and
scales them to :data:`CAPTURE_CAMERA_DISTANCE`; the held-out views are those nerfstudio's
instant-ngp parser holds out, so both hosts test on the same images.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import dataclasses
import functools
import json
import logging
import math
import shutil
import statistics
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch

from bench.failure_regime import FAILED_PSNR, SETTINGS, Setting, is_real, settings_to_run
from bench.failure_regime import scene_dir as rendered_scene
from bench.harness import scenes
from bench.harness import sdfstudio as host
from bench.harness.common import OUT_DIR, done_or_run, machine_info, start
from bench.harness.metrics import crop_to_object, geometry, no_geometry, num, pair_figure, psnr, sdf_mesh

PAIR = ("neus", "sp-neus")
CAPTURE_CAMERA_DISTANCE = 3.0
"""Mean camera distance from the captured point of interest after re-centring: the unit sphere (the
foreground of NeuS) then holds a third of the camera distance around it, as the DTU-like scenes'
object (radius 0.85, cameras at 4); the rest (the fox's wall) is the background model's."""


def eval_indices(n: int, train_fraction: float = 0.9) -> np.ndarray:
    """The held-out views of ``n`` frames: the ones nerfstudio's instant-ngp parser leaves out of its
    equally spaced ``ceil(0.9 n)`` training views (``eval_mode="fraction"``)."""
    train = np.linspace(0, n - 1, math.ceil(n * train_fraction), dtype=int)
    return np.setdiff1d(np.arange(n), train)


def focus_point(c2w: np.ndarray) -> np.ndarray:
    """The point nearest, in least squares, to every camera's optical axis (OpenCV: +z forward) ``[N, 4, 4] -> [3]``."""
    centres, axes = c2w[:, :3, 3], c2w[:, :3, 2] / np.linalg.norm(c2w[:, :3, 2], axis=1, keepdims=True)
    projectors = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]
    return np.linalg.solve(projectors.sum(0), np.einsum("nij,nj->i", projectors, centres))


def capture_scene(setting: Setting, out: Path) -> Path:
    """A real capture in the SDFStudio layout, re-centred on where its cameras look (once per capture)."""
    root = out / "scenes" / f"{setting.mesh}_sdfstudio"
    if (root / "sdfstudio_test" / "meta_data.json").is_file():
        return root
    capture = scenes.capture(scenes.REAL[setting.mesh], setting.mesh)
    converted = root / "converted"
    logging.info("converting %s with sdfstudio's process_nerfstudio_to_sdfstudio", capture)
    done = subprocess.run([sys.executable, "-m", "scripts.datasets.process_nerfstudio_to_sdfstudio", "--data", str(capture),
                           "--output-dir", str(converted), "--data-type", "colmap", "--scene-type", "unbound"],
                          capture_output=True, text=True)
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or ["(no message)"])[-1]
        raise SystemExit(f"{setting.mesh}: sdfstudio's process_nerfstudio_to_sdfstudio failed on {capture}: {last}")
    meta = json.loads((converted / "meta_data.json").read_text())
    c2w = np.array([frame["camtoworld"] for frame in meta["frames"]], dtype=np.float64)
    centre = focus_point(c2w)
    scale = CAPTURE_CAMERA_DISTANCE / float(np.linalg.norm(c2w[:, :3, 3] - centre, axis=1).mean())
    c2w[:, :3, 3] = (c2w[:, :3, 3] - centre) * scale
    distance = np.linalg.norm(c2w[:, :3, 3], axis=1)
    to_capture = np.eye(4)
    to_capture[:3, :3] /= scale
    to_capture[:3, 3] = centre
    meta["worldtogt"] = (np.asarray(meta["worldtogt"]) @ to_capture).tolist()
    meta["scene_box"] = {"aabb": [[-1.0] * 3, [1.0] * 3], "near": max(0.05, float(distance.min()) - math.sqrt(3)),
                         "far": float(distance.max()) + math.sqrt(3), "radius": 1.0, "collider_type": "near_far"}
    frames = [{**frame, "camtoworld": pose.tolist(), "rgb_path": f"../converted/{frame['rgb_path']}"}
              for pose, frame in zip(c2w, meta["frames"])]
    held_out = set(eval_indices(len(frames)).tolist())
    for folder, keep in (("sdfstudio", lambda i: i not in held_out), ("sdfstudio_test", lambda i: i in held_out)):
        (root / folder).mkdir(parents=True, exist_ok=True)
        subset = {**meta, "frames": [f for i, f in enumerate(frames) if keep(i)]}
        (root / folder / "meta_data.json").write_text(json.dumps(subset, indent=1))
    return root


def scene_dir(setting: Setting, out: Path) -> Path:
    """The setting's scene in the SDFStudio layout, plus its held-out views as a dataset of their own."""
    if is_real(setting):
        return capture_scene(setting, out)
    root = rendered_scene(setting, out, layout="sdfstudio")
    test = root / "sdfstudio_test"
    if not (test / "meta_data.json").is_file():  # the held-out views as a dataset of their own
        test.mkdir(exist_ok=True)
        shutil.copy(root / "sdfstudio" / "meta_data_test.json", test / "meta_data.json")
        for sub in ("rgb", "object_mask", "mask"):
            if (root / "sdfstudio" / sub).is_dir() and not (test / sub).exists():
                (test / sub).symlink_to(root / "sdfstudio" / sub)
    return root


def unsupported(setting: Setting) -> str:
    """Why this bench cannot run ``setting`` as the nerfstudio bench does ('' if it can)."""
    if setting.method != "neus":
        return f"method {setting.method!r}: only NeuS is paired here"
    return ""


GRID_GROUP = "grid"
"""The optimizer group of the SDF field's hash tables in this bench (see :func:`grid_group`)."""


def make_config(name: str, data: Path, setting: Setting, out: Path, tag: str):
    config = host.configure(name, data, out, steps=setting.steps, seed=setting.seed, rays=setting.rays, experiment=f"{name}-{tag}")
    model = config.pipeline.model
    if not setting.dtu_like:
        model.background_color = "white"
    if hasattr(model, "sp"):
        if setting.sp_alpha0 is not None:
            model.sp.alpha0 = setting.sp_alpha0
        if setting.sp_end is not None:
            model.sp.end = setting.sp_end
    config.optimizers[GRID_GROUP] = copy.deepcopy(config.optimizers["fields"])
    s = setting
    host.shrink(config, field=dict(use_grid_feature=True, encoding_type="hash", num_layers=2, num_layers_color=2, hidden_dim=s.hidden_dim,
                                   hidden_dim_color=s.hidden_dim, geo_feat_dim=s.hidden_dim - 1, num_levels=s.num_levels,
                                   max_res=s.max_res, log2_hashmap_size=s.log2_hashmap_size,
                                   inside_outside=False,  # an object seen from outside
                                   geometric_init=s.geometric_init, bias=0.5),
                num_samples=s.num_samples, num_samples_importance=s.num_samples_importance, num_up_sample_steps=2,
                background_model=s.background_model, lr={"fields": s.lr, GRID_GROUP: s.grid_lr, "field_background": s.lr},
                warm_up_end=s.warm_up_end, max_steps=s.steps)
    return config


@contextlib.contextmanager
def grid_group():
    """While trainers are set up, sdfstudio's surface models put the SDF field's hash tables in an
    optimizer group of their own (:data:`GRID_GROUP`), as our nerfstudio NeuS does, so the grid's lr
    can differ from the MLPs' (sdfstudio keeps them in ``fields``). The same for both runs: benchmark only."""
    import nerfstudio.models.base_surface_model as surface

    original = surface.SurfaceModel.get_param_groups

    def split(self):
        groups = original(self)
        grid = list(self.field.encoding.parameters())
        ids = {id(p) for p in grid}
        groups["fields"] = [p for p in groups["fields"] if id(p) not in ids]
        groups[GRID_GROUP] = grid
        return groups

    surface.SurfaceModel.get_param_groups = split
    try:
        yield
    finally:
        surface.SurfaceModel.get_param_groups = original


@contextlib.contextmanager
def background_mlp(layers: int, width: int):
    """While trainers are set up, sdfstudio's surface models build their NeRF++ background at this size."""
    import nerfstudio.models.base_surface_model as surface

    original = surface.NeRFField
    surface.NeRFField = functools.partial(original, base_mlp_num_layers=layers, base_mlp_layer_width=width,
                                          head_mlp_layer_width=min(128, width), skip_connections=(4,) if layers > 4 else ())
    try:
        yield
    finally:
        surface.NeRFField = original


def evaluate(run, scene: Path, setting: Setting, render_out: Path) -> dict:
    import imageio.v2 as imageio
    import trimesh
    from nerfstudio.data.dataparsers.sdfstudio_dataparser import SDFStudioDataParserConfig

    from sp_plugins.data import read_scene

    pipeline = run.trainer.pipeline
    pipeline.eval()
    test = SDFStudioDataParserConfig(data=scene / "sdfstudio_test").setup().get_dataparser_outputs("train")
    cameras = test.cameras
    whole, masked, first = [], [], None
    for index in range(len(cameras)):
        bundle = cameras.generate_rays(camera_indices=index)
        with torch.no_grad():
            outputs = pipeline.model.get_outputs_for_camera_ray_bundle(bundle)
        pred = outputs["rgb"].clamp(0, 1).cpu().numpy()
        target = imageio.imread(test.image_filenames[index])[..., :3].astype(np.float32) / 255.0
        mask_path = scene / "sdfstudio" / "object_mask" / f"test_{index:03d}.png"
        if is_real(setting):  # no object mask: the whole image
            mask = np.ones(target.shape[:2], dtype=bool)
        elif mask_path.is_file():
            mask = imageio.imread(mask_path) > 127
        else:  # object on white: the object is where the target is not background
            mask = np.any(target < 0.999, axis=-1)
        whole.append(psnr(pred, target))
        masked.append(psnr(pred[mask], target[mask]))
        first = pred if first is None else first
    mesh = sdf_mesh(pipeline.model.field, (-1.0, 1.0), setting.mesh_resolution)
    if is_real(setting):  # no true mesh
        shape = no_geometry()
    else:
        gt = trimesh.load(scene / "gt_mesh.ply", force="mesh")  # sdfstudio's parser does not move the world
        gt_cropped, pred = crop_to_object(gt, mesh, read_scene(scene), setting.dtu_like)
        shape = geometry(pred, gt_cropped, 50_000)
    render_out.parent.mkdir(parents=True, exist_ok=True)
    mesh.export(render_out.with_suffix(".ply"))
    np.save(render_out.with_suffix(".npy"), first.astype(np.float16))
    return {"psnr": statistics.mean(whole), "psnr_object": statistics.mean(masked), "psnr_views": whole,
            "psnr_object_views": masked, "chamfer": shape["chamfer"], "normal_consistency": shape["normal_consistency"],
            "fscore": shape["fscore"], "area_ratio": shape["area_ratio"]}


def run_pair(setting: Setting, out: Path, tag: str) -> dict:
    scene = scene_dir(setting, out)
    with background_mlp(*setting.background_mlp), grid_group():
        runs = {name: host.Run(name, make_config(name, scene / "sdfstudio", setting, out / "runs", tag), setting.seed) for name in PAIR}
    wall = host.train_together(runs, setting.steps, setting.seed, tag)
    result = {"tag": tag, "host": "sdfstudio", "setting": dataclasses.asdict(setting), "grid_lr_effective": setting.grid_lr, "train_wall_s": wall,
              "pairing": "same weights and rays (torch, numpy and random seeded per step)"}
    for name, run in runs.items():
        metrics = evaluate(run, scene, setting, out / "renders" / tag / name)
        metrics.update(host.step_stats(run))
        metrics["failed"] = bool(metrics["psnr_object"] < FAILED_PSNR)
        result[name] = metrics
    result["machine"] = machine_info()
    first_test = json.loads((scene / "sdfstudio_test" / "meta_data.json").read_text())["frames"][0]["rgb_path"]
    pair_figure(out / "renders" / tag, scene / "sdfstudio_test" / first_test, PAIR)
    return result


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--settings", nargs="+", default=["dtu-paper"], choices=sorted(SETTINGS))
    parser.add_argument("--steps", type=int, default=None)
    parser.add_argument("--list", action="store_true")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", type=Path, default=OUT_DIR / "sdfstudio_failure_regime")
    parser.add_argument("--overwrite", action="store_true")
    args = parser.parse_args(argv)
    if args.list:
        for name, setting in SETTINGS.items():
            print(f"{name}: {dataclasses.asdict(setting)}")
        return
    refused = [f"{name} ({why})" for name in args.settings for why in [unsupported(SETTINGS[name])] if why]
    if refused:
        parser.error(f"not available in sdfstudio's bench: {', '.join(refused)}; run them with bench.failure_regime")
    start(args.threads, quiet=("nerfstudio", "PIL", "trimesh"))
    host.prepare()
    args.out.mkdir(parents=True, exist_ok=True)
    for setting, tag in settings_to_run(args.settings, args.steps):
        result, fresh = done_or_run(args.out / f"{tag}.json", args.overwrite, lambda: run_pair(setting, args.out, tag))
        if not fresh:
            continue
        b, s = result[PAIR[0]], result[PAIR[1]]
        print(f"{tag}: neus {b['psnr']:.2f} dB (object {b['psnr_object']:.2f}, Chamfer {num(b['chamfer'], 4)}); "
              f"sp-neus {s['psnr']:.2f} dB (object {s['psnr_object']:.2f}, Chamfer {num(s['chamfer'], 4)})", flush=True)
    print(f"machine: {machine_info()}")


if __name__ == "__main__":
    main()
