"""Opening a run folder never runs its code, under sdfstudio.

- every sdfstudio method config (sdfstudio's own and ours) and a real run's ``config.yml`` load with
  the restricted loader as with PyYAML's full loader;
- sdfstudio's ``eval_setup`` and its ``scripts/train.py`` main read ``config.yml`` through it
  inside our commands;
- the checkpoint patch allows numpy numbers only: a numpy string scalar and a pickled callable are
  refused in its loads, the callable in one line;
- ``sp-sdfstudio-extract-mesh --load-config`` and ``sp-sdfstudio-train --trainer.load-config``:
  the one-line ``os.system`` config creates nothing and is refused in one line; a real run loads.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
import yaml

from tests.helpers.sdf_configs import BIN, env, tiny_config, train_in_process

from sp_plugins.adapter.safe_config import ConfigRefused, RunConfigLoader, load_run_config, reading_configs_safely


class _Touch:
    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


@pytest.fixture(scope="module")
def trained(patched, sdf_scene, tmp_path_factory) -> Path:
    """config.yml of a 2-step sp-neus run (sdfstudio's trainer, in this process)."""
    from nerfstudio.configs.method_configs import method_configs

    config = tiny_config(method_configs["sp-neus"], sdf_scene, tmp_path_factory.mktemp("trained"), steps=2)
    config.save_config()
    train_in_process(config)
    return config.get_base_dir() / "config.yml"


def test_every_sdfstudio_method_config_loads_as_with_the_full_loader(patched):
    from nerfstudio.configs.base_config import Config
    from nerfstudio.configs.method_configs import method_configs

    assert len(method_configs) >= 40 and "sp-neus-facto" in method_configs and "bakedangelo" in method_configs
    for name, config in method_configs.items():
        text = yaml.dump(config)  # what save_config writes
        ours = yaml.load(text, Loader=RunConfigLoader)
        assert isinstance(ours, Config) and ours == yaml.load(text, Loader=yaml.Loader), name


def test_a_real_run_loads_and_the_hosts_reads_go_through_the_restricted_loader(trained, tmp_path):
    from nerfstudio.configs.base_config import Config
    from nerfstudio.utils import eval_utils

    import scripts.train as host_train

    assert load_run_config(trained, expect=Config) == yaml.load(trained.read_text(), Loader=yaml.Loader)
    with reading_configs_safely(eval_utils, f"--load-config {trained}") as proxy:
        config, pipeline, checkpoint = eval_utils.eval_setup(trained)
    assert proxy.loads == 1 and checkpoint.name == "step-000000001.ckpt" and pipeline.model.sp is not None

    marker = tmp_path / "marker"
    bad = tmp_path / "config.yml"
    bad.write_text(f'!!python/object/apply:os.system ["touch {marker}"]\n')
    config.trainer.load_config = bad
    with reading_configs_safely(host_train, f"--trainer.load-config {bad}") as proxy:
        with pytest.raises(ConfigRefused, match="would call os.system"):
            host_train.main(config)
    assert proxy.loads == 1 and not marker.exists()


def test_the_checkpoint_patch_allows_numpy_numbers_only(patched, tmp_path):
    from nerfstudio.utils import eval_utils

    from sp_plugins.adapter.errors import describe_failure
    from sp_plugins.patches.sdfstudio_checkpoint_load import numpy_scalar_globals

    allowed = {getattr(g, "__name__", "") for g in numpy_scalar_globals()}
    assert {"dtype", "scalar", "Float64DType", "Int64DType", "BoolDType"} <= allowed
    assert not allowed & {"ObjectDType", "StrDType", "BytesDType", "VoidDType", "TimeDelta64DType", "DateTime64DType"}

    class Pipeline:
        def load_pipeline(self, state):
            self.loaded = state

    def load(payload) -> Path:
        folder = tmp_path / f"models-{len(list(tmp_path.iterdir()))}"
        folder.mkdir()
        torch.save({"step": 1, "pipeline": payload}, folder / "step-000000001.ckpt")
        return eval_utils.eval_load_checkpoint(SimpleNamespace(load_dir=folder, load_step=None), Pipeline())

    assert load({"lr": np.float64(0.5), "n": np.int64(3)}).name == "step-000000001.ckpt"
    with pytest.raises(Exception, match="StrDType|Weights only load failed"):
        load({"s": np.str_("x")})
    marker = tmp_path / "marker"
    try:
        load({"x": _Touch(marker)})
    except Exception as exc:  # noqa: BLE001
        message = describe_failure(exc)
    else:
        raise AssertionError("a checkpoint carrying os.system loaded")
    assert "holds a pickled posix.system" in message and "\n" not in message and not marker.exists()


def _one_line(proc, prog: str, *says: str) -> str:
    report = f"rc={proc.returncode}\n--- stderr\n{proc.stderr[-3000:]}\n--- stdout\n{proc.stdout[-1500:]}"
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, report
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert lines and lines[-1].startswith(f"{prog}: error: "), report
    assert sum(": error: " in line for line in lines) == 1, report
    for word in says:
        assert word in lines[-1], f"{word!r} not in the error line\n{report}"
    return lines[-1]


def test_our_sdfstudio_commands_refuse_a_hostile_config_and_load_a_real_one(trained, tmp_path):
    marker = tmp_path / "marker"
    hostile = tmp_path / "hostile" / "config.yml"
    hostile.parent.mkdir()
    hostile.write_text(f'!!python/object/apply:os.system ["touch {marker}"]\n')
    # a copy of the run to resume from its config (sdfstudio writes the loaded run's folder again)
    copy_root = tmp_path / "copy"
    shutil.copytree(trained.parents[3], copy_root)
    copy = copy_root / trained.relative_to(trained.parents[3])
    config = load_run_config(copy)
    config.output_dir = copy_root
    copy.write_text(yaml.dump(config))
    runs = {
        "mesh-os.system": ["sp-sdfstudio-extract-mesh", "--load-config", hostile, "--output-path", tmp_path / "m1" / "m.ply"],
        "train-os.system": ["sp-sdfstudio-train", "sp-neus", "--machine.num-gpus", "0", "--trainer.load-config", hostile],
        "mesh-real": ["sp-sdfstudio-extract-mesh", "--load-config", trained, "--resolution", "24",
                      "--output-path", tmp_path / "m2" / "m.ply"],
        "train-real": ["sp-sdfstudio-train", "sp-neus", "--machine.num-gpus", "0", "--trainer.load-config", copy],
    }
    started = {name: subprocess.Popen([str(BIN / args[0]), *map(str, args[1:])], env=env(), stdout=subprocess.PIPE,
                                      stderr=subprocess.PIPE, text=True, cwd=tmp_path) for name, args in runs.items()}
    procs = {}
    for name, proc in started.items():
        out, err = proc.communicate(timeout=600)
        procs[name] = SimpleNamespace(returncode=proc.returncode, stdout=out, stderr=err)
    assert not marker.exists(), "a command ran what a file named"
    _one_line(procs["mesh-os.system"], "sp-sdfstudio-extract-mesh", f"--load-config {hostile}: refused line 1",
              "!!python/object/apply:os.system", "would call os.system")
    _one_line(procs["train-os.system"], "sp-sdfstudio-train", f"--trainer.load-config {hostile}: refused line 1",
              "!!python/object/apply:os.system", "would call os.system")
    assert not (tmp_path / "m1").exists()
    for name in ("mesh-real", "train-real"):
        assert procs[name].returncode == 0, f"[{name}]\n{procs[name].stderr[-3000:]}"
    assert (tmp_path / "m2" / "m.ply").is_file()
    assert "Loading pre-set config from" in procs["train-real"].stdout
