"""SP's per-step cost: baseline and SP training steps alternated in one process.

Three workloads, all at CPU scale:

- ``methods``: one training step (``Trainer.train_iteration``: forward, loss, backward, optimizer) of
  our registered nerfstudio methods with SP on and off (``sp.enabled``), same weights and rays, the
  steps alternated in one process: ``sp-nerfacto``, ``sp-neus-hashgrid``, ``sp-mipnerf``,
  ``sp-relu-field``. SP on is the one seam (moved RaySamples handed to each field) plus the noise.

- ``sdf``: a hash-grid SDF step (encoding + 2x64 MLP, SIREN-style surface/eikonal loss with the
  eikonal gradient by double backward, Adam), SP perturbing every query point.
- ``dense``: a ReLU-field render step (RGB + density grid, trilinear, ReLU, 1024 rays x 96
  samples, white background, MSE, Adam), SP perturbing every sample with reflection.

Usage: ``python -m bench.speed.sp_overhead [--repeats 40] [--threads 2] [--only sdf|dense|methods]``
Writes ``bench/out/sp_overhead.json`` and prints a markdown table.
"""

from __future__ import annotations

import argparse
import torch
import torch.nn.functional as F
from torch import nn

from bench.harness.common import machine_info, paired_timing, ratio_summary, write_json
from sp_plugins import SPConfig


def _hash_encoding(levels=16, log2_table=19, base=16, finest=1024):
    try:
        from sp_plugins.encodings import HashGrid

        return HashGrid(num_levels=levels, log2_hashmap_size=log2_table, base_resolution=base, max_resolution=finest, backend="torch"), "sp_plugins.encodings.HashGrid"
    except ImportError:
        from nerfstudio.field_components.encodings import HashEncoding

        enc = HashEncoding(levels, base, finest, log2_table, 2, implementation="torch")
        enc.n_output_dims = enc.get_out_dim()
        return enc, "nerfstudio HashEncoding(torch)"


def make_sdf_step(sp_on: bool, batch: int, seed: int = 0):
    torch.manual_seed(seed)
    enc, enc_name = _hash_encoding()
    mlp = nn.Sequential(nn.Linear(enc.n_output_dims, 64), nn.Softplus(100), nn.Linear(64, 64), nn.Softplus(100), nn.Linear(64, 1))
    opt = torch.optim.Adam(list(enc.parameters()) + list(mlp.parameters()), lr=1e-3)
    sp = SPConfig(enabled=sp_on, alpha0=0.02, schedule="constant", boundary="reflect").setup(total_steps=10**6, bounds=(-1.0, 1.0))
    sp.train()

    def sdf(x):
        return mlp(enc((x + 1) / 2)).squeeze(-1)

    def step():
        d = torch.randn(batch, 3)
        surface = 0.5 * d / d.norm(dim=-1, keepdim=True)
        free = torch.rand(batch, 3) * 2 - 1
        x = sp(torch.cat([surface, free])).requires_grad_(True)
        f = sdf(x)
        (g,) = torch.autograd.grad(f.sum(), x, create_graph=True)
        loss = 3e3 * f[:batch].abs().mean() + 5e1 * (g.norm(dim=-1) - 1).abs().mean() + 1e2 * torch.exp(-100 * f[batch:].abs()).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    return step, enc_name


def make_dense_step(sp_on: bool, res: int, n_rays: int = 1024, n_samples: int = 96, seed: int = 0, sp=None):
    torch.manual_seed(seed)
    grid = nn.Parameter(torch.rand(1, 4, res, res, res) * 2 - 1)
    opt = torch.optim.Adam([grid], lr=0.03)
    n_pool = 16 * n_rays
    origins = F.normalize(torch.randn(n_pool, 3), dim=-1) * 3.0
    dirs = F.normalize(torch.rand(n_pool, 3) - 0.5 - origins, dim=-1)
    targets = torch.rand(n_pool, 3)
    # clip every ray to the [-1, 1]^3 box, as a ReLU field (and nerfstudio's AABB collider) does
    t0 = (-1.0 - origins) / dirs
    t1 = (1.0 - origins) / dirs
    near = torch.minimum(t0, t1).amax(-1, keepdim=True)
    far = torch.maximum(t0, t1).amin(-1, keepdim=True)
    keep = (far > near + 0.5).squeeze(-1)
    origins, dirs, targets, near, far = origins[keep], dirs[keep], targets[keep], near[keep], far[keep]
    n_pool = origins.shape[0]
    delta_pool = (far - near) / n_samples
    density_scale = (res - 1) / 2.0  # one unit of density per voxel
    if sp is None:
        sp = SPConfig(enabled=sp_on, alpha0=2.0 / (res - 1), schedule="constant", boundary="reflect").setup(total_steps=10**6, bounds=(-1.0, 1.0))
        sp.train()

    def step():
        idx = torch.randint(0, n_pool, (n_rays,))
        delta = delta_pool[idx]
        t = near[idx] + delta * (torch.arange(n_samples) + torch.rand(n_rays, n_samples))
        pts = origins[idx, None] + t[..., None] * dirs[idx, None]
        pts = sp(pts)
        feats = F.grid_sample(grid, pts.view(1, 1, n_rays, n_samples, 3), align_corners=True)[0, :, 0]
        sigma = F.relu(feats[3]) * density_scale
        rgb = torch.sigmoid(feats[:3]).permute(1, 2, 0)
        alpha = 1 - torch.exp(-sigma * delta)
        trans = torch.cumprod(torch.cat([torch.ones(n_rays, 1), 1 - alpha + 1e-10], -1), -1)[:, :-1]
        w = alpha * trans
        color = (w[..., None] * rgb).sum(1) + (1 - w.sum(1, keepdim=True))
        loss = F.mse_loss(color, targets[idx])
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    return step


