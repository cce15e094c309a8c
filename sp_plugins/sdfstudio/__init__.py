"""Adapters for sdfstudio (autonomousvision/sdfstudio, commit 370902a), a second host.

sdfstudio installs as a package named ``nerfstudio`` (0.1.12), so this subpackage and
``sp_plugins.nerfstudio`` never run in one environment. The host is imported lazily: importing
``sp_plugins.sdfstudio`` itself imports nothing of sdfstudio.
"""
