"""Baseline vs SP side by side, for the README: renders and meshes of finished failure-search pairs.

Per setting (one row pair): the first test view's ground truth, baseline and SP renders (saved by
``bench.failure_regime`` as ``renders/TAG/NAME.npy``), then the true object mesh and the two
marching-cubes meshes, cropped to the object's box as for the Chamfer metric and shaded from that
same test camera (`sp_plugins.data.render.render_views`). Titles carry object PSNR and Chamfer.

Usage::

    python -m bench.failure_figure --out bench/out/failure_regime dtu-paper_steps600 q-6-views_steps300 \
        --save bench/results/failure_regime/figure.png
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path
from typing import List

import numpy as np

from bench.harness.common import OUT_DIR


def test_camera(scene: Path):
    """The first test camera (OpenGL c2w, K) and the dataparser outputs of the Blender layout."""
    from nerfstudio.data.dataparsers.blender_dataparser import BlenderDataParserConfig

    parser = BlenderDataParserConfig(data=scene / "blender").setup()
    train = parser.get_dataparser_outputs("train")
    cameras = parser.get_dataparser_outputs("test").cameras
    c2w = np.eye(4)
    c2w[:3, :4] = cameras.camera_to_worlds[0].numpy()
    K = np.array([[float(cameras.fx[0]), 0.0, float(cameras.cx[0])], [0.0, float(cameras.fy[0]), float(cameras.cy[0])], [0, 0, 1]])
    return c2w, K, int(cameras.width[0]), int(cameras.height[0]), train


def object_meshes(result: dict, out: Path, scene: Path, train_outputs) -> List:
    """True object mesh and the pair's meshes, cropped as ``failure_regime.evaluate`` crops them."""
    import trimesh

    from bench.harness.metrics import crop_to_object
    from sp_plugins.data import load_gt_mesh, read_scene

    gt, info = load_gt_mesh(scene, train_outputs), read_scene(scene)
    meshes = []
    for name in result["pair"]:
        pred = trimesh.load(out / "renders" / result["tag"] / f"{name}.ply", force="mesh", process=False)
        gt_cropped, cropped = crop_to_object(gt, pred, info, result["setting"]["dtu_like"])
        meshes.append(cropped)
    return [gt_cropped, *meshes]


def figure(out: Path, tags: List[str], save: Path, upscale: int = 2) -> Path:
    import imageio.v2 as imageio
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from bench.failure_regime import PAIR, Setting, scene_dir
    from sp_plugins.data.render import render_views

    results = [json.loads((out / f"{tag}.json").read_text()) for tag in tags]
    cols = 1 + max(len(r.get("pair", PAIR)) for r in results)  # ground truth, then every run (a pair or more)
    fig, axes = plt.subplots(2 * len(tags), cols, figsize=(2.5 * cols, 2.0 * 2 * len(tags)), squeeze=False)
    for row, (tag, result) in enumerate(zip(tags, results)):
        result.setdefault("pair", list(PAIR))
        fields = {k: tuple(v) if isinstance(v, list) else v for k, v in result["setting"].items()}
        scene = scene_dir(Setting(**fields), out)
        c2w, K, width, height, train = test_camera(scene)
        target = imageio.imread(scene / "blender" / "test" / "r_0.png") / 255.0
        if target.shape[-1] == 4:  # object on white: composite as the model's white background does
            target = target[..., :3] * target[..., 3:] + (1.0 - target[..., 3:])
        images = [target[..., :3]]
        images += [np.load(out / "renders" / tag / f"{name}.npy").astype(np.float32) for name in result["pair"]]
        K_big = K.copy()
        K_big[:2] *= upscale
        meshes = object_meshes(result, out, scene, train)
        shaded = []
        for mesh in meshes:
            if len(mesh.faces) == 0:
                shaded.append(np.ones((height * upscale, width * upscale, 3)))
                continue
            rgba = render_views(mesh, c2w[None], K_big, width * upscale, height * upscale)[0]
            shaded.append(rgba[..., :3] * rgba[..., 3:] + (1.0 - rgba[..., 3:]))
        titles = ["ground truth"] + [f"{name}\n{result[name]['psnr_object']:.2f} dB (object)" for name in result["pair"]]
        mesh_titles = [f"true object ({tag})"] + [_chamfer(result[name]["chamfer"]) for name in result["pair"]]
        for col in range(len(images), cols):
            axes[2 * row, col].axis("off")
            axes[2 * row + 1, col].axis("off")
        for col in range(len(images)):
            for r, (picture, title) in enumerate(((images[col], titles[col]), (shaded[col], mesh_titles[col]))):
                ax = axes[2 * row + r, col]
                ax.imshow(np.clip(picture, 0, 1))
                ax.set_title(title, fontsize=7)
                ax.axis("off")
    fig.tight_layout()
    save.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(save, dpi=110)
    plt.close(fig)
    return save


def _chamfer(value) -> str:
    return "no surface in the object's box" if value is None or not np.isfinite(value) else f"Chamfer {value:.4f}"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("tags", nargs="+", help="finished settings, e.g. dtu-paper_steps600")
    parser.add_argument("--out", type=Path, default=OUT_DIR / "failure_regime", help="the failure search's output folder")
    parser.add_argument("--save", type=Path, default=None, help="PNG to write (default OUT/figure.png)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    missing = [t for t in args.tags if not (args.out / f"{t}.json").is_file()]
    if missing:
        parser.error(f"no finished result for {', '.join(missing)} in {args.out}: run `python -m bench.failure_regime --settings ...` first")
    print(figure(args.out, args.tags, args.save or args.out / "figure.png"))


if __name__ == "__main__":
    main()