METHODS = {
    # method: (model settings that make a CPU step ~0.1-1 s, data layout)
    "sp-nerfacto": (dict(log2_hashmap_size=15, max_res=512, num_nerf_samples_per_ray=48), "blender"),
    "sp-neus-hashgrid": (dict(num_samples=32, num_samples_importance=16, num_up_sample_steps=2, background_model="none",
                              sdf_field=dict(num_levels=12, max_res=512, log2_hashmap_size=15, hidden_dim=64)), "sdfstudio"),
    "sp-mipnerf": (dict(num_coarse_samples=48, num_importance_samples=48, mlp_num_layers=4, mlp_layer_width=128), "blender"),
    "sp-relu-field": (dict(resolution=65, num_samples=128), "blender"),
}


def make_method_steps(name: str, scene, out, rays: int = 1024):
    """``(baseline_step, sp_step)``: training iterations of method ``name`` with SP off / on, from the
    same initial weights, with a constant alpha so every timed SP step perturbs."""
    import dataclasses

    from sp_plugins.nerfstudio.runs import configure_run, method_config

    settings, layout = METHODS[name]
    trainers = []
    for enabled in (False, True):
        config = method_config(name)
        model = config.pipeline.model
        for key, value in settings.items():
            if isinstance(value, dict):
                for k, v in value.items():
                    setattr(getattr(model, key), k, v)
            else:
                setattr(model, key, value)
        model.sp = dataclasses.replace(model.sp, enabled=enabled, schedule="constant", alpha_grid=False, num_samples=1)
        configure_run(config, scene / layout, steps=10**6, output_dir=out / f"{name}-{enabled}", rays_per_batch=rays)
        config.mixed_precision = False
        torch.manual_seed(0)
        trainer = config.setup(local_rank=0, world_size=1)
        trainer.setup()
        trainers.append(trainer)
    trainers[1].pipeline.model.load_state_dict(trainers[0].pipeline.model.state_dict(), strict=False)
    counters = [0, 0]

    def stepper(i: int):
        def step():
            trainer = trainers[i]
            for callback in trainer.callbacks:
                callback.run_callback_at_location(counters[i], location=_before())
            trainer.train_iteration(counters[i])
            counters[i] += 1

        return step

    return stepper(0), stepper(1)


