"""nerfstudio 1.1.5 as our methods need it on a CPU, offline: none of it is SP.

- :mod:`.datamanagers`: data managers that check their input (one-line errors) and feed surface models
  from any layout; :mod:`.views`: training on N of the views (sparse-view runs);
- :mod:`.hash_encoding`: our hash grids where tiny-cuda-nn cannot run (nerfacto's, NeuS's background);
- :mod:`.schedulers`: nerfstudio's schedulers with float learning rates (torch >= 2.6 loads
  checkpoints weights-only and refuses numpy scalars);
- :mod:`.lpips`: LPIPS that never downloads (on :mod:`sp_plugins.adapter.lpips`);
- :mod:`.trainer`: our methods' trainer config, whose ``save_config`` checks the input before
  ``ns-train`` writes the run folder (a refused run writes nothing).

Patches of nerfstudio's own modules live in ``sp_plugins.patches`` (``patches/``), not here.
"""
