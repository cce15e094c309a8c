"""bench/failure_direct.py at a toy size: SP done by hand outside the field follows the adapter's SP
run, and both leave the baseline's trajectory. A hook that stopped perturbing (or perturbed twice,
or with another alpha) would break the first assertion; a direct run that did nothing, the second."""

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the checkout: bench/ is not an installed package
import bench.failure_direct as fd
import bench.failure_regime as fr

TOY = fr.Setting(mesh="box", steps=6, views=6, test_views=1, resolution=(24, 18), rays=32, num_samples=8,
                 num_samples_importance=4, hidden_dim=16, num_levels=4, max_res=32, log2_hashmap_size=10,
                 background_mlp=(2, 16), mesh_resolution=16, warm_up_end=1, sp_alpha0=0.1, sp_end=0.5)


@pytest.fixture(scope="module")
def triple(tmp_path_factory):
    return fr.run_pair(TOY, tmp_path_factory.mktemp("direct"), "toy", names=fd.TRIPLE, make=fd.make_config)


def test_direct_perturbation_follows_the_adapter(triple):
    _, adapter, direct = (triple[name]["losses"] for name in fd.TRIPLE)
    assert len(adapter) == len(direct) == TOY.steps
    assert adapter[0] == pytest.approx(direct[0], abs=1e-6)  # the same noise on the same rays: the same loss
    assert fd.max_loss_gap(triple, TOY.steps) < 2e-3  # later steps: float rounding of two ways to add the offset
    assert fd.max_loss_gap(triple, TOY.steps, runs=fd.TRIPLE[:2]) > 1e-2  # ...while SP moves the run off the baseline's


def test_direct_config_takes_the_sp_runs_schedule_and_keeps_the_adapter_off(tmp_path):
    config = fd.make_config(fd.DIRECT, Path("unused"), TOY, tmp_path, "config")
    assert isinstance(config.pipeline.model, fd.DirectSPNeuSModelConfig)
    assert config.pipeline.model.direct_alpha0 == TOY.sp_alpha0 and config.pipeline.model.direct_end == TOY.sp_end
    assert config.pipeline.model.sp.enabled is False


def test_summary_names_the_three_runs_and_the_gap(triple):
    text = fd.summarise(triple)
    for name in fd.TRIPLE:
        assert f"| {name} |" in text
    assert "largest |loss(adapter SP) - loss(direct SP)|" in text


def test_cli_resumes_a_finished_setting_and_prints_its_table(triple, tmp_path):
    """`python -m bench.failure_direct` as a user runs it: a finished setting is not retrained, its table is printed."""
    import json
    import subprocess

    (tmp_path / "x-direct_steps300.json").write_text(json.dumps(triple))
    done = subprocess.run([sys.executable, "-m", "bench.failure_direct", "--out", str(tmp_path), "--settings", "x-direct"],
                          cwd=Path(__file__).resolve().parents[2], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "done already: x-direct_steps300.json" in done.stderr
    assert f"| {fd.DIRECT} |" in done.stdout and "largest |loss(adapter SP) - loss(direct SP)|" in done.stdout
