"""Every method sp-plugins registers, one module per host: each attribute is one method's config, and the entry
points in ``pyproject.toml`` name them (``sp_plugins.method_configs.<host>:<attribute>``; this folder ships in the
wheel as the sub-package ``sp_plugins.method_configs``, as ``patches/`` ships as ``sp_plugins.patches``).

- :mod:`~sp_plugins.method_configs.nerfstudio`: nerfstudio's ``MethodSpecification`` per method (group
  ``nerfstudio.method_configs``: ``ns-train sp-neus``, ...);
- :mod:`~sp_plugins.method_configs.sdfstudio`: sdfstudio's per method (our group ``sp_plugins.sdfstudio_methods``, read by
  ``sp-sdfstudio-train``).

A module here only picks and names configs; how they are built (the models, fields and their SP settings) is
each host's adapter's (``sp_plugins/<host>/``) and our methods' (``sp_plugins/nerfstudio/``) code.
"""
