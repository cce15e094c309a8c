"""Opening a run folder never runs its code: our commands read ``config.yml`` with the
restricted loader (:mod:`sp_plugins.adapter.safe_config`) and checkpoints weights-only.

- every config ``ns-train`` / ``sp-train`` writes (each registered method of nerfstudio, ours, and
  sp-train's SP variants) and a real trained run's ``config.yml`` load as with PyYAML's full loader;
- anything else is refused in one line naming the file, the line, the tag and why, before any
  object is built (a loader that counts what it builds shows nothing was);
- the hosts' own reads of ``config.yml`` inside our commands (``eval_setup``, ``ns-train``'s main for
  ``--load-config``) go through the same loader;
- the console scripts (``sp-export-mesh``, ``sp-train --load-config``): the one-line
  ``os.system`` config creates nothing and is refused in one line; a checkpoint carrying a pickled
  callable is refused in one line (also with ``TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD=1`` set); a real run
  still loads.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
import yaml

from tests.helpers.ns_commands import ENV, command
from tests.helpers.ns_configs import tiny_sdf_config, run_recording

from sp_plugins.adapter.safe_config import ConfigRefused, RunConfigLoader, load_run_config, reading_configs_safely

METHOD = "sp-neus-hashgrid"


class _Touch:
    """Pickles as ``os.system("touch <marker>")``: what a hostile checkpoint carries."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def relocate(config_path: Path, root: Path) -> Path:
    """A copy of the run folder of ``config_path`` under ``root``, its config.yml pointing there."""
    base = config_path.parent
    dest = root / base.relative_to(base.parents[2])
    shutil.copytree(base, dest)
    config = load_run_config(dest / "config.yml")
    config.output_dir = root
    (dest / "config.yml").write_text(yaml.dump(config))
    return dest / "config.yml"


@pytest.fixture(scope="module")
def trained(tiny_scene, tmp_path_factory) -> Path:
    """config.yml of a 2-step sp-neus-hashgrid run (the real trainer, in this process)."""
    config = tiny_sdf_config(METHOD, tiny_scene, tmp_path_factory.mktemp("trained"), steps=2)
    run_recording(config)
    return config.get_base_dir() / "config.yml"


# -- what real runs write loads -----------------------------------------------------------------------


def test_a_config_yml_saved_with_our_sdf_fields_old_names_loads_with_either_loader():
    """An earlier release renamed our nerfstudio SDF field ``SPSDFField`` (it perturbs nothing itself) to
    ``CoarseToFineSDFField``; a run folder saved before names the old classes. The nerfstudio host's
    registry entry maps them (``Host.renamed``): our restricted reader and the host's own loader (``ns-eval``,
    ``ns-export``) both build the new classes; the module defines no alias."""
    from nerfstudio.configs.method_configs import all_methods

    import sp_plugins.nerfstudio.sdf_field as sdf_field
    from sp_plugins.nerfstudio.sdf_field import CoarseToFineSDFField, CoarseToFineSDFFieldConfig

    text = yaml.dump(all_methods["sp-neus-hashgrid"])
    assert "sdf_field.CoarseToFineSDFFieldConfig" in text and "SPSDFField" not in text
    old = text.replace("sdf_field.CoarseToFineSDFField", "sdf_field.SPSDFField")
    for loader in (RunConfigLoader, yaml.Loader):
        field = yaml.load(old, Loader=loader).pipeline.model.sdf_field
        assert type(field) is CoarseToFineSDFFieldConfig and field._target is CoarseToFineSDFField, loader
    assert "SPSDFField" not in vars(sdf_field)


def test_every_registered_method_config_loads_as_with_the_full_loader():
    from nerfstudio.configs.method_configs import all_descriptions, all_methods

    from sp_plugins.nerfstudio.registration import sp_methods

    configs, _, _ = sp_methods(all_methods, all_descriptions)
    everything = {**{f"ns-train {k}": v for k, v in all_methods.items()}, **{f"sp-train {k}": v for k, v in configs.items()}}
    assert len(everything) >= 60 and "ns-train sp-neus-hashgrid" in everything and "sp-train nerfacto" in everything
    for name, config in everything.items():
        text = yaml.dump(config)  # what save_config writes
        ours = yaml.load(text, Loader=RunConfigLoader)
        assert ours == yaml.load(text, Loader=yaml.Loader), name
        assert type(ours) is type(config), name


