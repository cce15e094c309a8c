"""CPU recipes: the ``ns-train`` flags that shrink a GPU-sized preset to what a CPU trains in minutes.

    python -m sp_plugins.nerfstudio.recipes                  # list them
    python -m sp_plugins.nerfstudio.recipes nerfacto-cpu     # one, as ns-train flags

    ns-train sp-nerfacto --machine.device-type cpu ... $(python -m sp_plugins.nerfstudio.recipes nerfacto-cpu) \\
        instant-ngp-data --data fox

They live in the package (not in ``bench/``, which only a source checkout has) so the README's
recipes work wherever sp-plugins is installed; ``bench/fox_nerfacto.py`` measures this same table.
Importing this module imports no host.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from typing import Dict, List, Mapping, Optional, Sequence, Tuple, Union

from sp_plugins.nerfstudio import table

Value = Union[bool, int, float, str, Tuple[int, ...]]


@dataclass(frozen=True)
class Recipe:
    """Flags (without the leading dashes) over a method's own settings, and what they are for."""

    methods: Tuple[str, ...]
    about: str
    flags: Mapping[str, Value]

    def argv(self) -> List[str]:
        """The flags as ``ns-train`` takes them (a tuple is one flag with several values)."""
        out: List[str] = []
        for key, value in self.flags.items():
            out.append(f"--{key}")
            out.extend(str(v) for v in (value if isinstance(value, tuple) else (value,)))
        return out


RECIPES: Dict[str, Recipe] = {
    "nerfacto-cpu": Recipe(
        methods=(table.SP_NERFACTO, table.NERFACTO),
        about="a real capture on one CPU core: 256 rays, a 2^17 table, 32 field and 64/32 proposal samples per ray "
              "(the fox: 0.29 s per step)",
        flags={
            "pipeline.datamanager.train-num-rays-per-batch": 256,
            "pipeline.model.log2-hashmap-size": 17,
            "pipeline.model.num-nerf-samples-per-ray": 32,
            "pipeline.model.num-proposal-samples-per-ray": (64, 32),
            "pipeline.model.eval-num-rays-per-chunk": 4096,
        },
    ),
    "nerfacto-object": Recipe(
        methods=(table.SP_NERFACTO, table.NERFACTO),
        about="an object on a white background seen from a ring of cameras (Blender scenes, `sp-scene`): nerfstudio's "
              "and nerfbaselines' Blender settings (near 2 / far 6 for cameras about 4 units out, white background, "
              "no scene contraction, no appearance embedding, camera optimizer or distortion loss)",
        flags={
            "pipeline.model.near-plane": 2.0,
            "pipeline.model.far-plane": 6.0,
            "pipeline.model.background-color": "white",
            "pipeline.model.disable-scene-contraction": True,
            "pipeline.model.proposal-initial-sampler": "uniform",
            "pipeline.model.distortion-loss-mult": 0.0,
            "pipeline.model.use-appearance-embedding": False,
            "pipeline.model.average-init-density": 1.0,
            "pipeline.model.camera-optimizer.mode": "off",
        },
    ),
}


def main(argv: Optional[Sequence[str]] = None) -> int:
    prog = "python -m sp_plugins.nerfstudio.recipes"
    parser = argparse.ArgumentParser(prog=prog, description="Print a CPU recipe as ns-train flags (no name: list them).")
    parser.add_argument("name", nargs="?", help=f"one of: {', '.join(RECIPES)}")
    args = parser.parse_args(argv)
    if args.name is None:
        for name, recipe in RECIPES.items():
            print(f"{name}: {recipe.about}; for {', '.join(recipe.methods)}")
        return 0
    if args.name not in RECIPES:  # on stderr: $(...) then adds nothing to the command
        print(f"{prog}: error: no recipe {args.name!r}; known: {', '.join(RECIPES)}", file=sys.stderr)
        return 2
    print(" ".join(RECIPES[args.name].argv()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
