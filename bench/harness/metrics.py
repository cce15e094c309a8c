"""What the studies measure and draw: PSNR, SDF meshes against the true mesh, table cells, figures.

Figures are conveniences: a failure to draw one is logged, never a reason to lose results.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Dict, Iterable, List, Optional, Sequence, Tuple

import numpy as np

GEOMETRY = ("chamfer", "accuracy", "completeness", "normal_consistency", "fscore", "area_ratio")
"""The mesh metrics a study reports (:func:`sp_plugins.geometry.mesh_metrics`, in units of the true
mesh's bounding-box diagonal)."""


def psnr(pred: np.ndarray, target: np.ndarray) -> float:
    mse = float(np.mean((pred - target) ** 2))
    return float("inf") if mse == 0 else -10.0 * math.log10(mse)


def sdf_mesh(field, bounds: Tuple[float, float], resolution: int):
    """Marching cubes of the plain SDF of a NeuS-family field (``forward_geonetwork``'s first channel)."""
    from sp_plugins.geometry import extract_mesh

    return extract_mesh(lambda x: field.forward_geonetwork(x)[:, 0], bounds=bounds, resolution=resolution, chunk=1 << 16)


def geometry(mesh, gt, n_points: int, keys: Sequence[str] = GEOMETRY) -> dict:
    from sp_plugins.geometry import mesh_metrics

    found = mesh_metrics(mesh, gt, n_points=n_points)
    return {k: found[k] for k in keys}


def no_geometry() -> dict:
    """The geometry metrics of a run with no true mesh to compare against (a real capture)."""
    return dict.fromkeys(("chamfer", "normal_consistency", "fscore", "area_ratio"))


def crop_to_object(gt, pred, info: dict, dtu_like: bool):
    """The true object above the ground (+0.03) and the prediction inside the object's box + 0.1 above
    that floor: the ground and the backdrop are not the object. Returns ``(gt, pred)`` cropped."""
    floor = info["dtu_like"]["ground_z"] + 0.03 if dtu_like else -np.inf
    low, high = gt.bounds[0] - 0.1, gt.bounds[1] + 0.1
    low[2] = max(low[2], floor)
    return _crop(gt, np.array([-np.inf, -np.inf, floor]), np.full(3, np.inf)), _crop(pred, low, high)


def _crop(mesh, low, high):
    centres = mesh.triangles_center if len(mesh.faces) else np.zeros((0, 3))
    keep = np.all((centres >= low) & (centres <= high), axis=1)
    out = mesh.copy()
    out.update_faces(keep)
    out.remove_unreferenced_vertices()
    return out


def table(columns: Sequence[str], rows: Iterable[Sequence[str]]) -> str:
    """A markdown table."""
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    return "\n".join(lines + ["| " + " | ".join(str(cell) for cell in row) + " |" for row in rows])


def ratio_cell(m: dict) -> str:
    """SP's time ratio while active / over the whole run (:func:`bench.harness.lockstep.active_time_ratios`), if measured."""
    if "time_ratio_whole_run" not in m:
        return ""
    return f"{fmt(m.get('time_ratio_while_active'), '.3f')} / {fmt(m.get('time_ratio_whole_run'), '.3f')}"


def fmt(value, spec: str = ".2f") -> str:
    """A table cell: ``-`` for a missing or NaN value."""
    return "-" if value is None or (isinstance(value, float) and math.isnan(value)) else format(value, spec)


def num(value: Optional[float], digits: int) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def loss_figure(panels: Sequence[Tuple[str, Dict[str, List[float]]]], path: Path) -> None:
    """One panel per ``(title, {run: losses})``: the loss curves smoothed over 25 steps, log scale."""
    try:
        import torch

        plt = _pyplot()
        n = max(1, len(panels))
        fig, axes = plt.subplots(1, n, figsize=(max(6, 4 * n), 3.2), squeeze=False)
        for ax, (title, curves) in zip(axes[0], panels):
            for name, losses in curves.items():
                t = torch.tensor(losses)
                k = 25
                smooth = torch.nn.functional.avg_pool1d(t[None, None], k, 1)[0, 0] if len(t) > k else t
                ax.plot(smooth.numpy(), label=name, lw=1)
            ax.set_title(title, fontsize=8)
            ax.set_yscale("log")
            ax.set_xlabel("step")
            ax.legend(fontsize=6)
        fig.tight_layout()
        fig.savefig(path, dpi=110)
        plt.close(fig)
    except Exception as err:
        logging.warning("loss figure skipped: %s", err)


def render_grid(columns: Dict[str, List[Tuple[np.ndarray, Optional[np.ndarray]]]], truth: List[np.ndarray], path: Path) -> Optional[Path]:
    """Rows: views; columns: ground truth, then each run's colour (and opacity where given)."""
    try:
        plt = _pyplot()
        names = list(columns)
        with_acc = any(acc is not None for views in columns.values() for _, acc in views)
        per_run = 2 if with_acc else 1
        cols = 1 + per_run * len(names)
        fig, axes = plt.subplots(len(truth), cols, figsize=(1.6 * cols, 1.6 * len(truth)), squeeze=False)
        for v, gt in enumerate(truth):
            axes[v, 0].imshow(gt)
            for k, name in enumerate(names):
                rgb, acc = columns[name][v]
                axes[v, 1 + per_run * k].imshow(rgb)
                if with_acc:
                    axes[v, 2 + per_run * k].imshow(acc, cmap="magma", vmin=0, vmax=1)
                if v == 0:
                    axes[0, 1 + per_run * k].set_title(name, fontsize=6)
                    if with_acc:
                        axes[0, 2 + per_run * k].set_title("opacity", fontsize=6)
        axes[0, 0].set_title("ground truth", fontsize=6)
        for ax in axes.flat:
            ax.set_axis_off()
        fig.tight_layout()
        fig.savefig(path, dpi=115)
        plt.close(fig)
        return path
    except Exception as err:
        logging.warning("render figure skipped: %s", err)
        return None


def pair_figure(folder: Path, target_image: Path, pair) -> None:
    """Ground truth | baseline | SP for the first test view, from each run's ``<name>.npy`` render."""
    try:
        import imageio.v2 as imageio

        target = imageio.imread(target_image)[..., :3]
        tiles = [target]
        for name in pair:
            tiles.append((np.load(folder / f"{name}.npy").astype(np.float32) * 255).round().astype(np.uint8))
        imageio.imwrite(folder / "test0_gt_baseline_sp.png", np.concatenate(tiles, axis=1))
    except Exception as error:  # noqa: BLE001
        logging.warning("figure skipped: %s", error)