def test_a_trained_run_config_loads_as_with_the_full_loader(trained):
    text = trained.read_text()
    assert "!!python/object/apply:pathlib.PosixPath" in text and "!!python/object/apply:nerfstudio.utils.writer.EventName" in text
    assert load_run_config(trained) == yaml.load(text, Loader=yaml.Loader)


# -- anything else is refused before anything is built ----------------------------------------------------


class _Counting(RunConfigLoader):
    built = 0

    def construct_object(self, node, deep=False):
        type(self).built += 1
        return super().construct_object(node, deep)


REFUSED = {
    "os.system": ('!!python/object/apply:os.system ["touch {m}"]', "!!python/object/apply:os.system", "would call os.system"),
    "subprocess": ('!!python/object/apply:subprocess.Popen [["touch", "{m}"]]', "subprocess.Popen", "would call subprocess.Popen"),
    "host function": ('!!python/object/apply:nerfstudio.utils.scripts.run_command ["touch {m}"]',
                      "nerfstudio.utils.scripts.run_command", "which is not an enum"),
    "name of a function": ("a: !!python/name:nerfstudio.utils.scripts.run_command ''", "run_command", "not a class"),
    "name outside": ("a: !!python/name:builtins.eval ''", "!!python/name:builtins.eval", "outside the host's and sp-plugins'"),
    "object/new": ('!!python/object/new:os.system ["touch {m}"]', "!!python/object/new:os.system", "never holds"),
    "module": ("a: !!python/module:os ''", "!!python/module:os", "never holds"),
    "not a dataclass": ("!!python/object:nerfstudio.engine.trainer.Trainer {config: 1}", "nerfstudio.engine.trainer.Trainer",
                        "not a config dataclass"),
    "dunder key": ("!!python/object:sp_plugins.core.config.SPConfig {__class__: 1}", "sp_plugins.core.config.SPConfig",
                   "not a setting name"),
    "getitem outside": ("a: !!python/object/apply:_operator.getitem [!!python/name:os.system '', 1]",
                        "!!python/name:os.system", "outside the host's and sp-plugins'"),  # before os is imported
    "getitem of a function": ("a: !!python/object/apply:_operator.getitem [!!python/name:nerfstudio.utils.scripts.run_command '', 1]",
                              "_operator.getitem", "generic class"),
    "local tag": ("a: !touch {m}", "!touch", "not a tag"),
}


@pytest.mark.parametrize("case", sorted(REFUSED))
def test_a_file_naming_anything_else_is_refused_in_one_line_and_nothing_is_built(case, tmp_path):
    text, tag, why = REFUSED[case]
    marker = tmp_path / "marker"
    path = tmp_path / "config.yml"
    path.write_text(text.replace("{m}", str(marker)))
    _Counting.built = 0
    with pytest.raises(ConfigRefused) as refused:
        load_run_config(path)
    line = str(refused.value)
    assert "\n" not in line and line.startswith(f"--load-config {path}: refused line 1: the tag "), line
    assert tag in line and why in line, line
    with pytest.raises(Exception):
        yaml.load(path.read_text(), Loader=_Counting)
    assert _Counting.built == 0 and not marker.exists()


def test_a_bad_tag_deep_in_a_real_config_is_refused_before_its_real_objects_are_built(trained, tmp_path):
    lines = trained.read_text().splitlines()
    at = next(i for i, line in enumerate(lines) if line.endswith("!!python/object/apply:pathlib.PosixPath") and i > 40)
    lines[at] = lines[at].replace("pathlib.PosixPath", "os.system")
    path = tmp_path / "config.yml"
    path.write_text("\n".join(lines) + "\n")
    _Counting.built = 0
    with pytest.raises(ConfigRefused, match=rf"refused line {at + 1}: the tag !!python/object/apply:os.system would call"):
        load_run_config(path)
    with pytest.raises(Exception):
        yaml.load(path.read_text(), Loader=_Counting)
    assert _Counting.built == 0


