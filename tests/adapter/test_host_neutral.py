"""``sp_plugins.adapter`` imports no host: every module of it imports, and a host written
against it (tests/adapter/toy_host.py) builds and trains, in a process where neither nerfstudio nor
sdfstudio (both the package ``nerfstudio``, plus sdfstudio's ``scripts``) can be imported."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
ADAPTER = REPO / "sp_plugins" / "adapter"
HOSTS = ("nerfstudio", "scripts")

CODE = f"""
import importlib, importlib.abc, pkgutil, sys

class NoHost(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in {HOSTS!r}:
            raise ImportError(f"no host here: {{name}}")

sys.meta_path.insert(0, NoHost())
import sp_plugins.adapter
names = [m.name for m in pkgutil.walk_packages(sp_plugins.adapter.__path__, "sp_plugins.adapter.")]
for name in names:
    importlib.import_module(name)

from types import SimpleNamespace
from sp_plugins.adapter.callbacks import alpha_grid_optimizer
from sp_plugins.core import SPConfig
from tests.adapter.toy_host import ToySPModel, train_steps

model = ToySPModel(SimpleNamespace(sp=SPConfig(alpha0=0.1, schedule="exponential", end=0.5, boundary="reflect")))
train_steps(model, 3)
assert model.reach_checks == [0] and model.sp.step == 2, (model.reach_checks, model.sp.step)
assert alpha_grid_optimizer(SPConfig(alpha_grid_lr=0.5), dict)["optimizer"] == {{"lr": 0.5, "eps": 1e-15}}
hosts = sorted(m for m in sys.modules if m.split(".")[0] in {HOSTS!r})
print(len(names), "modules;", "hosts loaded:", hosts)
assert not hosts
"""


def test_the_adapter_imports_and_serves_a_host_with_no_host_importable():
    proc = subprocess.run([sys.executable, "-c", CODE], cwd=REPO, capture_output=True, text=True, timeout=300,
                          env={"OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin", "PYTHONPATH": str(REPO)})
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "modules; hosts loaded: []" in proc.stdout


def test_no_module_of_the_adapter_names_a_host_import_even_inside_a_function():
    found = []
    for path in sorted(ADAPTER.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""] if isinstance(node, ast.ImportFrom) else []
            found += [f"{path.name}:{node.lineno} {n}" for n in names if n.split(".")[0] in HOSTS]
    assert not found, found
