"""Our nerfstudio method configs (entry points in pyproject.toml).

nerfstudio imports this package when it discovers plugin methods, before it builds its list of
installable external methods: the moment to install the startup patch
(:mod:`sp_plugins.patches.nerfstudio_external_methods`)."""

from sp_plugins.patches.nerfstudio_external_methods import install_fast_external_methods

install_fast_external_methods()
