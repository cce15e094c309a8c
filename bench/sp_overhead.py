"""SP's per-step cost: baseline and SP training steps alternated in one process.

Two workloads, both at CPU scale:

- ``sdf``: a hash-grid SDF step (encoding + 2x64 MLP, SIREN-style surface/eikonal loss with the
  eikonal gradient by double backward, Adam), SP perturbing every query point.
- ``dense``: a ReLU-field render step (RGB + density grid, trilinear, ReLU, 1024 rays x 96
  samples, white background, MSE, Adam), SP perturbing every sample with reflection.

Usage: ``python -m bench.sp_overhead [--repeats 40] [--threads 2]``
Writes ``bench/out/sp_overhead.json`` and prints a markdown table.
"""

from __future__ import annotations

import argparse
import torch
import torch.nn.functional as F
from torch import nn

from bench.common import machine_info, paired_timing, ratio_summary, write_json
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
    ap.add_argument("--only", choices=["sdf", "dense"], default=None)
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
