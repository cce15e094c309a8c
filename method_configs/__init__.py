"""Our nerfstudio method configs (entry points in pyproject.toml).

nerfstudio imports these modules in every ``ns-*`` command, also when the user trains a method that
is not ours, so importing them only registers methods: no exception hook, no warning filters, no
patched host module. What our methods need is installed when one of them is built
(:func:`sp_plugins.nerfstudio.model.install_process_settings`) or by our own commands (``sp-train``
installs the start-up patch of :mod:`sp_plugins.patches.nerfstudio_external_methods`)."""
