"""The same method, seed and steps through ``ns-train`` and through nerfbaselines: the loss curves
.

``ns-train sp-nerfacto ... blender-data`` (its ``Train Loss`` every step, from its tensorboard
events) against nerfbaselines' ``python`` backend building ``sp-nerfacto`` from its spec with the
same settings (the spec's ``sp-scene`` preset given to ns-train as flags) and the same seed, each
step's ``loss`` from ``train_iteration`` (nerfbaselines' own ``train`` command logs 100-step means).

    python -m bench.nerfbaselines_loss [--steps 60] [--out bench/out/nerfbaselines_loss]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

BIN = Path(sys.executable).parent
SETTINGS = {  # what the spec's sp-scene preset sets, plus the CPU budget
    "machine.device_type": "cpu", "pipeline.datamanager.train_num_rays_per_batch": 256,
    "pipeline.model.near_plane": 2.0, "pipeline.model.far_plane": 6.0, "pipeline.model.use_appearance_embedding": False,
    "pipeline.model.background_color": "white", "pipeline.model.proposal_initial_sampler": "uniform",
    "pipeline.model.distortion_loss_mult": 0.0, "pipeline.model.disable_scene_contraction": True,
    "pipeline.model.average_init_density": 1.0, "pipeline.model.camera_optimizer.mode": "off",
    "pipeline.model.log2_hashmap_size": 12, "pipeline.model.max_res": 64, "pipeline.model.hidden_dim": 16,
    "pipeline.model.num_nerf_samples_per_ray": 16,
}


def ns_train(scene: Path, out: Path, steps: int) -> np.ndarray:
    flags = []
    for key, value in SETTINGS.items():
        flags += ["--" + key.replace("_", "-"), str(value)]
    never = str(10 * steps)
    shutil.rmtree(out, ignore_errors=True)
    subprocess.run([str(BIN / "ns-train"), "sp-nerfacto", "--vis", "tensorboard", "--max-num-iterations", str(steps),
                    "--logging.steps-per-log", "1", "--steps-per-eval-batch", never, "--steps-per-eval-image", never,
                    "--steps-per-eval-all-images", never, "--steps-per-save", never, "--output-dir", str(out),
                    "--timestamp", "t", *flags, "blender-data", "--data", str(scene)], check=True,
                   env=dict(os.environ, OMP_NUM_THREADS="1"))
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    (events,) = out.glob("**/events.out.tfevents.*")
    acc = EventAccumulator(str(events.parent), size_guidance={"scalars": 0})
    acc.Reload()
    return np.array([e.value for e in sorted(acc.Scalars("Train Loss"), key=lambda e: e.step)])


def nerfbaselines_train(scene: Path, steps: int) -> np.ndarray:
    import nerfbaselines
    from nerfbaselines.datasets import load_dataset

    spec = nerfbaselines.get_method_spec("sp-nerfacto")
    with nerfbaselines.build_method_class(spec, "python") as method_cls:
        info = method_cls.get_method_info()
        data = load_dataset(str(scene), split="train", features=info["required_features"],
                            supported_camera_models=info["supported_camera_models"], load_features=True)
        overrides = {"pipeline.datamanager.dataparser": "blender-data", "max_num_iterations": steps}
        overrides.update({k: str(v) for k, v in SETTINGS.items()})  # as --set hands them over: strings
        method = method_cls(train_dataset=data, config_overrides=overrides)
        return np.array([method.train_iteration(step)["loss"] for step in range(steps)])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--out", type=Path, default=Path("bench/out/nerfbaselines_loss"))
    parser.add_argument("--scene", type=Path, default=None, help="a Blender layout (default: sp-scene spot, 64 px)")
    args = parser.parse_args()
    scene = args.scene
    if scene is None:
        scene = args.out / "spot" / "blender"
        if not (scene / "nb-info.json").exists():
            subprocess.run([str(BIN / "sp-scene"), "spot", str(scene.parent), "--overwrite", "--quiet"], check=True)
    os.environ["OMP_NUM_THREADS"] = "1"
    import torch

    torch.set_num_threads(1)
    ns = ns_train(scene, args.out / "ns-train", args.steps)
    nb = nerfbaselines_train(scene, args.steps)
    diff = np.abs(ns - nb)
    report = {"steps": args.steps, "ns_train": ns.tolist(), "nerfbaselines": nb.tolist(),
              "max_abs_diff": float(diff.max()), "max_rel_diff": float((diff / np.abs(ns)).max()),
              "first_differing_step": int(np.argmax(diff > 1e-6)) if (diff > 1e-6).any() else None}
    (args.out / "loss_curves.json").write_text(json.dumps(report, indent=1))
    print(json.dumps({k: v for k, v in report.items() if k not in ("ns_train", "nerfbaselines")}))


if __name__ == "__main__":
    main()
