"""Synthetic-scene rendering: trimesh's Embree caster vs its rtree caster, and whole-scene times.

- ``casters``: one 64x64 view of Spot (one ray per pixel), the two trimesh ray casters
  alternated in one process; reports seconds per view and the ratio.
- ``scenes``: wall time of `make_scene` (render + write both layouts) for the sizes the demo,
  benchmarks and tests use, with the default (Embree) caster.

Usage: ``python -m bench.speed.scene_render [--repeats 3]``
Writes ``bench/out/scene_render.json`` and prints a markdown table.
"""

from __future__ import annotations

import argparse
import tempfile
import time

import numpy as np

from bench.harness.common import machine_info, paired_timing, ratio_summary, write_json
from sp_plugins.data import make_scene
from sp_plugins.data.cameras import balanced_directions, default_fov, intrinsics, look_at_origin
from sp_plugins.data.mesh import load_mesh, normalize_mesh
from sp_plugins.data.render import ray_intersector, render_views

SCENES = [
    ("tiny: 8+2+2 views, 32x32, 1 ray/px", dict(n_train=8, n_val=2, n_test=2, resolution=32, supersample=1)),
    ("24+4+4 views, 64x64, 4 rays/px", dict(n_train=24, resolution=64)),
    ("50+4+4 views, 128x128, 4 rays/px", dict(n_train=50, resolution=128)),
]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()

    mesh, _, _ = normalize_mesh(load_mesh("spot"))
    c2w = look_at_origin(4.0 * balanced_directions(2, np.random.default_rng(0)))[:1]
    K = intrinsics(64, 64, default_fov(0.85, 4.0))
    casters = {name: ray_intersector(mesh, name) for name in ("embree", "triangle")}
    images = {name: render_views(mesh, c2w, K, 64, 64, 1, intersector=caster) for name, caster in casters.items()}
    agreement = float((images["embree"][..., 3] == images["triangle"][..., 3]).mean())
    steps = {name: (lambda caster=caster: render_views(mesh, c2w, K, 64, 64, 1, intersector=caster)) for name, caster in casters.items()}
    caster_summary = ratio_summary(paired_timing(steps, repeats=args.repeats, warmup=1), baseline="embree")

    scene_times = {}
    for label, settings in SCENES:
        runs = []
        for _ in range(args.repeats):
            with tempfile.TemporaryDirectory() as out:
                start = time.perf_counter()
                make_scene("spot", out, **settings)
                runs.append(time.perf_counter() - start)
        scene_times[label] = float(np.median(runs))

    payload = {"machine": machine_info(), "casters_64x64_view": caster_summary, "alpha_agreement": agreement, "make_scene_s": scene_times}
    path = write_json("scene_render", payload)
    print("| ray caster (Spot, one 64x64 view) | s / view | x Embree |\n|---|---|---|")
    for name, row in caster_summary.items():
        print(f"| {name} | {row['median_s']:.4f} | {row['ratio_vs_embree']:.0f} |")
    print(f"\nalpha masks identical on {100 * agreement:.2f}% of pixels\n")
    print("| make_scene('spot', ...) | wall s |\n|---|---|")
    for label, seconds in scene_times.items():
        print(f"| {label} | {seconds:.2f} |")
    print(f"\nwrote {path}")


if __name__ == "__main__":
    main()
