"""Adapters for sdfstudio (autonomousvision/sdfstudio, commit 370902a), a second host.

sdfstudio installs as a package named ``nerfstudio`` (0.1.12), so this subpackage and
``sp_plugins.nerfstudio`` never run in one environment. The host is imported lazily: importing
``sp_plugins.sdfstudio`` itself imports nothing of sdfstudio. The module names and roles are the
nerfstudio adapter's:

- :mod:`~sp_plugins.sdfstudio.seam` (fields): where SP enters, the SDF field's scene contraction
  (``SeamSDFField``), which every training query of every sdfstudio SDF method passes;
- :mod:`~sp_plugins.sdfstudio.model` (models): ``SPModel`` (preconditioner, optimizer group,
  callbacks from :mod:`sp_plugins.adapter`) and ``SDFFieldSPModel``, which hands SP to the seam;
- :mod:`~sp_plugins.sdfstudio.table`: what is known about methods (refused models, presets,
  finite-difference steps), the one file to edit to support or refuse one;
- :mod:`~sp_plugins.sdfstudio.registration` (registration): ``with_sp``, ``refusal``,
  ``preset_for``, ``sp_methods``, and our entry-point group
  ``sp_plugins.sdfstudio_methods`` (sp-neus, sp-neus-facto, sp-neuralangelo, sp-bakedangelo),
  added to ns-train with ``sp-<method>`` for every SDF method sdfstudio registers;
  :mod:`~sp_plugins.sdfstudio.conversion` builds those configs (host config, classes swapped,
  coarse-to-fine replaced where the host enables it);
- :mod:`~sp_plugins.sdfstudio.variants`: the SP subclass of any sdfstudio SDF model / model config,
  made on demand and importable by a path that names the host class (``config.yml`` loads);
- :mod:`~sp_plugins.sdfstudio.cli`: ``sp-sdfstudio-train``, ``sp-sdfstudio-extract-mesh``;
- :mod:`~sp_plugins.sdfstudio.hook`: opt-in start-up hook for sdfstudio's unmodified ``ns-*``;
- :mod:`~sp_plugins.sdfstudio.detect`: is the installed ``nerfstudio`` sdfstudio's (marker file).

The runtime patches that make sdfstudio run on Python 3.11 / torch 2.x / CPU live in
``sp_plugins.patches.sdfstudio_*``.
"""
