"""sdfstudio tests: they run only with sdfstudio's ``nerfstudio`` (its own venv; ``./run.sh test``
runs them there). In any other environment each module is reported as skipped, with the reason,
so a run without the host says so in its summary instead of leaving them out unseen; only when
``./run.sh test`` runs them in their own environment beside the main run
(``SP_SDFSTUDIO_TESTS=separate``) does the main run leave them out."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from sp_plugins.sdfstudio.detect import is_sdfstudio

HERE = is_sdfstudio()
SEPARATE = os.environ.get("SP_SDFSTUDIO_TESTS") == "separate"
collect_ignore_glob = ["test_*.py"] if not HERE and SEPARATE else []
SKIP_REASON = "sdfstudio tests need sdfstudio's environment: " + (
    os.environ.get("SP_SDFSTUDIO_MISSING")
    or "this is not it (run them with ./run.sh test, which builds it with ./run.sh setup-sdfstudio from $SP_SDFSTUDIO_SRC)"
)


class HostMissing(pytest.File):
    """A test module of this folder outside sdfstudio's environment: not imported (its imports
    need sdfstudio); one test item that skips with the reason, so the summary counts it."""

    def collect(self):
        yield HostMissingItem.from_parent(self, name="needs sdfstudio")


class HostMissingItem(pytest.Item):
    def runtest(self):
        pytest.skip(SKIP_REASON)

    def reportinfo(self):
        return self.path, None, f"{self.path.name}: {self.name}"


def pytest_pycollect_makemodule(module_path, parent):
    if not HERE:
        return HostMissing.from_parent(parent, path=module_path)
    return None

@pytest.fixture(scope="session")
def sdf_scene(tmp_path_factory) -> Path:
    """A 6-view 24x24 sphere in the SDFStudio layout."""
    from sp_plugins.data import make_tiny_scene

    root = tmp_path_factory.mktemp("sdf_scene")
    paths = make_tiny_scene(root, "sphere", n_train=6, n_val=1, n_test=1, resolution=24, layouts=("sdfstudio",))
    return Path(paths.sdfstudio)


@pytest.fixture(scope="session")
def patched():
    """Compatibility patches and our methods, in this process (for the in-process tests)."""
    from sp_plugins.patches.sdfstudio_import_hook import install_all

    install_all()
    import scripts.train  # noqa: F401  (sdfstudio's own import order: base_config before method_configs)

    from sp_plugins.sdfstudio.registration import add_methods

    add_methods()


def pytest_sessionfinish(session, exitstatus):
    """Stop the fork server :func:`tests.helpers.sdf_configs.run` started (if it did)."""
    if HERE:
        from tests.helpers.sdf_configs import close_fork_server

        close_fork_server()
