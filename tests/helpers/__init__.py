"""What the tests share, imported as ``from tests.helpers.<module> import ...``:

- :mod:`~tests.helpers.ns_configs`: CPU-sized nerfstudio trainer configs (our SDF and radiance methods,
  nerfstudio's built-ins under ``sp-train``) and ``run_recording`` (train in process, loss per step);
- :mod:`~tests.helpers.sdf_configs`: the same for sdfstudio (command-line flags and in-process configs);
- :mod:`~tests.helpers.ns_commands`: the subprocess runner for ``ns-train`` / ``ns-eval`` / ... with
  CPU-sized flags;
- :mod:`~tests.helpers.forkserver`: console scripts in processes forked from one import of nerfstudio;
- :mod:`~tests.helpers.errors`: one-line-error checks (exit status 2, ``<prog>: error: ...``, no traceback);
- :mod:`~tests.helpers.kill_resume`: the kill/resume driver (RNG isolation, wait for the checkpoint to
  kill at, bit-for-bit comparison);
- :mod:`~tests.helpers.ddp`: two-process DDP training on the CPU (also run as a script);
- :mod:`~tests.helpers.fs_faults`: read-only folders and "nothing written" listings;
- :mod:`~tests.helpers.fox_crop`: a small crop of the real fox capture (skips name what is missing).

``forkserver.py`` and ``ddp.py`` also run as scripts (``python <file>``) and so import nothing from
``tests``.
"""
