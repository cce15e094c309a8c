"""A sweep's trial runs in a Ray worker that only starts a subprocess and reads its results: importing
the trial runner and the soundness check must not import torch (2-5 s and some hundred MB per worker;
it did through ``sp_plugins/__init__`` and ``sp_plugins/geometry/__init__`` until both loaded their
names on first use). The public names still import as documented."""

from __future__ import annotations

import subprocess
import sys


def _modules_after(code: str) -> set:
    out = subprocess.run([sys.executable, "-c", code + "\nimport sys; print(' '.join(sys.modules))"],
                         capture_output=True, text=True, timeout=120, check=True).stdout
    return set(out.split())


def test_the_trial_runner_and_soundness_check_do_not_import_torch():
    loaded = _modules_after("import sp_plugins.sweeps.trial, sp_plugins.sweeps.soundness, sp_plugins.sweeps.report\n"
                            "from sp_plugins.geometry import Frame, load_mesh, sample_surface")
    assert "sp_plugins.sweeps.trial" in loaded and "trimesh" in loaded
    assert "torch" not in loaded, sorted(m for m in loaded if m.startswith(("torch", "sp_plugins")))


def test_the_public_names_still_import_from_the_package():
    loaded = _modules_after("from sp_plugins import AlphaGrid, AlphaSchedule, SPConfig, StochasticPreconditioner, perturb\n"
                            "import sp_plugins, sp_plugins.geometry as g\n"
                            "assert all(callable(getattr(g, n)) for n in g.__all__)\n"
                            "assert set(sp_plugins.__all__) <= set(dir(sp_plugins))\n"
                            "assert sp_plugins.perturb is __import__('sp_plugins.core', fromlist=['x']).perturb\n"
                            "try:\n    sp_plugins.nothing\nexcept AttributeError as e:\n    assert 'nothing' in str(e)\n"
                            "else:\n    raise SystemExit('no AttributeError')")
    assert "torch" in loaded and "sp_plugins.core.perturb" in loaded
