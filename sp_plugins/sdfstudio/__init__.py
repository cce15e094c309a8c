"""Adapters for sdfstudio (autonomousvision/sdfstudio, commit 370902a), a second host.

sdfstudio installs as a package named ``nerfstudio`` (0.1.12), so this subpackage and
``sp_plugins.nerfstudio`` never run in one environment. The host is imported lazily: importing
``sp_plugins.sdfstudio`` itself imports nothing of sdfstudio. The same shape as the nerfstudio
adapter:

- :mod:`~sp_plugins.sdfstudio.sdf_field`: where positions are perturbed (``SPSDFField``);
- :mod:`~sp_plugins.sdfstudio.model`: what every SP model shares: the SP module, optimizer group,
  callbacks (:mod:`~sp_plugins.adapter.callbacks`), handing SP to the SDF field;
- :mod:`~sp_plugins.sdfstudio.variants`: the SP subclass of any sdfstudio SDF model / model config,
  made on demand and importable by a path that names the host class (``config.yml`` loads);
  :mod:`~sp_plugins.sdfstudio.neus` keeps the old class names of the NeuS family as aliases;
- :mod:`~sp_plugins.sdfstudio.sdf_methods` / :mod:`~sp_plugins.sdfstudio.registration`: ``sp-<method>``
  for every SDF method sdfstudio registers (its own config, classes swapped, paper preset), the
  refusals of the others, and our entry-point group ``sp_plugins.sdfstudio_methods`` (sp-neus,
  sp-neus-facto, sp-neuralangelo, sp-bakedangelo);
- :mod:`~sp_plugins.sdfstudio.cli`: ``sp-sdfstudio-train``, ``sp-sdfstudio-extract-mesh``;
- :mod:`~sp_plugins.sdfstudio.hook`: opt-in start-up hook for sdfstudio's unmodified ``ns-*``;
- :mod:`~sp_plugins.sdfstudio.host`: is the installed ``nerfstudio`` sdfstudio's (marker file).

The runtime patches that make sdfstudio run on Python 3.11 / torch 2.x / CPU live in
``sp_plugins.patches.sdfstudio_*``.
"""
