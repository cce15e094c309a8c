"""nerfacto's hash encodings as our :class:`~sp_plugins.encodings.HashGrid` where tiny-cuda-nn cannot run.

nerfstudio 1.1.5 builds its hash grids inside ``NerfactoModel.populate_modules``:

- the field's ``mlp_base`` is an ``MLPWithHashEncoding``: with tcnn one fused
  ``tcnn.NetworkWithInputEncoding`` (``mlp_base.model``), without it
  ``Sequential(HashEncoding, MLP)`` (``mlp_base.model.0`` / ``.1``);
- each proposal network (``HashMLPDensityField``) holds a ``HashEncoding`` as ``encoding``,
  registered a second time as ``mlp_base.0``.

Without tcnn, ``HashEncoding`` falls back to a slow torch implementation (with a "slow
implementation" warning per module) that is also a *different function* from the tcnn grid
nerfacto was designed with: level scales ``floor(min_res * growth**l)`` without tcnn's
``- 1`` / ``+ 0.5`` vertex convention, every level hashed (tcnn indexes the coarse levels that
fit densely), and a table initialised in ``[-1e-3, 1e-3]`` (tcnn: ``1e-4``). Our ``HashGrid`` is
tcnn's function and layout, with the same levels, table size, base resolution and per-level
scale (nerfstudio passes its ``growth_factor`` to tcnn as ``per_level_scale``), and takes the
same ``[0, 1]`` positions (nerfstudio maps the contracted ``[-2, 2]`` box with ``(x + 2) / 4``).

So, when tcnn cannot run on the model's device, :func:`use_sp_hash_grids` makes nerfstudio build
its torch modules (no warnings) and :func:`replace_hash_encodings` swaps every ``HashEncoding``
for a ``HashGrid`` (the MLPs stay nerfstudio's torch MLPs). Where tcnn runs, nothing changes:
nerfstudio's fused tcnn modules are faster still, and their checkpoints are nerfstudio's.
The hash-grid weights of a GPU checkpoint load either way (``tcnn_encoding.params`` maps onto
``table``), but the main field's fused tcnn MLP does not map onto a torch MLP: such a checkpoint
is refused with one line (:func:`refuse_fused_tcnn_checkpoints`).
"""

from __future__ import annotations

import logging
from typing import Dict, List, Optional, Union

import torch
from nerfstudio.field_components.encodings import HashEncoding
from torch import nn

from sp_plugins.encodings import HashGrid, tcnn_usable
from sp_plugins.adapter.errors import InputError
from sp_plugins.nerfstudio import table

log = logging.getLogger(__name__)

_announced: set = set()


def hash_grid_like(encoding: HashEncoding) -> HashGrid:
    """Our grid with ``encoding``'s levels, features, table size, base resolution and growth."""
    return HashGrid(
        num_levels=int(encoding.num_levels),
        features_per_level=int(encoding.features_per_level),
        log2_hashmap_size=int(encoding.log2_hashmap_size),
        base_resolution=int(encoding.min_res),
        per_level_scale=float(encoding.growth_factor),
        backend="auto",
    )


def replace_hash_encodings(module: nn.Module) -> List[str]:
    """Replace every torch-implemented ``HashEncoding`` below ``module`` by :func:`hash_grid_like`
    (one grid per encoding, wherever it is registered); the names it was registered under."""
    replaced: Dict[int, HashGrid] = {}
    names: List[str] = []
    for parent_name, parent in list(module.named_modules(remove_duplicate=False)):
        for child_name, child in list(parent._modules.items()):
            if isinstance(child, HashEncoding) and child.tcnn_encoding is None:
                if id(child) not in replaced:
                    replaced[id(child)] = hash_grid_like(child)
                setattr(parent, child_name, replaced[id(child)])
                names.append(f"{parent_name}.{child_name}" if parent_name else child_name)
    return names