def seam_only_ms(n_rays: int, n_samples: int, repeats: int) -> tuple:
    """``(seam_ms, noise_ms)``: the seam's copy of ``n_rays x n_samples`` RaySamples with moved
    origins (:func:`sp_plugins.nerfstudio.seam.perturbed_samples`), and the noise and fold alone."""
    from nerfstudio.cameras.rays import Frustums, RaySamples

    from sp_plugins.nerfstudio.seam import perturbed_samples

    sp = SPConfig(alpha0=0.02, schedule="constant", boundary="reflect").setup(total_steps=10**6, bounds=(-1.0, 1.0))
    sp.train()
    o = (torch.rand(n_rays, 1, 3) * 2 - 1).expand(n_rays, n_samples, 3)
    d = F.normalize(torch.randn(n_rays, 1, 3), dim=-1).expand(n_rays, n_samples, 3)
    t = torch.sort(torch.rand(n_rays, n_samples + 1), dim=-1).values[..., None]
    samples = RaySamples(Frustums(origins=o, directions=d, starts=t[:, :-1], ends=t[:, 1:], pixel_area=torch.ones(n_rays, n_samples, 1)),
                         camera_indices=torch.zeros(n_rays, n_samples, 1, dtype=torch.long))
    x = samples.frustums.get_positions().reshape(-1, 3)
    times = paired_timing({"seam": lambda: perturbed_samples(samples, sp), "noise": lambda: sp(x)}, repeats)
    return tuple(1e3 * sorted(times[k])[len(times[k]) // 2] for k in ("seam", "noise"))


def _before():
    from nerfstudio.engine.callbacks import TrainingCallbackLocation

    return TrainingCallbackLocation.BEFORE_TRAIN_ITERATION


def perturb_only_ms(n_points: int, repeats: int, alpha: float) -> float:
    """SP's own arithmetic (noise + reflection) on ``n_points`` points, in milliseconds."""
    sp = SPConfig(alpha0=alpha, schedule="constant", boundary="reflect").setup(total_steps=10**6, bounds=(-1.0, 1.0))
    sp.train()
    x = torch.rand(n_points, 3) * 2 - 1
    t = paired_timing({"perturb": lambda: sp(x)}, repeats)["perturb"]
    return 1e3 * sorted(t)[len(t) // 2]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=40)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--batch", type=int, default=2500, help="surface points (and as many free points) per SDF step")
    ap.add_argument("--only", choices=["sdf", "dense", "methods"], default=None)
    ap.add_argument("--methods", nargs="*", default=list(METHODS), choices=list(METHODS), help="methods of the 'methods' workload")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    results = {"machine": machine_info(), "workloads": {}}
    rows = []
    if args.only in (None, "sdf"):
        base, enc_name = make_sdf_step(False, args.batch)
        spst, _ = make_sdf_step(True, args.batch)
        s = ratio_summary(paired_timing({"baseline": base, "sp": spst}, args.repeats), "baseline")
        own = perturb_only_ms(2 * args.batch, args.repeats, 0.02)
        results["workloads"]["sdf"] = {"encoding": enc_name, "batch": 2 * args.batch, "perturb_only_ms": own, **s}
        s["perturb_only_ms"] = own
        rows.append((f"hash-grid SDF step ({2 * args.batch} pts, {enc_name})", s))
    if args.only in (None, "dense"):
        for res in (65, 129):
            s = ratio_summary(paired_timing({"baseline": make_dense_step(False, res), "sp": make_dense_step(True, res)}, args.repeats), "baseline")
            own = perturb_only_ms(1024 * 96, args.repeats, 2.0 / (res - 1))
            s["perturb_only_ms"] = own
            results["workloads"][f"dense{res}"] = {"rays": 1024, "samples": 96, "perturb_only_ms": own, **s}
            rows.append((f"dense-grid render step {res}^3 (1024 rays x 96)", s))
    if args.only in (None, "methods"):
        import tempfile
        from pathlib import Path

        from sp_plugins.data import make_tiny_scene

        tmp = Path(tempfile.mkdtemp(prefix="sp-overhead-"))
        scene = make_tiny_scene(tmp / "scene", mesh="sphere").root
        seam_ms, noise_ms = seam_only_ms(1024, 64, args.repeats)
        results["workloads"]["seam_alone"] = {"rays": 1024, "samples": 64, "seam_ms": seam_ms, "noise_and_fold_ms": noise_ms}
        for name in args.methods:
            base, spst = make_method_steps(name, scene, tmp)
            s = ratio_summary(paired_timing({"baseline": base, "sp": spst}, args.repeats), "baseline")
            s["perturb_only_ms"] = seam_ms
            results["workloads"][name] = {"rays": 1024, **s}
            rows.append((f"{name} training step (1024 rays, SP on vs off; last column: the seam's copy of 1024 x 64 samples)", s))
    results["machine_after"] = machine_info()["loadavg_1_5_15"]
    path = write_json("sp_overhead", results)
    print("| workload | baseline ms | SP ms | SP / baseline (median of pairs) | SP arithmetic alone |\n|---|---|---|---|---|")
    for name, s in rows:
        base_ms = 1e3 * s["baseline"]["median_s"]
        print(
            f"| {name} | {base_ms:.1f} | {1e3 * s['sp']['median_s']:.1f} | {s['sp']['ratio_vs_baseline']:.3f} "
            f"| {s['perturb_only_ms']:.2f} ms ({100 * s['perturb_only_ms'] / base_ms:.1f}%) |"
        )
    print(f"\nload average before/after: {results['machine']['loadavg_1_5_15']} / {results['machine_after']}; wrote {path}")


if __name__ == "__main__":
    main()
