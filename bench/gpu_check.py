"""The first-run GPU check from a source checkout: ``python bench/gpu_check.py [options]`` is
``sp-gpu-check [options]`` (:mod:`sp_plugins.cli.gpu_check`, installed with the package)."""

import sys
from pathlib import Path

if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a file from a checkout
    from sp_plugins.cli.gpu_check import entrypoint

    entrypoint()