def tcnn_runs_on(device: Union[str, torch.device, None]) -> bool:
    """Whether nerfstudio's tcnn modules can run on ``device`` (None: CUDA when available)."""
    if device is None:
        device = "cuda" if torch.cuda.is_available() else "cpu"
    return tcnn_usable(device)


def use_sp_hash_grids(device: Union[str, torch.device, None]) -> bool:
    """Whether a nerfacto model for ``device`` should build torch modules with our grids."""
    return not tcnn_runs_on(device)


def announce(method: str, device, names: List[str]) -> None:
    """Say once per process which grids were swapped in (nerfstudio's console when it has one)."""
    key = (method, str(device))
    if key in _announced:
        return
    _announced.add(key)
    def owner(name: str) -> str:  # "proposal_networks.0.mlp_base.0" -> "proposal_networks.0"
        parts = name.split(".")
        cut = next((i for i, p in enumerate(parts) if p in ("mlp_base", "encoding")), len(parts))
        return ".".join(parts[:cut]) or "the field"

    grids = sorted({owner(n) for n in names})
    message = (
        f"{method}: tiny-cuda-nn cannot run on {device or 'this machine'}: the hash grids of {', '.join(grids)} are "
        "sp_plugins' HashGrid (tcnn's function and layout, the host's levels and sizes), the MLPs torch"
    )
    log.info(message)
    try:
        from nerfstudio.utils.rich_utils import CONSOLE

        CONSOLE.print(message)
    except ImportError:  # pragma: no cover - nerfstudio always has it
        pass


FUSED_KEY_SUFFIX = "mlp_base.model.params"


def refuse_fused_tcnn_checkpoints(module: nn.Module, method: str) -> None:
    """A load pre-hook: a checkpoint whose field holds tcnn's fused ``NetworkWithInputEncoding``
    (``...mlp_base.model.params``) cannot load into torch MLPs; say so in one line instead of a
    list of missing keys."""

    def hook(state_dict, prefix, *args, **kwargs) -> None:
        fused = [k for k in state_dict if k.startswith(prefix) and k.endswith(FUSED_KEY_SUFFIX)]
        if fused:
            raise InputError(
                f"{method}: this checkpoint was trained with tiny-cuda-nn's fused MLP ({fused[0]}), which has no torch "
                "equivalent here (tiny-cuda-nn cannot run on this device); evaluate it on a CUDA machine with tinycudann"
            )

    module._register_load_state_dict_pre_hook(hook)


def setup_host_modules(model: nn.Module, method: str, device: Optional[Union[str, torch.device]]) -> List[str]:
    """After ``populate_modules`` built torch modules: swap in our grids, refuse fused-tcnn
    checkpoints, say so once. Returns the replaced names."""
    names = replace_hash_encodings(model)
    refuse_fused_tcnn_checkpoints(model, method)
    announce(method, device, names)
    return names


# -- nerfacto on our grids ----------------------------------------------------------------------
from dataclasses import dataclass, field  # noqa: E402
from typing import Type  # noqa: E402

from nerfstudio.models.nerfacto import NerfactoModel, NerfactoModelConfig  # noqa: E402


@dataclass
class NerfactoHashGridModelConfig(NerfactoModelConfig):
    """nerfacto, with our hash grids where tiny-cuda-nn cannot run (the base of ``sp-nerfacto``)."""

    _target: Type = field(default_factory=lambda: NerfactoHashGridModel)


class NerfactoHashGridModel(NerfactoModel):
    """``NerfactoModel`` that, where tcnn cannot run on its device, builds nerfstudio's torch
    modules (no slow-path warnings) and swaps their hash encodings for our :class:`HashGrid`.
    Not SP: ``sp-nerfacto`` is ``with_sp`` of the method built on it."""

    config: NerfactoHashGridModelConfig

    def populate_modules(self) -> None:
        device = self.kwargs.get("device")
        ours = use_sp_hash_grids(device)
        if ours:
            self.config.implementation = "torch"
        super().populate_modules()
        if ours:
            setup_host_modules(self, table.NERFACTO, device)
