"""The docs' CPU recipe (docs/guides/real-captures.md) as a user outside a source checkout runs
it: its ``$(...)`` prints the package's flags, and ns-train's own parser takes them for each method."""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from sp_plugins.nerfstudio.recipes import RECIPES

PAGE = Path(__file__).resolve().parents[2] / "docs" / "guides" / "real-captures.md"


def _readme_recipe_call() -> str:
    (call,) = set(re.findall(r"\$\((python -m sp_plugins\.nerfstudio\.recipes [^)]*)\)", PAGE.read_text()))
    return call


def test_the_readme_recipe_prints_its_flags_outside_a_checkout(tmp_path):
    """It was ``python -m bench.fox_nerfacto --print-flags``: ``bench`` exists only in a checkout."""
    call = _readme_recipe_call()
    env = dict(os.environ, OMP_NUM_THREADS="1", PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}")
    env.pop("PYTHONPATH", None)
    proc = subprocess.run(["bash", "-c", f"set -e; flags=$({call}); printf '%s\\n' \"$flags\""], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and not proc.stderr.strip(), proc.stderr
    name = shlex.split(call)[-1]
    assert shlex.split(proc.stdout) == RECIPES[name].argv()


@pytest.mark.parametrize("name", sorted(RECIPES))
def test_ns_train_takes_the_recipe_for_each_of_its_methods(name, tmp_path):
    import tyro
    from nerfstudio.configs.method_configs import AnnotatedBaseConfigUnion

    recipe = RECIPES[name]
    for method in recipe.methods:
        config = tyro.cli(AnnotatedBaseConfigUnion, args=[method, *recipe.argv(), "instant-ngp-data", "--data", str(tmp_path)])
        for key, value in recipe.flags.items():
            got = config
            for part in key.replace("-", "_").split("."):
                got = getattr(got, part)
            assert got == value, (method, key, got)