@pytest.mark.parametrize("text, says", [
    ("!!python/object:sp_plugins.nerfstudio.retired.SPNeuSModelConfig {}",
     "line 1: names sp_plugins.nerfstudio.retired.SPNeuSModelConfig, which this installation lacks"),
    ("!!python/object:nerfstudio.engine.trainer.TrainerConfig\n  a: [1, 2\n", "not a valid config.yml (line 3:"),
    ("[" * 3000 + "]" * 3000, "nested too deeply"),
    ("!!python/object/apply:nerfstudio.utils.writer.EventName [no such event]", "a value does not fit its type"),
    ("just a string", "holds a str, not the TrainerConfig"),
])
def test_other_bad_files_are_one_line_naming_the_file(text, says, tmp_path):
    from nerfstudio.engine.trainer import TrainerConfig

    path = tmp_path / "config.yml"
    path.write_text(text)
    with pytest.raises(ConfigRefused) as refused:
        load_run_config(path, expect=TrainerConfig)
    line = str(refused.value)
    assert "\n" not in line and line.startswith(f"--load-config {path}: ") and says in line, line


def test_a_binary_file_is_refused_in_one_line(tmp_path):
    path = tmp_path / "config.yml"
    path.write_bytes(bytes(range(256)) * 4)
    with pytest.raises(ConfigRefused, match="not UTF-8 text"):
        load_run_config(path)


# -- the hosts' own reads inside our commands go through it -----------------------------------------------


def test_eval_setup_reads_the_config_through_the_restricted_loader(trained):
    """sp-export-mesh hands the run to nerfstudio's eval_setup, which reads config.yml again; inside
    reading_configs_safely it must read through our loader (fails loudly if nerfstudio changes how)."""
    from nerfstudio.utils import eval_utils

    real = eval_utils.yaml
    with reading_configs_safely(eval_utils, f"--load-config {trained}") as proxy:
        config, pipeline, _, step = eval_utils.eval_setup(trained, test_mode="inference")
    assert proxy.loads == 1 and eval_utils.yaml is real and step == 1
    assert type(config).__name__ == "CheckedTrainerConfig" and pipeline.model.sp is not None


def test_ns_train_main_reads_load_config_through_the_restricted_loader(tmp_path):
    from nerfstudio.scripts import train as host_train

    from sp_plugins.nerfstudio.runs import method_config

    marker = tmp_path / "marker"
    bad = tmp_path / "config.yml"
    bad.write_text(f'!!python/object/apply:os.system ["touch {marker}"]\n')
    config = method_config(METHOD)
    config.load_config = bad
    with reading_configs_safely(host_train, f"--load-config {bad}") as proxy:
        with pytest.raises(ConfigRefused, match="would call os.system"):
            host_train.main(config)
    assert proxy.loads == 1 and not marker.exists()


# -- checkpoints ------------------------------------------------------------------------------------------


def test_a_checkpoint_carrying_a_pickled_callable_is_refused_in_one_line(tmp_path):
    from sp_plugins.adapter.errors import describe_failure

    marker = tmp_path / "marker"
    path = tmp_path / "step-000000001.ckpt"
    torch.save({"pipeline": {"w": torch.zeros(2)}, "x": _Touch(marker)}, path)
    try:
        torch.load(path, map_location="cpu")  # what nerfstudio's eval_setup / --load-dir call
    except Exception as exc:  # noqa: BLE001
        message = describe_failure(exc)
    else:
        raise AssertionError("the checkpoint loaded")
    assert message.startswith(f"{path}: holds a pickled posix.system, which torch's weights-only loading refuses (nothing")
    assert "\n" not in message and not marker.exists()


# -- the console scripts ----------------------------------------------------------------------------------


