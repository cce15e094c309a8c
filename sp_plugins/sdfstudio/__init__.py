"""Adapters for sdfstudio (autonomousvision/sdfstudio, commit 370902a), a second host.

sdfstudio installs as a package named ``nerfstudio`` (0.1.12), so this subpackage and
``sp_plugins.nerfstudio`` never run in one environment. The host is imported lazily: importing
``sp_plugins.sdfstudio`` itself imports nothing of sdfstudio. The same shape as the nerfstudio
adapter:

- :mod:`~sp_plugins.sdfstudio.sdf_field`: where positions are perturbed (``SPSDFField``);
- :mod:`~sp_plugins.sdfstudio.model` / :mod:`~sp_plugins.sdfstudio.neus`: models with the SP
  module, optimizer group, callbacks (:mod:`~sp_plugins.sdfstudio.callbacks`);
- :mod:`~sp_plugins.sdfstudio.sdf_methods` / :mod:`~sp_plugins.sdfstudio.registration`: method
  configs (sdfstudio's own, classes swapped) and our entry-point group ``sp_plugins.sdfstudio_methods``;
- :mod:`~sp_plugins.sdfstudio.cli`: ``sp-sdfstudio-train``, ``sp-sdfstudio-extract-mesh``;
- :mod:`~sp_plugins.sdfstudio.hook`: opt-in start-up hook for sdfstudio's unmodified ``ns-*``;
- :mod:`~sp_plugins.sdfstudio.host`: is the installed ``nerfstudio`` sdfstudio's (marker file).

The runtime patches that make sdfstudio run on Python 3.11 / torch 2.x / CPU live in
``sp_plugins.patches.sdfstudio_*``.
"""
