"""The ns-* startup patch: guards on nerfstudio, the fast path, and the install offer it must keep."""

import importlib.metadata
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("nerfstudio")

from nerfstudio.configs import external_methods as ns_external

from sp_plugins.patches import nerfstudio_external_methods as patch


def test_nerfstudio_still_makes_the_slow_check():
    version = importlib.metadata.version("nerfstudio")
    assert version in patch.TESTED_NERFSTUDIO_VERSIONS, (
        f"nerfstudio {version} was not verified against the startup patch: re-check "
        "nerfstudio/configs/external_methods.py and update patches/nerfstudio_external_methods.py"
    )
    assert patch.host_post_init_is_as_expected(), "nerfstudio no longer calls inspect.stack() there: drop the patch?"


@pytest.fixture
def fast():
    """The patch for one test (registry scope); nerfstudio's __post_init__ again after it."""
    from sp_plugins.patches import registry

    with registry.scope("nerfstudio_external_methods"):
        yield


def test_installing_it_is_idempotent(fast):
    """It goes in only through our own command (sp-train); discovery of our methods leaves it out
    (tests/nerfstudio/test_guest.py checks that in a fresh process)."""
    post_init = ns_external.ExternalMethodDummyTrainerConfig.__post_init__
    assert getattr(post_init, "__sp_original__", None) is not None
    assert patch.install_fast_external_methods()
    assert ns_external.ExternalMethodDummyTrainerConfig.__post_init__ is post_init


def test_built_by_get_external_methods_stays_quiet(fast, monkeypatch):
    printed = []
    monkeypatch.setattr(ns_external.CONSOLE, "print", lambda *a, **k: printed.append(a))
    configs, descriptions = ns_external.get_external_methods()
    assert len(configs) == sum(len(m.configurations) for m in ns_external.external_methods) > 0
    assert set(configs) == set(descriptions)
    assert printed == []


def test_built_elsewhere_still_offers_the_install(fast, monkeypatch):
    printed = []
    monkeypatch.setattr(ns_external.CONSOLE, "print", lambda *a, **k: printed.append(a))
    method = ns_external.ExternalMethod(instructions="install me first", configurations=[("x", "x")])
    with pytest.raises(SystemExit) as exit_info:
        ns_external.ExternalMethodDummyTrainerConfig(method_name="x", method=method)
    assert exit_info.value.code == 0
    assert printed and printed[0][0] == "install me first"


NS_TRAIN = shutil.which("ns-train", path=str(Path(sys.executable).parent)) or shutil.which("ns-train")


@pytest.mark.skipif(NS_TRAIN is None, reason="ns-train is not installed")
def test_ns_train_of_an_external_method_still_prints_how_to_install_it():
    """The user's view: ``ns-train zipnerf`` shows zipnerf's instructions and asks; we answer no."""
    out = subprocess.run([NS_TRAIN, "zipnerf"], input="n\n", capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "To enable Zip-NeRF" in out.stdout
    assert "Would you like to run the install" in out.stdout