def _one_line(proc, prog: str, *says: str) -> str:
    report = f"rc={proc.returncode}\n--- stderr\n{proc.stderr[-3000:]}\n--- stdout\n{proc.stdout[-1500:]}"
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, report
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    errors = [line for line in lines if ": error: " in line]
    assert len(errors) == 1 and errors[0] == lines[-1] and errors[0].startswith(f"{prog}: error: "), report
    for word in says:
        assert word in errors[0], f"{word!r} not in the error line\n{report}"
    return errors[0]


def test_console_scripts_refuse_a_hostile_run_and_load_a_real_one(trained, ns_server, tmp_path):
    marker = tmp_path / "marker"
    hostile = tmp_path / "hostile" / "config.yml"
    hostile.parent.mkdir()
    hostile.write_text(f'!!python/object/apply:os.system ["touch {marker}"]\n')
    evil = relocate(trained, tmp_path / "evil-ckpt")
    (ckpt,) = (evil.parent / "nerfstudio_models").glob("*.ckpt")
    state = torch.load(ckpt, map_location="cpu", weights_only=True)
    state["x"] = _Touch(marker)
    torch.save(state, ckpt)
    copy = relocate(trained, tmp_path / "copy")
    before = (copy.parent / "nerfstudio_models" / "step-000000001.ckpt").stat().st_mtime_ns
    real = {  # the console scripts themselves
        "mesh-os.system": ([command("sp-export-mesh"), "--load-config", hostile, "--output-dir", tmp_path / "m1"], ENV),
        "train-os.system": ([command("sp-train"), METHOD, "--load-config", hostile], ENV),
        "mesh-evil-ckpt": ([command("sp-export-mesh"), "--load-config", evil, "--output-dir", tmp_path / "m2", "--resolution", "16"],
                           dict(ENV, TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD="1")),  # the user's environment asks for full unpickling
    }
    started = {name: subprocess.Popen(list(map(str, args)), env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                      text=True, cwd=tmp_path) for name, (args, env) in real.items()}
    # the real runs' loads, through the session's fork server (tests/nerfstudio/conftest.py, tests/helpers/forkserver.py)
    try:
        forked = ns_server.run([
            {"name": "mesh-real", "script": "sp-export-mesh", "cwd": str(tmp_path),
             "args": ["--load-config", str(trained), "--output-dir", str(tmp_path / "m3"), "--resolution", "16"]},
            {"name": "train-real", "script": "sp-train", "cwd": str(tmp_path), "args": [METHOD, "--load-config", str(copy)]},
        ], parallel=1)
        procs = {}
        for name, proc in started.items():
            out, err = proc.communicate(timeout=600)
            procs[name] = SimpleNamespace(returncode=proc.returncode, stdout=out, stderr=err)
    finally:
        for proc in started.values():
            if proc.poll() is None:
                proc.kill()
    procs.update({name: SimpleNamespace(returncode=r["rc"], stdout=r["stdout"], stderr=r["stderr"]) for name, r in forked.items()})
    assert not marker.exists(), "a command ran what a file named"
    for name, prog in (("mesh-os.system", "sp-export-mesh"), ("train-os.system", "sp-train")):
        _one_line(procs[name], prog, f"--load-config {hostile}: refused line 1: the tag !!python/object/apply:os.system",
                  "would call os.system", "nothing was built or run")
    _one_line(procs["mesh-evil-ckpt"], "sp-export-mesh", str(ckpt), "holds a pickled posix.system", "weights-only")
    assert not (tmp_path / "m1").exists() and not (tmp_path / "m2").exists()
    for name in ("mesh-real", "train-real"):
        assert procs[name].returncode == 0, f"[{name}]\n{procs[name].stderr[-3000:]}"
    assert (tmp_path / "m3" / "mesh.ply").is_file() and "wrote" in procs["mesh-real"].stdout
    trained_again = copy.parent / "nerfstudio_models" / "step-000000001.ckpt"
    assert "Loading pre-set config from" in procs["train-real"].stdout
    assert trained_again.stat().st_mtime_ns > before, "sp-train --load-config did not train the loaded run"
