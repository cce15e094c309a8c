"""What the studies in ``bench/`` are built on.

- :mod:`~bench.harness.lockstep`: the lockstep pair driver (runs of one host trained side by side in
  one process from the same weights on the same rays, alternating step by step) and what every
  study reports per run (seconds per step, final loss, time ratios);
- :mod:`~bench.harness.nerfstudio` / :mod:`~bench.harness.sdfstudio`: each host's trainer for that
  driver and its own evaluation; trainer configs are shrunk by ``sp_plugins.adapter.shrink``;
- :mod:`~bench.harness.metrics`: PSNR, SDF meshes against the true mesh, table cells, figures;
- :mod:`~bench.harness.scenes`: meshes by file or name, scenes rendered once, real captures;
- :mod:`~bench.harness.radiance`: the CPU-sized MipNeRF and the scenes the radiance studies share;
- :mod:`~bench.harness.common`: output folder, process set-up, machine info, seeding, paired timing.

A study (``bench/NAME.py``) defines its settings, trains them with the driver and writes its JSON,
markdown and figures; the speed benchmarks live apart in ``bench/speed/``.
"""
