"""``python -m sp_plugins.cli.gpu_check`` is ``sp-gpu-check``."""

from sp_plugins.cli.gpu_check.harness import entrypoint

entrypoint()
