"""Per-step time of nerfacto with nerfstudio's torch ``HashEncoding`` against our ``HashGrid``.

Both models are sp-nerfacto's baseline (``sp.enabled=False``: nerfstudio's nerfacto, with our
offline LPIPS) at nerfacto's default field and proposal-network settings (16 levels, 2^19 rows,
resolution 16..2048; proposals 5 levels, 2^17 rows, 128 / 256), built with
``implementation="torch"`` (what nerfstudio falls back to without tiny-cuda-nn). Variant
``nerfstudio`` keeps nerfstudio's ``HashEncoding``; variant ``ours`` is what sp-nerfacto builds
on a CPU (:mod:`sp_plugins.nerfstudio.components.hash_encoding`). A step is nerfacto's own training step on
random rays through the unit box: forward, nerfacto's losses (RGB, interlevel, distortion),
backward, Adam. Steps alternate between the two models in one process (A B B A ...), so load on
the shared machine hits both alike; the result is the median of per-pair ratios.

Usage: ``python -m bench.speed.nerfacto_hash_speed [--rays 256] [--repeats 8] [--threads 1]``
Writes ``bench/out/nerfacto_hash_speed.json``.
"""

from __future__ import annotations

import argparse
import sys

import torch


def build_model(variant: str, seed: int = 0):
    from nerfstudio.data.scene_box import SceneBox

    from sp_plugins.nerfstudio.components import hash_encoding
    from sp_plugins.nerfstudio.components.hash_encoding import NerfactoHashGridModelConfig
    from sp_plugins.nerfstudio.variants import variant

    config = variant("ModelConfig", NerfactoHashGridModelConfig)(implementation="torch")
    config.sp.enabled = False
    config.camera_optimizer.mode = "off"
    box = SceneBox(aabb=torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))
    keep_host = variant == "nerfstudio"
    if keep_host:  # build the host's torch HashEncoding: skip our replacement for this model only
        original = hash_encoding.use_sp_hash_grids
        hash_encoding.use_sp_hash_grids = lambda device: False
    torch.manual_seed(seed)
    try:
        model = config.setup(scene_box=box, num_train_data=8, metadata={}, device="cpu", grad_scaler=None)
    finally:
        if keep_host:
            hash_encoding.use_sp_hash_grids = original
    kinds = {type(m).__name__ for m in model.modules()}
    expected = "HashEncoding" if keep_host else "HashGrid"
    assert expected in kinds and ({"HashEncoding", "HashGrid"} - {expected}).isdisjoint(kinds), kinds
    model.train()
    return model


def make_step(model, rays: int, seed: int):
    from nerfstudio.cameras.rays import RayBundle

    generator = torch.Generator().manual_seed(seed)
    params = [p for group in model.get_param_groups().values() for p in group]
    optimizer = torch.optim.Adam(params, lr=1e-2, eps=1e-15)

    def step() -> None:
        origins = torch.nn.functional.normalize(torch.randn(rays, 3, generator=generator), dim=-1) * 2.5
        target = torch.rand(rays, 3, generator=generator) * 0.6 - 0.3
        directions = torch.nn.functional.normalize(target - origins, dim=-1)
        bundle = RayBundle(
            origins=origins, directions=directions, pixel_area=torch.full((rays, 1), 1e-4),
            camera_indices=torch.randint(0, 8, (rays, 1), generator=generator), metadata={},
        )
        batch = {"image": torch.rand(rays, 3, generator=generator)}
        outputs = model(bundle)
        metrics = model.get_metrics_dict(outputs, batch)
        loss = sum(model.get_loss_dict(outputs, batch, metrics).values())
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()

    return step


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="bench.speed.nerfacto_hash_speed", description=__doc__.split("\n\n")[0])
    ap.add_argument("--rays", type=int, default=256, help="rays per step (nerfacto's default is 4096)")
    ap.add_argument("--repeats", type=int, default=8, help="timed steps per model")
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    from bench.harness.common import machine_info, paired_timing, ratio_summary, write_json

    models = {v: build_model(v) for v in ("nerfstudio", "ours")}
    steps = {v: make_step(m, args.rays, seed=1) for v, m in models.items()}
    times = paired_timing(steps, repeats=args.repeats, warmup=args.warmup)
    summary = ratio_summary(times, baseline="nerfstudio")
    payload = {"setting": {"rays": args.rays, "repeats": args.repeats, "threads": args.threads,
                           "field": "16 levels, 2^19, 16..2048", "proposals": "5 levels, 2^17, 128 / 256"},
               "times_s": times, "summary": summary, "machine": machine_info()}
    path = write_json("nerfacto_hash_speed", payload)
    for name, s in summary.items():
        print(f"{name:10s} median {s['median_s']:.3f} s/step   ratio vs nerfstudio {s['ratio_vs_nerfstudio']:.3f}")
    print(f"-> {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
