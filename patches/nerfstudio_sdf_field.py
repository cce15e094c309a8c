"""Let nerfstudio's ``SDFField`` run without tiny-cuda-nn, on our torch :class:`HashGrid`.

Targets nerfstudio 1.1.5 (see ``TESTED_NERFSTUDIO_VERSIONS``). There, ``nerfstudio/fields/sdf_field.py``
does ``from nerfstudio.utils.external import tcnn`` at import time and ``SDFField.__init__``
calls ``tcnn.Encoding(n_input_dims=3, encoding_config={...})`` unconditionally; without tcnn that
name is a lazy error object, so NeuS cannot even be constructed. The patch rebinds the module
global ``nerfstudio.fields.sdf_field.tcnn`` to a tiny namespace whose ``Encoding`` builds a
:class:`HashGrid` (torch backend) from the same config. Nothing else in nerfstudio changes.

Registry entry ``nerfstudio_sdf_field``, scoped: our SDF field builds its host part inside
``registry.scope("nerfstudio_sdf_field")`` (:func:`torch_tcnn_fallback`), which installs the
fallback for that construction only and restores nerfstudio's ``tcnn`` after, so an ``SDFField``
of any other method is built exactly as without sp-plugins. When tcnn imports and CUDA is
available it does nothing.
"""

from __future__ import annotations

import importlib.metadata
import inspect
import logging
import types
import warnings
from contextlib import contextmanager
from typing import Any, Iterator, Mapping, Optional

import torch

from sp_plugins.encodings.hashgrid import HashGrid
from sp_plugins.patches.registry import nerfstudio_patch

logger = logging.getLogger(__name__)

TESTED_NERFSTUDIO_VERSIONS: tuple[str, ...] = ("1.1.5",)
PATCHED_MODULE = "nerfstudio.fields.sdf_field"
PATCHED_ATTRIBUTE = "tcnn"

_original: Optional[Any] = None


def _encoding(n_input_dims: int, encoding_config: Mapping[str, Any], seed: int = 1337, dtype: Optional[torch.dtype] = None):
    """Stand-in for ``tinycudann.Encoding``: a torch :class:`HashGrid` (``seed`` follows torch's RNG)."""
    return HashGrid.from_tcnn_config(n_input_dims, encoding_config, backend="torch")


class _TorchTcnnShim(types.SimpleNamespace):
    """Only ``Encoding`` is provided; anything else names the patch instead of failing deep inside."""

    def __getattr__(self, name: str):
        if name.startswith("__"):
            raise AttributeError(name)
        raise RuntimeError(
            f"tinycudann.{name} is not available: sp_plugins' torch fallback only provides tcnn.Encoding "
            "(grid encodings). Install tiny-cuda-nn for the rest."
        )


def _looks_like_tcnn(value: Any) -> bool:
    """tinycudann, nerfstudio's lazy import error standing in for it, or our shim."""
    from nerfstudio.utils import external

    return value is getattr(external, "tcnn", None) or isinstance(value, (types.ModuleType, _TorchTcnnShim))


def check_nerfstudio_sdf_field() -> str:
    """Verify the nerfstudio internals the patch relies on; return the nerfstudio version.

    Raises ``RuntimeError`` when ``sdf_field`` no longer looks ``tcnn`` up as a module global
    used as ``tcnn.Encoding(...)`` in ``SDFField.__init__``, or when the field no longer reads
    ``self.encoding.n_output_dims`` (what our HashGrid provides)."""
    from nerfstudio.fields import sdf_field

    version = importlib.metadata.version("nerfstudio")
    problems = []
    if not hasattr(sdf_field, PATCHED_ATTRIBUTE):
        problems.append(f"{PATCHED_MODULE} has no module attribute '{PATCHED_ATTRIBUTE}'")
    elif not _looks_like_tcnn(getattr(sdf_field, PATCHED_ATTRIBUTE)):
        problems.append(f"{PATCHED_MODULE}.{PATCHED_ATTRIBUTE} = {getattr(sdf_field, PATCHED_ATTRIBUTE)!r} has no Encoding")
    host = getattr(sdf_field, "SDFField", None)
    try:
        init_src = inspect.getsource(host.__init__)
        layers_src = inspect.getsource(host.initialize_geo_layers)
    except (AttributeError, OSError, TypeError):
        init_src = layers_src = ""
        problems.append(f"{PATCHED_MODULE}.SDFField = {host!r} (its __init__ / initialize_geo_layers unreadable)")
    if init_src and "tcnn.Encoding(" not in init_src:
        problems.append("SDFField.__init__ no longer calls tcnn.Encoding(...)")
    if layers_src and "self.encoding.n_output_dims" not in layers_src:
        problems.append("SDFField.initialize_geo_layers no longer reads self.encoding.n_output_dims")
    if problems:
        PATCH.fail(f"{PATCHED_MODULE}.{PATCHED_ATTRIBUTE}.Encoding(...) in SDFField.__init__", "; ".join(problems))
    return version


