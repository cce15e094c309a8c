"""What torch's deterministic kernels cost a training step (``patches/torch_deterministic.py``).

One trainer per method; its steps alternate between deterministic kernels on and off
(``torch.use_deterministic_algorithms``), so load on the machine hits both alike. Methods:
nerfstudio's own nerfacto as ``sp-train`` builds it (its torch ``HashEncoding`` is where the
backward of ``table[index]`` needed the ordered kernel; its parallel data manager included) and
our ``sp-neus-hashgrid``, both with SP on.

Usage: ``python -m bench.speed.deterministic_cost [--repeats 20] [--threads 2] [--rays 256]``
Writes ``bench/out/deterministic_cost.json`` and prints a markdown table.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import torch

from bench.harness.common import machine_info, paired_timing, ratio_summary, write_json


def trainer_for(method: str, scene: Path, out: Path, rays: int):
    from sp_plugins.nerfstudio.runs import configure_run, method_config

    if method == "sp-train nerfacto":
        from nerfstudio.configs.method_configs import all_methods

        from sp_plugins.nerfstudio.registration import with_sp

        config = with_sp(all_methods["nerfacto"], name="nerfacto").config
        data = scene / "blender"
    else:
        config = method_config(method)
        data = scene / "sdfstudio"
    configure_run(config, data, steps=10**6, output_dir=out / method.replace(" ", "-"), rays_per_batch=rays)
    config.mixed_precision = False
    torch.manual_seed(0)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    return trainer


def steps_for(trainer):
    from nerfstudio.engine.callbacks import TrainingCallbackLocation

    counter = [0]

    def step(deterministic: bool):
        def run():
            torch.use_deterministic_algorithms(deterministic, warn_only=True)
            for callback in trainer.callbacks:
                callback.run_callback_at_location(counter[0], location=TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)
            trainer.train_iteration(counter[0])
            counter[0] += 1

        return run

    return {"default kernels": step(False), "deterministic kernels": step(True)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--rays", type=int, default=256, help="rays per step (the README recipes: 256)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    from sp_plugins.data import make_scene

    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        scene = make_scene("spot", Path(tmp) / "scene", resolution=64).root
        for method in ("sp-train nerfacto", "sp-neus-hashgrid"):
            times = paired_timing(steps_for(trainer_for(method, scene, Path(tmp), args.rays)), args.repeats)
            results[method] = ratio_summary(times, "default kernels")
            print(method, results[method], flush=True)
    torch.use_deterministic_algorithms(False)
    payload = {"results": results, "args": vars(args), "machine": machine_info()}
    write_json("deterministic_cost", payload)
    print(f"| method ({args.rays} rays, {args.threads} threads) | default s/step | deterministic s/step | ratio (median of pairs) |")
    print("|---|---|---|---|")
    for method, r in results.items():
        print(f"| {method} | {r['default kernels']['median_s']:.4f} | {r['deterministic kernels']['median_s']:.4f} | "
              f"{r['deterministic kernels']['ratio_vs_default kernels']:.3f} |")


if __name__ == "__main__":
    main()
