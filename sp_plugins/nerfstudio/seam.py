"""The one seam: SP enters where a nerfstudio model hands its ``RaySamples`` to a field.

Every position a nerfstudio field reads from its samples derives from ``frustums.origins``:
``get_positions()`` (nerfacto, vanilla NeRF, TensoRF, the ReLU field), ``get_start_positions()``
(SDF fields: NeuS, neus-facto, Neuralangelo-lite) and ``get_gaussian_blob()`` (MipNeRF's conical
frustums). So while training with alpha > 0 the field is handed a copy of its samples whose origins
are shifted, per sample, by ``sp(x) - x`` with ``x = get_positions()`` (:func:`perturbed_samples`).
Every accessor then sees the same moved sample, with no host class touched:

- ``get_positions()`` is exactly ``sp(x)`` (reflected into the scene box with ``boundary reflect``);
- ``get_start_positions()`` and the Gaussian's mean move by the same offset (the covariance, which
  depends on directions and bins only, is unchanged), so an SDF's autograd eikonal gradient is taken
  at the moved point and a finite-difference stencil around it shares the one offset. The offset is
  computed where the field reads (its *read point*, :meth:`SeamField.sp_read_positions`): at the
  start for SDF fields (nerfstudio's ``SDFField`` and its subclasses, ``table.READ_POINTS``), at the
  bin's midpoint for the others (a MipNeRF mean sits near it), so the box reflection is exact at
  the point queried. A field class that queries elsewhere defines ``sp_read_positions`` itself;
  the seam is not edited;
- directions, bins, camera indices and times are the host's, and the host's own ``RaySamples`` is
  never modified: renderers, samplers and losses read the plain samples.

:func:`attach_seam` puts the seam on the field *instances* a model built (after the host's
``populate_modules``, however the field was constructed): every submodule that is a nerfstudio
``Field`` or whose ``forward`` takes ``ray_samples`` gets its class swapped for a subclass whose
``forward`` perturbs (:class:`SeamField`; state-dict keys unchanged). nerfstudio models call
``self.field.forward(...)`` directly as often as ``self.field(...)``, so ``nn.Module`` hooks would miss
half of them. Calls that only place samples go through ``density_fn`` / ``get_density`` (proposal
networks) or ``get_sdf`` (the NeuS sampler), not ``forward``, and stay plain; so do evaluation,
rendering and export (the field is not training).

"Reached" means a field *read* positions SP *moved* (the glossary of :mod:`sp_plugins.adapter`): the
copy's frustums record, per field, which of their tensors the field read while it ran
(:class:`SeamFrustums`), and the handle keeps the first move. :func:`check_reached` refuses, in one
line naming the field class and what it read, a field that was handed moved samples and never read
their origins (it reads positions some other way), samples that did not move, and a model where no
field was handed any.
"""

from __future__ import annotations

import contextvars
import dataclasses
import functools
import inspect
from dataclasses import dataclass
from typing import Any, Callable, Dict, List, Mapping, Optional, Set, Tuple

import torch.nn.functional as F
from nerfstudio.cameras.rays import Frustums, RaySamples
from nerfstudio.field_components.field_heads import FieldHeadNames
from nerfstudio.fields.base_field import Field
from torch import Tensor, nn

from sp_plugins.adapter.errors import InputError
from sp_plugins.adapter.field import SPFieldMixin
from sp_plugins.adapter.tables import lookup, read_point
from sp_plugins.adapter.variants import class_path
from sp_plugins.core import StochasticPreconditioner
from sp_plugins.core.preconditioner import previewing
from sp_plugins.nerfstudio import table, variants

__all__ = ["ALPHA_GRID_OUTPUT", "ReadPoint", "SeamField", "SeamFrustums", "attach_seam", "check_reached", "perturbed_samples",
           "seam_fields", "table_read_point", "takes_ray_samples"]

_READS: contextvars.ContextVar[Optional[Set[str]]] = contextvars.ContextVar("sp_seam_reads", default=None)
"""The read record of the field that is running on moved samples (None outside such a call)."""

