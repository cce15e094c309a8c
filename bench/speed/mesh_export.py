"""Mesh export wall time of an SDF method's field: a dense grid (what nerfstudio's mesher evaluates)
vs our coarse-to-fine sparse mesher (``ns-export marching-cubes`` on a CPU, ``sp-export-mesh``).

    python -m bench.speed.mesh_export --resolutions 256 512    # writes bench/out/mesh_export.json

The field is sp-neus-hashgrid's (the paper's hash grid, 16 levels, 2^19 entries, 2x256 MLP) at its
geometric initialisation: a sphere of radius 0.8 in the [-1, 1] box, queried through
``forward_geonetwork`` as the exporters do. The dense time is measured on ``--dense-sample`` points
and scaled to the full grid (a dense 512^3 grid is 135M queries), plus scikit-image on the full
volume, measured at 256^3 and scaled by the point count for 512^3.
"""

from __future__ import annotations

import argparse
import logging
import time

import numpy as np
import torch

from bench.harness.common import machine_info, write_json


def sdf_field():
    from sp_plugins.nerfstudio.runs import method_config

    from nerfstudio.field_components.spatial_distortions import SceneContraction

    config = method_config("sp-neus-hashgrid")
    field = config.pipeline.model.sdf_field.setup(aabb=torch.tensor([[-1.0] * 3, [1.0] * 3]),
                                                  spatial_distortion=SceneContraction(order=float("inf")),
                                                  num_images=1, use_average_appearance_embedding=False)
    field.eval()

    def sdf(points: torch.Tensor) -> torch.Tensor:
        return field.forward_geonetwork(points)[:, 0]

    return sdf


def dense_seconds(sdf, resolution: int, sample: int, chunk: int) -> dict:
    """Seconds to evaluate a dense ``(resolution+1)^3`` grid, from ``sample`` points."""
    from skimage.measure import marching_cubes

    points = torch.rand(sample, 3) * 2 - 1
    start = time.perf_counter()
    with torch.no_grad():
        for i in range(0, sample, chunk):
            sdf(points[i : i + chunk])
    per_point = (time.perf_counter() - start) / sample
    n = (resolution + 1) ** 3
    volume = np.linalg.norm(np.stack(np.meshgrid(*(np.linspace(-1, 1, 257),) * 3, indexing="ij"), -1), axis=-1) - 0.8
    start = time.perf_counter()
    marching_cubes(volume.astype(np.float32), level=0.0)
    mc = (time.perf_counter() - start) * n / volume.size
    return {"points": n, "s_per_point": per_point, "field_s": per_point * n, "marching_cubes_s": mc, "total_s": per_point * n + mc}


def sparse_seconds(sdf, resolution: int, chunk: int) -> dict:
    from sp_plugins.geometry import sparse_extract_mesh

    counts = []
    start = time.perf_counter()
    mesh = sparse_extract_mesh(sdf, (-1.0, 1.0), resolution, chunk=chunk, progress=False,
                               on_level=lambda lev, cells, pts: counts.append(pts))
    total = time.perf_counter() - start
    return {"points": int(sum(counts)), "total_s": total, "faces": int(len(mesh.faces)), "watertight": bool(mesh.is_watertight)}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--resolutions", type=int, nargs="+", default=[256, 512])
    parser.add_argument("--dense-sample", type=int, default=1 << 20)
    parser.add_argument("--chunk", type=int, default=1 << 17)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    sdf = sdf_field()
    rows = {}
    for res in args.resolutions:
        dense = dense_seconds(sdf, res, args.dense_sample, args.chunk)
        sparse = sparse_seconds(sdf, res, args.chunk)
        rows[res] = {"dense": dense, "sparse": sparse, "speedup": dense["total_s"] / sparse["total_s"]}
        print(f"| {res}^3 | {dense['total_s'] / 60:.1f} min ({dense['points'] / 1e6:.1f}M points, scaled) | "
              f"{sparse['total_s'] / 60:.2f} min ({sparse['points'] / 1e6:.2f}M points) | {rows[res]['speedup']:.0f}x |", flush=True)
    path = write_json("mesh_export", {"benchmark": "mesh_export", "machine": machine_info(), "results": rows})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
