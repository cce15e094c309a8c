"""Sweeps of our nerfstudio methods and ``sp-fit`` tasks on Ray Tune (``sp-sweep``).

- :mod:`~sp_plugins.sweeps.spec`: the spec (command, grid, SP axis, seeds) and its trials.
- :mod:`~sp_plugins.sweeps.trial`: one trial as a subprocess, its ``result.json``.
- :mod:`~sp_plugins.sweeps.ray_runner`: pending trials on a local Ray or a cluster.
- :mod:`~sp_plugins.sweeps.report`: CSV / markdown table, histogram, success rate, per-axis medians.
- :mod:`~sp_plugins.sweeps.soundness`: whether a fitted SDF is one sheet with the right sign.

Ray is imported only when trials run (``pip install 'sp-plugins[sweeps]'``).
"""

from sp_plugins.sweeps.spec import SpecError, SweepSpec, Trial, expand, load_spec, spec_from_dict

__all__ = ["SpecError", "SweepSpec", "Trial", "expand", "load_spec", "spec_from_dict"]