_FRUSTUM_TENSORS = frozenset(f.name for f in dataclasses.fields(Frustums))
POSITION_READ = "origins"
"""Every position accessor reads the origins: a field that never did, never saw the offset."""

ReadPoint = Callable[[Frustums], Tensor]
"""Where a field queries a batch of samples: ``frustums -> positions [*bs, 3]``."""




@functools.lru_cache(maxsize=None)
def table_read_point(cls: type) -> str:
    """The ``Frustums`` accessor instances of host field class ``cls`` query at: ``table.READ_POINTS``'
    entry for it or its nearest base, else ``get_positions`` (looked up once per class)."""
    return read_point(table.READ_POINTS, cls)


@dataclass
class SeamFrustums(Frustums):
    """``Frustums`` with SP-shifted origins that record which tensors the running field reads.

    The subclass survives the host's reshapes and indexing (they rebuild it with
    ``dataclasses.replace``), and marks samples already moved so a field nested in another is
    not perturbed twice."""

    def __getattribute__(self, name: str) -> Any:
        if name in _FRUSTUM_TENSORS:
            reads = _READS.get()
            if reads is not None:
                reads.add(name)
        return object.__getattribute__(self, name)


def perturbed_samples(samples: RaySamples, sp: StochasticPreconditioner, read: ReadPoint = Frustums.get_positions) -> RaySamples:
    """A copy of ``samples`` whose every position accessor sees ``sp`` applied once per sample.

    ``origins`` ``[*bs, 3]`` become ``origins + sp(x) - x`` with ``x = read(frustums)``, the field's
    read point: ``get_positions()`` by default (existing ``offsets`` kept: the perturbation applies to
    the offset position), ``get_start_positions()`` for SDF fields (the box reflection is then exact
    where they query). Gradients reach ``sp``'s alpha grid through the offset. ``samples`` itself is
    not modified."""
    frustums = samples.frustums
    x = read(frustums)
    q = sp(x.reshape(-1, x.shape[-1])).view(x.shape)
    values = {f.name: getattr(frustums, f.name) for f in dataclasses.fields(Frustums)}
    values["origins"] = frustums.origins + (q - x)
    return dataclasses.replace(samples, frustums=SeamFrustums(**values))


def _find_samples(args: tuple, kwargs: dict) -> Tuple[Optional[RaySamples], Any]:
    """The ``RaySamples`` a field was called with and where (an argument index or keyword)."""
    if "ray_samples" in kwargs and isinstance(kwargs["ray_samples"], RaySamples):
        return kwargs["ray_samples"], "ray_samples"
    if args and isinstance(args[0], RaySamples):
        return args[0], 0
    return None, None


def _with_samples(args: tuple, kwargs: dict, where: Any, samples: RaySamples) -> Tuple[tuple, dict]:
    if where == "ray_samples":
        return args, {**kwargs, "ray_samples": samples}
    return (samples, *args[1:]), kwargs


def _finish_mean(field: nn.Module, outputs: Any, samples: RaySamples) -> Any:
    """After averaging K draws of an SDF field: unit normals from the mean gradient, and the NeuS
    alpha from the mean SDF and gradient (an average of alphas is not the alpha of the average)."""
    if not isinstance(outputs, dict) or FieldHeadNames.GRADIENT not in outputs:
        return outputs
    if FieldHeadNames.NORMALS in outputs:
        outputs[FieldHeadNames.NORMALS] = F.normalize(outputs[FieldHeadNames.GRADIENT], p=2, dim=-1)
    if FieldHeadNames.ALPHA in outputs and FieldHeadNames.SDF in outputs and hasattr(field, "get_alpha"):
        outputs[FieldHeadNames.ALPHA] = field.get_alpha(samples, outputs[FieldHeadNames.SDF], outputs[FieldHeadNames.GRADIENT])
    return outputs


ALPHA_GRID_OUTPUT = "sp_alpha_grid"
"""The output a model with a learnable alpha grid adds to its renders (viewer, ``ns-render``)."""


