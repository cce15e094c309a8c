"""What every host adapter shares, importing no host (neither at module level nor in a function).

A host adapter (``sp_plugins.nerfstudio``, ``sp_plugins.sdfstudio``) has one shape: a *seam*
(``seam.py``: where a model hands its samples to a field, the positions move), a *model*
(``model.py``: the preconditioner, optimizer group, callbacks) and *registration*
(``registration.py``: how methods reach the host's commands, ``with_sp``), with what it knows about
single methods in ``table.py``. The pieces both hosts need live here, one idea per module:

- :mod:`.model`: :class:`~sp_plugins.adapter.model.SPModelBase`, whose abstract methods are what a
  host provides (attach SP to the fields it built, the reached check, the preset for a model, the
  scene box, a training callback), and ``SPModelConfig``;
- :mod:`.field`: the preconditioner handle a seam holds, and the K-draw average;
- :mod:`.variants`: SP subclasses of host classes made on demand, importable by the path a saved
  ``config.yml`` names; the refusal-table lookup;
- :mod:`.callbacks`: the schedule's training callbacks, made through the host's callback factory;
- :mod:`.shrink`: a trainer config of either host made CPU-sized (tests, benchmarks);
- :mod:`.presets`, :mod:`.tables`, :mod:`.checks`, :mod:`.errors`, :mod:`.safe_config`,
  :mod:`.lpips`: presets, lookups in the hosts' method tables, input checks with one-line errors,
  the restricted config loader, LPIPS without downloads.

A new host gets a folder of its own (``seam.py``, ``model.py``, ``registration.py``) built on
these, and an entry point; a new method of an existing host usually needs no code at all (the
host's ``with_sp``).

Glossary (the words mean this in code, errors and the README):

- **host**: a training codebase SP is brought into (nerfstudio 1.x; sdfstudio, a fork of nerfstudio
  0.1); a *host class* is one of its classes, named by path (``module.QualName``).
- **seam**: the one place in a host where the positions a field queries are moved (nerfstudio: the
  ``RaySamples`` handed to a field's ``forward``; sdfstudio: the SDF field's scene contraction).
- **read point**: where a field queries a batch of samples (bin midpoints, bin starts for SDF
  fields); SP's offset is computed there (nerfstudio: ``SeamField.sp_read_positions``).
- **reached**: after the first training step with alpha > 0, a field query *read* positions that SP
  *moved*; each host's ``check_sp_reached`` refuses a run where none did, in one line.
- **plain**: not perturbed: a field SP leaves alone (a background model, a sampler's queries), and
  every query while evaluating, rendering or exporting.
- **variant**: the SP subclass of a host class (model, model config, field), made on demand and
  named after the host class's path (``SPModel__<encoded path>``).
- **preset**: the SP settings (an ``SPConfig``) a method gets by default: the paper's for its family,
  :data:`sp_plugins.adapter.presets.DEFAULT` otherwise.
- **perturb** (``core.perturb``, a preconditioner's ``forward``): move positions once, ``x + alpha *
  eps`` folded into the bounds; **mean over draws** (``mean_over_draws``, ``perturbed_mean``): a
  result averaged over ``num_samples`` perturbations; **blurred** (``StochasticPreconditioner.blurred``):
  a function of positions averaged so, the blurred field.
"""

from sp_plugins._lazy import lazy_attribute

_WHERE = {"PreconditionerHandle": "field", "SPFieldMixin": "field", "VariantFactory": "variants"}
"""Where each public name lives: loaded on first use (PEP 562), so that the modules that need no torch
(errors, hosts, checks, safe_config: a run folder's commands, the patches) import without it."""


def __getattr__(name: str):
    return lazy_attribute(__name__, _WHERE, name)


def __dir__():
    return sorted(set(globals()) | set(__all__))


__all__ = ["PreconditionerHandle", "SPFieldMixin", "VariantFactory"]