def install_torch_tcnn_fallback(force: bool = False) -> bool:
    """Make ``SDFField`` build a torch :class:`HashGrid` when tcnn is unusable (the registry's scope
    calls it; :func:`torch_tcnn_fallback` undoes it).

    Returns True when the fallback is (now) installed, False when a real tcnn with CUDA is left in
    place. ``force`` installs it even then (for tests and CPU runs on GPU machines). Idempotent.
    """
    global _original
    from nerfstudio.fields import sdf_field
    from nerfstudio.utils import external

    version = check_nerfstudio_sdf_field()
    current = getattr(sdf_field, PATCHED_ATTRIBUTE)
    if isinstance(current, _TorchTcnnShim):
        return True
    if external.TCNN_EXISTS and torch.cuda.is_available() and not force:
        return False
    if version not in TESTED_NERFSTUDIO_VERSIONS:
        warnings.warn(
            f"sp_plugins' SDFField tcnn fallback was tested with nerfstudio {TESTED_NERFSTUDIO_VERSIONS}, "
            f"found {version}; it passed the structural checks, so it is installed anyway",
            stacklevel=2,
        )
    _original = current
    setattr(sdf_field, PATCHED_ATTRIBUTE, _TorchTcnnShim(Encoding=_encoding))
    logger.info("nerfstudio SDFField: tiny-cuda-nn unavailable, hash grids use sp_plugins' torch HashGrid")
    return True


def uninstall_torch_tcnn_fallback() -> None:
    """Restore what ``install_torch_tcnn_fallback`` replaced (no-op when it is not installed)."""
    global _original
    from nerfstudio.fields import sdf_field

    if isinstance(getattr(sdf_field, PATCHED_ATTRIBUTE), _TorchTcnnShim):
        setattr(sdf_field, PATCHED_ATTRIBUTE, _original)
        _original = None


def torch_tcnn_fallback_installed() -> bool:
    from nerfstudio.fields import sdf_field

    return isinstance(getattr(sdf_field, PATCHED_ATTRIBUTE), _TorchTcnnShim)


@contextmanager
def torch_tcnn_fallback(force: bool = False) -> Iterator[bool]:
    """The fallback for the duration of the block (yields whether it is active); afterwards
    nerfstudio's ``tcnn`` is what it was before."""
    was_installed = torch_tcnn_fallback_installed()
    active = install_torch_tcnn_fallback(force)
    try:
        yield active
    finally:
        if active and not was_installed:
            uninstall_torch_tcnn_fallback()


PATCH = nerfstudio_patch(
    "nerfstudio_sdf_field", TESTED_NERFSTUDIO_VERSIONS, lambda patch: check_nerfstudio_sdf_field(), torch_tcnn_fallback,
    ((PATCHED_MODULE, PATCHED_ATTRIBUTE), (PATCHED_MODULE, "SDFField")),
    changes=f"{PATCHED_MODULE}.{PATCHED_ATTRIBUTE}: a namespace whose Encoding is our torch HashGrid (no tiny-cuda-nn, or no CUDA)",
    scope_text="the construction of our SDF field's host part (CoarseToFineSDFField.__init__)")