def _record_alpha_render(field: "SeamField", samples: RaySamples, outputs: Any) -> None:
    """In a render (not training) of a model with a learnable alpha grid: the grid's expected value
    along each ray, ``sum_i w_i alpha(x_i)`` ``[*rays, 1]`` over the samples this field was handed,
    the weights from its density or NeuS alpha, kept on the handle for the model's outputs."""
    handle = field.sp_handle
    grid = None if handle is None or handle.sp is None else handle.sp.alpha_grid
    if grid is None or not isinstance(outputs, dict):
        return
    if FieldHeadNames.ALPHA in outputs:
        weights, _ = samples.get_weights_and_transmittance_from_alphas(outputs[FieldHeadNames.ALPHA])
    elif FieldHeadNames.DENSITY in outputs:
        weights = samples.get_weights(outputs[FieldHeadNames.DENSITY])
    else:
        return
    x = field.sp_read_positions(samples.frustums)
    alpha = grid(x.reshape(-1, x.shape[-1]).detach()).view(*x.shape[:-1], 1)
    handle.alpha_render = (weights.detach() * alpha).sum(dim=-2)


class SeamField(SPFieldMixin):
    """The seam on one field: first among the bases of the class a field instance is swapped to.

    While training with alpha > 0, a call with ``RaySamples`` runs the host's ``forward`` on
    :func:`perturbed_samples` (averaged over ``sp.num_samples`` draws), recording what it read.
    Any other call is the host's, untouched."""

    def sp_read_positions(self, frustums: Frustums) -> Tensor:
        """The positions ``[*bs, 3]`` this field queries for ``frustums``: SP's offset is computed
        there. The field class's own ``sp_read_positions`` wins (a
        :class:`~sp_plugins.adapter.field.ReadPointField`: one method, in the field's file); else the
        host table's entry (:func:`table_read_point`); else ``get_positions()``."""
        own = getattr(super(), "sp_read_positions", None)
        if own is not None:
            return own(frustums)
        return getattr(frustums, table_read_point(type(self)))()

    def forward(self, *args: Any, **kwargs: Any) -> Any:
        host_forward = super().forward  # type: ignore[misc]
        samples, where = _find_samples(args, kwargs)
        if samples is None or isinstance(samples.frustums, SeamFrustums) or not self.sp_active():
            outputs = host_forward(*args, **kwargs)
            if samples is not None and not self.training:  # type: ignore[attr-defined]
                _record_alpha_render(self, samples, outputs)
            return outputs
        handle = self.sp_handle
        assert handle is not None and handle.sp is not None
        sp = handle.sp

        viewing = previewing()  # a viewer render: perturbed, but nothing recorded for the reach check

        def one_draw() -> Any:
            moved = perturbed_samples(samples, sp, self.sp_read_positions)
            if handle.first_move is None and not viewing:  # once per run, device-side: the reach check reads it
                handle.first_move = (moved.frustums.origins - samples.frustums.origins).detach().abs().max()
            moved_args, moved_kwargs = _with_samples(args, kwargs, where, moved)
            token = _READS.set(set() if viewing else handle.reads)
            try:
                return host_forward(*moved_args, **moved_kwargs)
            finally:
                _READS.reset(token)

        outputs = self.mean_over_draws(one_draw)
        return _finish_mean(self, outputs, samples) if sp.config.num_samples > 1 else outputs


variants.FACTORY.register("Field", SeamField)


def takes_ray_samples(module: nn.Module) -> bool:
    """True for a nerfstudio ``Field`` or a module whose ``forward`` takes ``ray_samples`` first."""
    if isinstance(module, Field):
        return True
    try:
        params = list(inspect.signature(type(module).forward).parameters.values())[1:]
    except (TypeError, ValueError):
        return False
    if not params:
        return False
    first = params[0]
    return first.name == "ray_samples" or first.annotation in (RaySamples, "RaySamples")


