"""``SPRun``: SP's lifecycle for a plain training loop. Its docstring's example and the docs page's loop run as
written (the page's printed numbers included); the reach check, the baseline, evaluation, the alpha grid's
optimizer and a resumed run that continues as the uninterrupted one."""

from __future__ import annotations

import doctest
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from sp_plugins import SPConfig, SPRun
from sp_plugins.core import run as run_module
from sp_plugins.core.run import SPNotReached

PAGE = Path(__file__).resolve().parents[2] / "docs" / "guides" / "own-loop.md"


def test_the_docstring_example_runs():
    result = doctest.testmod(run_module, optionflags=doctest.ELLIPSIS)
    assert result.attempted >= 8 and result.failed == 0


def test_the_docs_page_loop_prints_what_the_page_states(tmp_path):
    text = PAGE.read_text()
    (code,) = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    (stated,) = re.findall(r"```text\n(.*?)```", text, flags=re.S)
    (tmp_path / "loop.py").write_text(code)
    proc = subprocess.run([sys.executable, "loop.py"], cwd=tmp_path, capture_output=True, text=True, timeout=300,
                          env={"OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"})
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout == stated
    assert "better" in stated


def _loop(sp: SPRun, steps: int, start: int = 0, weights=None, call_sp: bool = True):
    w = weights if weights is not None else torch.nn.Parameter(torch.ones(4, 3))
    optimizer = torch.optim.SGD([w], lr=0.1)
    seen = []
    for step in range(start, steps):
        sp.step_pre(step)
        x = torch.linspace(-1, 1, 12).view(4, 3)
        xs = sp(x) if call_sp else x
        seen.append(xs.detach().clone())
        loss = (w * xs).sum() ** 2
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        sp.step_post(step)
    return w, seen


def test_positions_move_while_alpha_is_positive_and_never_in_evaluation_or_the_baseline():
    sp = SPRun(SPConfig(alpha0=0.1, schedule="step", end=0.5, boundary="none", seed=3), total_steps=10)
    _, seen = _loop(sp, 10)
    x = torch.linspace(-1, 1, 12).view(4, 3)
    assert all(not torch.equal(s, x) for s in seen[:5]) and all(torch.equal(s, x) for s in seen[5:])
    assert sp.alpha == 0.0 and sp.step_index == 9
    sp.step_pre(0)
    assert sp.alpha == pytest.approx(0.1) and sp.eval()(x) is x and sp.train()(x) is not x
    off = SPRun(SPConfig(enabled=False), total_steps=10, bounds=(-1.0, 1.0))
    off.step_pre(0)
    assert off(x) is x and off.metrics() == {"sp_alpha": 0.0}


def test_noise_is_gaussian_with_the_scheduled_alpha():
    sp = SPRun(SPConfig(alpha0=0.05, schedule="constant", boundary="none", seed=0), total_steps=10)
    sp.step_pre(0)
    x = torch.zeros(200_000, 3)
    d = sp(x) - x
    assert d.mean().abs() < 1e-3 and d.std().item() == pytest.approx(0.05, rel=0.01)
    assert sp.metrics() == {"sp_alpha": pytest.approx(0.05)}


def test_a_loop_that_never_hands_the_field_sp_x_is_stopped_at_the_first_sp_step():
    sp = SPRun(SPConfig(alpha0=0.1, end=0.5, boundary="none"), total_steps=10)
    with pytest.raises(SPNotReached, match=r"SP was on at step 0 .* hand the field sp\(x\)"):
        _loop(sp, 10, call_sp=False)
    _loop(SPRun(SPConfig(enabled=False), total_steps=10, bounds=(-1.0, 1.0)), 10, call_sp=False)  # nothing to reach


def test_a_resumed_run_ends_as_the_uninterrupted_one():
    config = SPConfig(alpha0=0.2, end=0.8, boundary="reflect", seed=5)
    straight, _ = _loop(SPRun(config, total_steps=8, bounds=(-1.0, 1.0)), 8)
    first = SPRun(config, total_steps=8, bounds=(-1.0, 1.0))
    w, _ = _loop(first, 4)
    state = {"w": w.detach().clone(), "sp": first.state_dict()}
    resumed = SPRun(config, total_steps=8, bounds=(-1.0, 1.0))
    resumed.load_state_dict(state["sp"])
    assert resumed.step_index == 3
    w2, _ = _loop(resumed, 8, start=4, weights=torch.nn.Parameter(state["w"]))
    assert torch.equal(w2, straight)  # SP's noise, step and schedule continued where they stopped


def test_the_alpha_grid_is_learned_by_its_own_optimizer_and_saved():
    config = SPConfig(alpha0=0.05, end=0.5, alpha_grid=True, alpha_grid_resolution=4, alpha_grid_lr=0.1, seed=0)
    sp = SPRun(config, total_steps=6, bounds=(-1.0, 1.0))
    assert sp.optimizer is not None and len(list(sp.parameters())) == 1
    before = next(sp.parameters()).detach().clone()
    _loop(sp, 2)
    after = next(sp.parameters()).detach()
    assert not torch.equal(before, after)  # the grid's Adam stepped it
    assert "sp_alpha_grid_mean" in sp.metrics()
    state = sp.state_dict()
    assert set(state) == {"preconditioner", "optimizer"} and state["optimizer"]["state"]
