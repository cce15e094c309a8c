"""The size screen behind the regression test: one pair (MipNeRF, MipNeRF + SP at the
sparse-view setting) on 3 DTU-like views at a budget smaller than ``bench.sparse_views``' own, to
find the smallest size at which SP's gap still shows (on every seed). Paired like the study (same
initial weights, same rays); results under ``bench/out/sparse_views/gap-screen``, one JSON per run.

    OMP_NUM_THREADS=1 python -m bench.sparse_gap_screen --steps 800 --rays 64 --image 48x36 --seed 0
"""

from __future__ import annotations

import argparse
import json
import time

from bench.harness import radiance as rd
from bench.harness.common import start

import bench.sparse_views as sv


def image_size(text: str) -> tuple:
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected WIDTHxHEIGHT, e.g. 48x36") from None
    return width, height


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", default="spot", help="a key of bench.harness.radiance.SCENES or a mesh file")
    parser.add_argument("--steps", type=int, default=800)
    parser.add_argument("--rays", type=int, default=64)
    parser.add_argument("--samples", type=int, default=32, help="coarse and fine samples each")
    parser.add_argument("--mlp-num-layers", type=int, default=4)
    parser.add_argument("--mlp-layer-width", type=int, default=128)
    parser.add_argument("--image", type=image_size, default=(48, 36), help="WIDTHxHEIGHT of the 49 + 3 views")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--sp", type=sv.SPSetting.parse, default=sv.SPSetting.parse(sv.SPARSE))
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    start(args.threads, quiet=("nerfstudio", "PIL", "sp_plugins"))
    real = rd.dtu_scene_dir
    rd.dtu_scene_dir = lambda scene, up_axis=None: real(scene, up_axis, views=49, test_views=3, resolution=args.image)
    budget = rd.MipBudget(steps=args.steps, rays=args.rays, coarse=args.samples, fine=args.samples,
                          mlp_num_layers=args.mlp_num_layers, mlp_layer_width=args.mlp_layer_width,
                          head_width=max(8, args.mlp_layer_width // 2), views=3, dtu_like=True, lr=sv.QUICK["lr"])
    tag = f"gap-screen/{args.image[0]}x{args.image[1]}"
    t0 = time.time()
    pair = sv.study(args.scene, budget, args.seed, sv.run_specs([args.sp], freenerf=None), tag)
    base, sp = pair[sv.BASELINE], pair[args.sp.name]
    row = {"steps": args.steps, "rays": args.rays, "samples": args.samples, "mlp": f"{args.mlp_num_layers}x{args.mlp_layer_width}",
           "image": "x".join(map(str, args.image)), "seed": args.seed, "setting": args.sp.name, "wall_s": round(time.time() - t0)}
    for name, r in (("baseline", base), ("sp", sp)):
        row[name] = {"psnr": round(r["psnr"], 2), "psnr_object": round(r["psnr_object"], 2), "ssim": round(r["ssim"], 3)}
    print(json.dumps(row))
    print(f"object PSNR: baseline {base['psnr_object']:.2f}, SP {sp['psnr_object']:.2f} ({sp['psnr_object'] - base['psnr_object']:+.2f} dB); "
          f"SSIM {base['ssim']:.3f} -> {sp['ssim']:.3f}")


if __name__ == "__main__":
    main()