def seam_class(host: type) -> type:
    """The :class:`SeamField` subclass of ``host`` (importable by the path a variant name encodes
    when ``host`` is; a local subclass otherwise)."""
    if issubclass(host, SeamField):
        return host
    try:
        return variants.variant("Field", host)
    except ValueError:  # a class not importable by its path (defined in a function): still reachable
        return _LOCAL.setdefault(host, type(f"SPField_{host.__name__}", (SeamField, host), {"__module__": __name__}))


_LOCAL: Dict[type, type] = {}


def seam_fields(model: nn.Module) -> List[Tuple[str, SeamField]]:
    """``(name, field)`` of the model's submodules that carry the seam."""
    return [(name, m) for name, m in model.named_modules() if isinstance(m, SeamField)]


def attach_seam(model: nn.Module, sp: StochasticPreconditioner, plain: Mapping[str, str] = {}) -> List[str]:
    """Put the seam on every field of ``model`` (see :func:`takes_ray_samples`) except the
    submodules named in ``plain`` (attribute path -> why it stays plain); returns their names."""
    attached = []
    for name, module in model.named_modules():
        if module is model or isinstance(module, StochasticPreconditioner):
            continue
        if any(name == p or name.startswith(p + ".") for p in plain):
            continue
        if not takes_ray_samples(module):
            continue
        if not isinstance(module, SeamField):
            module.__class__ = seam_class(type(module))
        module.use_preconditioner(sp)
        attached.append(name)
    return attached


def host_name(module: nn.Module) -> str:
    """The class a seam field was built as (its host class), by path."""
    ours = (SeamField, SPFieldMixin)
    cls = next(c for c in type(module).__mro__ if c not in ours and c.__module__ not in (__name__, variants.__name__))
    return class_path(cls)


def check_reached(model: nn.Module, model_name: str, step: int, boundary: str = "none") -> None:
    """After the first training step with alpha > 0: at least one field was handed moved samples,
    they really moved, and every field handed them read their positions; a box ``boundary`` is
    refused on a field that contracts space (unless ``table.BOX_FIELDS`` names it: an SDF lives in the box). Runs once
    per run; one device read (the first move)."""
    fields = seam_fields(model)
    called = [(name, f) for name, f in fields if f.sp_handle is not None and f.sp_handle.perturbed_calls > 0]
    if not called:
        raise InputError(
            f"SP reached no field of {model_name} in training step {step}: no field was called with RaySamples "
            "(fields queried only through positions or density_fn stay plain); SP does not apply to this method"
        )
    moved = [float(f.sp_handle.first_move) for _, f in called if f.sp_handle.first_move is not None]  # type: ignore[union-attr]
    if not any(m > 0 for m in moved):
        raise InputError(
            f"SP reached the fields of {model_name} in training step {step} but moved no sample (largest move "
            f"{max(moved, default=0.0):g}): the perturbation is not applied; this is a bug of sp-plugins, please report it"
        )
    for name, f in called:
        if boundary != "none" and getattr(f, "spatial_distortion", None) is not None and not lookup(table.BOX_FIELDS, type(f)):
            way_out = " (or --pipeline.model.disable-scene-contraction True)" if hasattr(getattr(model, "config", None), "disable_scene_contraction") else ""
            raise InputError(
                f"--pipeline.model.sp.boundary {boundary} needs a bounded scene, but {host_name(f).rsplit('.', 1)[-1]} (model.{name}) "
                f"contracts space (scene contraction is on); pass --pipeline.model.sp.boundary none{way_out}"
            )
        reads = f.sp_handle.reads  # type: ignore[union-attr]
        if POSITION_READ not in reads:
            what = ", ".join(sorted(reads)) or "nothing"
            raise InputError(
                f"SP cannot reach {host_name(f)} (model.{name}) of {model_name}: it was called with RaySamples but read "
                f"{what} of their frustums, never a position (origins, get_positions(), get_start_positions() or "
                "get_gaussian_blob()), so it reads positions some other way and would train without SP"
            )
