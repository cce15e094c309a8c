"""The host registry (:mod:`sp_plugins.adapter.hosts`): a third host registers itself with one
entry point of its own distribution, and the adapter then knows it (its packages for the safe config
reader, its flags, its table, its renamed classes) with no file of sp-plugins edited."""

from __future__ import annotations

import subprocess
import textwrap
from pathlib import Path

import pytest

from sp_plugins.adapter import hosts
from sp_plugins.adapter.safe_config import allowed, load_run_config

ROOT = Path(__file__).resolve().parents[2]

HOST_PY = '''
from sp_plugins.adapter.hosts import Flags, Host

HOST = Host(name="thirdhost", packages=("thirdhost",), table="thirdhost.table", flags=Flags(steps="--steps"),
            renamed={"thirdhost.configs.OldConfig": "thirdhost.configs.RunConfig"})
'''
TABLE_PY = '''
import dataclasses
from sp_plugins.core import SPConfig

PRESET = SPConfig(alpha0=0.07)


def preset_for(model_config):
    return dataclasses.replace(PRESET)
'''
CONFIGS_PY = '''
from dataclasses import dataclass


@dataclass
class RunConfig:
    steps: int = 10
'''


def distribution(root: Path, name: str, entry_points: str) -> None:
    """A distribution ``name`` 0.1 in ``root`` (importable once ``root`` is on the path) with ``entry_points``."""
    dist = root / f"{name}-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text(entry_points)


@pytest.fixture
def third_host(tmp_path, monkeypatch):
    """A distribution ``thirdhost`` on the path: its package (host descriptor, table, a config class)
    and one entry point in ``sp_plugins.hosts``; nothing else."""
    package = tmp_path / "thirdhost"
    package.mkdir()
    for name, text in (("__init__.py", ""), ("host.py", HOST_PY), ("table.py", TABLE_PY), ("configs.py", CONFIGS_PY)):
        (package / name).write_text(textwrap.dedent(text))
    distribution(tmp_path, "thirdhost", "[sp_plugins.hosts]\nthirdhost = thirdhost.host:HOST\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    hosts._from_entry_points.cache_clear()
    yield tmp_path
    hosts._from_entry_points.cache_clear()


def ours_changed() -> str:
    """``git status`` of the package's own files (other tests may write elsewhere in the checkout meanwhile)."""
    return subprocess.run(["git", "status", "--porcelain", "--", "sp_plugins", "patches", "pyproject.toml"], cwd=ROOT,
                          capture_output=True, text=True).stdout


def test_a_third_host_is_known_from_its_own_entry_point(third_host, tmp_path):
    before = ours_changed()
    third = hosts.get("thirdhost")
    assert set(hosts.hosts()) >= {"nerfstudio", "sdfstudio", "thirdhost"}
    assert third.flags.steps == "--steps" and third.table_module().preset_for(None).alpha0 == 0.07
    assert "thirdhost" in allowed().objects  # the safe config reader builds its classes
    (tmp_path / "config.yml").write_text("!!python/object:thirdhost.configs.OldConfig {steps: 3}\n")  # saved before its rename
    loaded = load_run_config(tmp_path / "config.yml")
    assert type(loaded).__qualname__ == "RunConfig" and loaded.steps == 3
    assert ours_changed() == before  # no file of sp-plugins touched


def test_without_it_the_registry_names_what_it_has():
    with pytest.raises(KeyError, match=r"no host 'thirdhost' is registered \(registered: .*nerfstudio.*sdfstudio"):
        hosts.get("thirdhost")
    assert "thirdhost" not in allowed().objects


def test_a_broken_host_entry_is_skipped_with_one_line(tmp_path, monkeypatch, capsys):
    distribution(tmp_path, "brokenhost", "[sp_plugins.hosts]\nbrokenhost = no_such_module:HOST\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    hosts._from_entry_points.cache_clear()
    try:
        assert "brokenhost" not in hosts.hosts() and "nerfstudio" in hosts.hosts()
    finally:
        hosts._from_entry_points.cache_clear()
    assert "sp-plugins: skipping host 'brokenhost' (no_such_module:HOST): ModuleNotFoundError" in capsys.readouterr().err
