"""Adapter or scale? SP done by hand, beside the adapter's SP, on the same field.

Where the failure search finds a baseline that fails and SP that does not reliably rescue it, the
cause could be our adapter (SP entering NeuS wrongly, or not at all) or the scale (a CPU-sized
scene on which SP has little to act on). This bench tells them apart by training three runs side
by side from the same weights on the same rays (``bench.failure_regime.run_pair``):

- ``neus-hashgrid``: the baseline;
- ``sp-neus-hashgrid``: SP through our adapter (the field perturbs its own queries);
- ``direct-sp-neus-hashgrid``: the baseline's model and field with the adapter switched off; this
  module's :class:`DirectSPNeuSModel` moves every sample's position to ``perturb(x, alpha)``
  (:func:`sp_plugins.core.perturb`, the paper's ``x + alpha * N(0, I)``, reflected into the scene
  box) before the field is queried, with its own alpha schedule and its own noise generator seeded
  as the adapter's.

If the adapter puts exactly ``x + alpha * N(0, I)`` into every query the host makes while
training, and nothing else, the two SP runs draw the same noise and follow the same trajectory up
to float rounding (the hand-made shift moves ray origins, the adapter moves the positions: the sums
round differently), and their results agree as closely as SP runs of one seed can. A gap between
them is a defect of the adapter; agreement leaves the scale as the reason for what SP does here.

Usage::

    python -m bench.failure_direct                       # x-direct (q-grid-lr-1e-1, Spot, seed 0)
    python -m bench.failure_direct --settings x-direct x-direct-s2

Results: one JSON per setting in ``bench/out/failure_regime/`` (as the failure search's), and a
table of the three runs with the largest loss difference between the two SP runs.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import Dict, List, Type

import torch
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.field_components.field_heads import FieldHeadNames

from bench import failure_regime as fr
from bench.harness.common import OUT_DIR, done_or_run, machine_info, start
from bench.harness.metrics import table
from sp_plugins.core import perturb
from sp_plugins.core.schedule import AlphaSchedule
from sp_plugins.nerfstudio.neus import SPNeuSModel, SPNeuSModelConfig

DIRECT = "direct-sp-neus-hashgrid"
TRIPLE = ("neus-hashgrid", "sp-neus-hashgrid", DIRECT)


@dataclasses.dataclass
class DirectSPNeuSModelConfig(SPNeuSModelConfig):
    """The baseline NeuS (its ``sp`` must stay disabled) with SP done by :class:`DirectSPNeuSModel`."""

    _target: Type = dataclasses.field(default_factory=lambda: DirectSPNeuSModel)
    direct_alpha0: float = 0.013
    direct_end: float = 0.2
    """a fraction of training (as the SP config's ``end``)"""
    direct_total_steps: int = 300
    direct_seed: int = 0


class DirectSPNeuSModel(SPNeuSModel):
    """Perturbs in the model's sample-and-forward step, outside the field: the field sees ray
    samples whose start positions are ``perturb(x, alpha)`` and never knows."""

    config: DirectSPNeuSModelConfig

    def populate_modules(self) -> None:
        super().populate_modules()
        if self.config.sp.enabled:
            raise ValueError("DirectSPNeuSModel perturbs by itself: keep --pipeline.model.sp.enabled False")
        c = self.config
        self.direct_schedule = AlphaSchedule.resolve("exponential", c.direct_alpha0, end=c.direct_end,
                                                     total_steps=c.direct_total_steps, final_ratio=c.sp.final_ratio)
        self.direct_alpha = self.direct_schedule(0)
        self.direct_generator = torch.Generator().manual_seed(c.direct_seed)
        self.direct_bounds = self.scene_box.aabb.detach().float().cpu()

    def get_training_callbacks(self, training_callback_attributes: TrainingCallbackAttributes) -> List[TrainingCallback]:
        def set_alpha(step: int) -> None:
            self.direct_alpha = self.direct_schedule(step)

        return super().get_training_callbacks(training_callback_attributes) + [
            TrainingCallback([TrainingCallbackLocation.BEFORE_TRAIN_ITERATION], set_alpha, update_every_num_iters=1)
        ]

    def sample_and_forward_field(self, ray_bundle) -> Dict:
        ray_samples = self.sampler(ray_bundle, sdf_fn=self.field.get_sdf)
        queried = ray_samples
        if self.training and self.direct_alpha > 0:
            x = ray_samples.frustums.get_start_positions()
            q = perturb(x.reshape(-1, 3), self.direct_alpha, boundary="reflect", bounds=self.direct_bounds,
                        generator=self.direct_generator).view_as(x)
            frustums = dataclasses.replace(ray_samples.frustums, origins=ray_samples.frustums.origins + (q - x))
            queried = dataclasses.replace(ray_samples, frustums=frustums)
        field_outputs = self.field(queried, return_alphas=True)
        weights, transmittance = ray_samples.get_weights_and_transmittance_from_alphas(field_outputs[FieldHeadNames.ALPHA])
        return {"ray_samples": ray_samples, "field_outputs": field_outputs, "weights": weights,
                "bg_transmittance": transmittance[:, -1, :]}


def make_config(name: str, data: Path, setting: fr.Setting, out: Path, tag: str):
    """``bench.failure_regime.make_config``, plus the hand-made SP run built from the baseline's config."""
    if name != DIRECT:
        return fr.make_config(name, data, setting, out, tag)
    config = fr.make_config(TRIPLE[0], data, setting, out, f"direct-{tag}")
    host = config.pipeline.model
    sp_run = fr.make_config(TRIPLE[1], data, setting, out, tag).pipeline.model.sp  # the alpha0 / end the SP run uses
    fields = {f.name: getattr(host, f.name) for f in dataclasses.fields(SPNeuSModelConfig) if f.name != "_target"}
    config.pipeline.model = DirectSPNeuSModelConfig(**fields, direct_alpha0=sp_run.alpha0, direct_end=sp_run.end,
                                                    direct_total_steps=setting.steps, direct_seed=setting.seed)
    return config


SETTINGS: Dict[str, fr.Setting] = {
    # where the baseline fails and the adapter's SP run was ahead (seed 0) or behind (seed 2)
    "x-direct": fr.SETTINGS["q-grid-lr-1e-1"],
    "x-direct-s2": fr.SETTINGS["q-lr1-s2"],
}


def max_loss_gap(result: dict, steps: int, runs=TRIPLE[1:]) -> float:
    """Largest loss difference between two runs (default: adapter SP and direct SP) over the first ``steps``."""
    a, b = (result[name]["losses"][:steps] for name in runs)
    return max(abs(u - v) for u, v in zip(a, b))


def summarise(result: dict) -> str:
    lines = [table(["run", "PSNR (object)", "Chamfer", "NC", "final loss"],
                   [(name, f"{m['psnr']:.2f} ({m['psnr_object']:.2f})", f"{m['chamfer']:.4f}", f"{m['normal_consistency']:.3f}",
                     f"{m['final_loss']:.4f}") for name in TRIPLE for m in [result[name]]])]
    gaps = ", ".join(f"first {k}: {max_loss_gap(result, k):.2e}" for k in (1, 10, 50, len(result[TRIPLE[1]]["losses"])))
    base_gap = max_loss_gap(result, 10, runs=TRIPLE[:2])
    lines.append(f"\nlargest |loss(adapter SP) - loss(direct SP)| over the {gaps} steps "
                 f"(baseline vs adapter SP over the first 10: {base_gap:.2e})")
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--settings", nargs="+", default=["x-direct"], choices=sorted(SETTINGS))
    parser.add_argument("--out", type=Path, default=OUT_DIR / "failure_regime")
    parser.add_argument("--overwrite", action="store_true")
    args = parser.parse_args(argv)
    start(1, quiet=("nerfstudio", "PIL", "trimesh"))
    args.out.mkdir(parents=True, exist_ok=True)
    for setting, tag in fr.settings_to_run(args.settings, settings=SETTINGS):
        result, _ = done_or_run(args.out / f"{tag}.json", args.overwrite,
                                lambda: fr.run_pair(setting, args.out, tag, names=TRIPLE, make=make_config))
        print(f"{tag}\n{summarise(result)}", flush=True)
    print(f"machine: {machine_info()}")


if __name__ == "__main__":
    main()
