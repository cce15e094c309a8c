"""sdfstudio tests: they run only with sdfstudio's ``nerfstudio`` (its own venv, ``./run.sh test``
runs them there); in any other environment this folder is not collected."""

from __future__ import annotations

from pathlib import Path

import pytest

from sp_plugins.sdfstudio.host import is_sdfstudio

collect_ignore_glob = [] if is_sdfstudio() else ["test_*.py"]

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
