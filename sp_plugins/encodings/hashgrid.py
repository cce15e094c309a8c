"""Multiresolution hash grid (Instant-NGP): tiny-cuda-nn where it runs, pure torch elsewhere.

``HashGrid(...)`` takes the options of tcnn's ``HashGrid`` encoding and a ``backend``:
``"tcnn"`` (needs ``tinycudann`` and a CUDA device), ``"torch"`` (anywhere: CPU, CUDA, MPS), or
``"auto"``: tcnn where the module *is*, when ``tinycudann`` imports and the parameters are on a
CUDA device, the torch backend otherwise. The choice follows the module: it is made when the
grid is built (on the CPU, unless built under a CUDA default device) and again after every
``.to(...)`` / ``.cuda()`` / ``.cpu()``, which hands the values over between the two (so a fit or
``ns-train --machine.device-type cpu`` on a GPU machine runs the torch backend). Each choice is
logged once per device type. Build the optimizer after moving the module: a hand-over replaces
the Parameter object.

Both backends hold the grid in one parameter of the same layout: tcnn's ``tcnn_encoding.params``,
one flat float32 vector, and the torch backend's ``table``, the same flat vector (viewed as
``[rows, features]`` to look it up). So a checkpoint loads into either backend (the key is mapped;
nerfstudio's tcnn ``HashEncoding`` uses the same ``tcnn_encoding.params`` key) and so do the
optimizer's moments: torch's optimizers keep them per parameter, by position, with the
parameter's shape, so a run resumed under the other backend (trained on a CPU, continued on a GPU
with tcnn, or the reverse) carries on. The ``[rows, features]`` table of sp-plugins 0.1 does not
load (a size mismatch). The layout, read from tiny-cuda-nn's source
(``include/tiny-cuda-nn/encodings/grid.h``: ``GridEncodingTemplated``'s constructor and
``grid_index``; ``bindings/torch/tinycudann/modules.py`` and ``bindings.cpp`` for the dtype):

- levels back to back, coarsest first; a level has ``params_in_level = resolution**dims``
  entries rounded up to a multiple of 8, capped at ``2**log2_hashmap_size`` for hash grids; the
  offsets are the running sums, and ``n_params = total entries * n_features_per_level``;
- entry ``i`` of a level holds its features contiguously: value ``(offset + i) * F + f``, i.e.
  feature fastest, which is ``table.reshape(-1)`` for a ``[rows, F]`` table (our flat ``table``);
- the torch ``params`` Parameter is float32 (``initial_params`` makes a float32 tensor); the
  forward casts it to the module's parameter precision (half on most GPUs) per call.

:mod:`sp_plugins.encodings.tcnn_layout` is an independent, slow reading of that layout, used
as tcnn's stand-in in the tests.

The torch backend reproduces tcnn's semantics so that the two are interchangeable:

- inputs are expected in ``[0, 1]^dims``; level ``l`` uses ``scale_l = base_resolution *
  per_level_scale**l - 1`` (float32 arithmetic), ``position = x * scale_l + 0.5`` and
  ``resolution_l = ceil(scale_l) + 1`` vertices per axis;
- levels with ``resolution_l**dims <= 2**log2_hashmap_size`` are indexed densely
  (x fastest, then y, then z; modulo the level's padded size, so the ``+1`` corner on the far face
  wraps around exactly as in tcnn), finer levels by tcnn's hash: XOR of ``coord_i * prime_i`` with
  primes ``(1, 2654435761, 805459861)``, modulo the table size;
- Linear interpolation weights ``t``, Smoothstep weights ``t*t*(3-2t)`` (continuous derivative);
- the table is tcnn's flat layout (above), looked up as ``[entries, features_per_level]``;
- initialisation uniform in ``[-1e-4, 1e-4]`` as in tcnn.

Precision: the torch backend computes in the input's dtype (float32 or float64, so gradcheck
works) and in float32 for half-precision inputs, returning the input's dtype; tcnn's output is
cast to the input's dtype too.

Training tips (measured in ``bench/speed/hashgrid_speed.py`` on a CPU): use ``torch.optim.Adam(...,
fused=True)``; at 2^16 points per step it updates the 12M-value table about 5x faster than the
default Adam. A row-sparse optimizer is not provided: at that batch a step touches about 60% of
the rows, and finding them costs more than the fused dense update. Coarse-to-fine schedules call
:meth:`HashGrid.set_active_levels`.
"""

from __future__ import annotations

import contextlib
import logging
import math
from contextvars import ContextVar
from typing import Any, Dict, Literal, Mapping, Optional, Union

import torch
from jaxtyping import Float
from torch import Tensor, nn

from sp_plugins.encodings.grid_levels import GRID_TYPES, GridType, grid_levels, per_level_scale_from_max_resolution
from sp_plugins.encodings.hashgrid_torch import LevelConstants, hashgrid_encode, level_constants

logger = logging.getLogger(__name__)

Backend = Literal["auto", "tcnn", "torch"]
BACKENDS: tuple[str, ...] = ("auto", "tcnn", "torch")
Interpolation = Literal["Linear", "Smoothstep"]
INTERPOLATIONS: tuple[str, ...] = ("Linear", "Smoothstep")

TCNN_DEVICE_TYPES: tuple[str, ...] = ("cuda",)
"""Device types tiny-cuda-nn's kernels run on."""

_TORCH_ONLY: ContextVar[bool] = ContextVar("sp_plugins_hashgrid_torch_only", default=False)


@contextlib.contextmanager
def torch_backend_only():
    """Within the block (this thread or task), tiny-cuda-nn counts as unusable on every device: an
    ``auto`` grid built or moved there takes the torch backend, and so do nerfacto's grids
    (:func:`tcnn_usable`). What ``sp-gpu-check`` times our torch grid on a GPU with."""
    token = _TORCH_ONLY.set(True)
    try:
        yield
    finally:
        _TORCH_ONLY.reset(token)

_logged_choices: set = set()


def _import_tcnn():
    """The ``tinycudann`` module, or None when it does not import (not installed, no CUDA: its
    import raises ``EnvironmentError`` without a GPU)."""
    try:
        import tinycudann
    except (ImportError, OSError, RuntimeError):
        return None
    return tinycudann


def on_device(device: Union[str, torch.device]):
    """``torch.cuda.device(device)`` for a CUDA device, else nothing: tiny-cuda-nn builds its
    native module and launches its kernels on the *current* CUDA device, so a grid on ``cuda:1``
    (another DDP rank's GPU) is built and called with that device current."""
    import contextlib

    device = torch.device(device)
    return torch.cuda.device(device) if device.type == "cuda" else contextlib.nullcontext()


def tcnn_available() -> bool:
    """True when ``tinycudann`` imports and a CUDA device is available."""
    return torch.cuda.is_available() and _import_tcnn() is not None


def tcnn_usable(device: Union[str, torch.device], dtype: torch.dtype = torch.float32) -> bool:
    """Whether tiny-cuda-nn can hold a grid on ``device``: a CUDA device, ``tinycudann`` imports,
    and the table is float32 (tcnn's torch bindings keep ``params`` in float32)."""
    device = torch.device(device)
    if _TORCH_ONLY.get():
        return False
    return device.type in TCNN_DEVICE_TYPES and dtype == torch.float32 and _import_tcnn() is not None


def resolve_backend(backend: str, device: Union[str, torch.device] = "cpu", dtype: torch.dtype = torch.float32) -> str:
    """The backend a grid of ``dtype`` on ``device`` runs: ``auto`` is ``tcnn`` where
    :func:`tcnn_usable`, else ``torch`` (logged once per choice and device type); an explicit
    ``tcnn`` that cannot run there is refused."""
    if backend not in BACKENDS:
        raise ValueError(f"backend={backend!r} is not a backend; allowed values: {', '.join(BACKENDS)}")
    if backend == "torch":
        return "torch"
    device = torch.device(device)
    usable = tcnn_usable(device, dtype)
    if backend == "tcnn":
        if not usable:
            raise ValueError(
                f"backend='tcnn' cannot hold a {dtype} grid on {device}: it needs the tinycudann package, a CUDA "
                "device and a float32 table; install it (pip install git+https://github.com/NVlabs/tiny-cuda-nn/#subdirectory=bindings/torch), move the module to CUDA, "
                "or use backend='auto' / 'torch'"
            )
        return "tcnn"
    choice = "tcnn" if usable else "torch"
    key = (choice, device.type)
    if key not in _logged_choices:
        _logged_choices.add(key)
        if usable:
            reason = f"tinycudann imports and the module is on {device.type}"
        elif _TORCH_ONLY.get():
            reason = "torch_backend_only() is in force"
        elif device.type not in TCNN_DEVICE_TYPES:
            reason = f"the module is on {device.type}; tiny-cuda-nn runs on CUDA only"
        elif dtype != torch.float32:
            reason = f"the table is {dtype}; tiny-cuda-nn keeps float32 parameters"
        else:
            reason = "tinycudann does not import"
        logger.info("HashGrid backend 'auto' -> '%s' (%s)", choice, reason)
    return choice


class HashGrid(nn.Module):
    """Multiresolution hash encoding ``[..., dims] in [0,1] -> [..., num_levels * features_per_level]``.

    Args:
        num_levels: number of levels L.
        features_per_level: features F stored per table row (tcnn allows 1, 2, 4, 8).
        log2_hashmap_size: log2 of the maximum rows per level T.
        base_resolution: vertices per axis of the coarsest level.
        per_level_scale: growth factor between levels; or give ``max_resolution`` instead
            (then ``(max / base) ** (1 / (L - 1))``). Neither: 2.0, tcnn's default.
        interpolation: ``Linear`` or ``Smoothstep``.
        grid_type: ``Hash`` (hash the levels that do not fit) or ``Dense`` (never hash).
        backend: ``auto`` | ``tcnn`` | ``torch``.
        n_input_dims: 2 or 3.
        init_scale: the table starts uniform in ``[-init_scale, init_scale]``.
        dtype: dtype of the torch backend's table.
    """

    def __init__(
        self,
        num_levels: int = 16,
        features_per_level: int = 2,
        log2_hashmap_size: int = 19,
        base_resolution: int = 16,
        per_level_scale: Optional[float] = None,
        max_resolution: Optional[int] = None,
        interpolation: Interpolation = "Linear",
        grid_type: GridType = "Hash",
        backend: Backend = "auto",
        *,
        n_input_dims: int = 3,
        init_scale: float = 1e-4,
        dtype: torch.dtype = torch.float32,
    ) -> None:
        super().__init__()
        if interpolation not in INTERPOLATIONS:
            raise ValueError(
                f"interpolation={interpolation!r} is not supported; allowed values: {', '.join(INTERPOLATIONS)}"
            )
        if grid_type not in GRID_TYPES:
            raise ValueError(f"grid_type={grid_type!r} is not supported; allowed values: {', '.join(GRID_TYPES)}")
        if n_input_dims not in (2, 3):
            raise ValueError(f"n_input_dims={n_input_dims}: must be 2 or 3 (as in tcnn)")
        if features_per_level not in (1, 2, 4, 8):
            raise ValueError(f"features_per_level={features_per_level}: must be 1, 2, 4 or 8 (as in tcnn)")
        if num_levels < 1 or base_resolution < 1 or not 1 <= log2_hashmap_size <= 30:
            raise ValueError(
                f"num_levels={num_levels}, base_resolution={base_resolution} must be >= 1 and "
                f"log2_hashmap_size={log2_hashmap_size} in [1, 30]"
            )
        if per_level_scale is not None and max_resolution is not None:
            raise ValueError("give per_level_scale or max_resolution, not both")
        if max_resolution is not None:
            if max_resolution < base_resolution:
                raise ValueError(f"max_resolution={max_resolution} must be >= base_resolution={base_resolution}")
            per_level_scale = per_level_scale_from_max_resolution(base_resolution, max_resolution, num_levels)
        if per_level_scale is None:
            per_level_scale = 2.0
        if not (math.isfinite(per_level_scale) and per_level_scale >= 1.0):
            raise ValueError(f"per_level_scale={per_level_scale}: must be a finite number >= 1")

        self.n_input_dims = n_input_dims
        self.num_levels = num_levels
        self.features_per_level = features_per_level
        self.log2_hashmap_size = log2_hashmap_size
        self.base_resolution = base_resolution
        self.per_level_scale = float(per_level_scale)
        self.interpolation = interpolation
        self.grid_type = grid_type
        self.n_output_dims = num_levels * features_per_level
        self.levels = grid_levels(num_levels, n_input_dims, log2_hashmap_size, base_resolution, per_level_scale, grid_type)
        n_values = (self.levels[-1].offset + self.levels[-1].size) * features_per_level
        if n_values > 2**31:
            raise ValueError(
                f"the grid would hold {n_values:.3g} values (finest resolution {self.levels[-1].resolution}, "
                f"grid_type={grid_type!r}); use grid_type='Hash', fewer levels or a lower resolution"
            )
        self.active_levels = num_levels
        self.n_table_rows = self.levels[-1].offset + self.levels[-1].size
        if backend not in BACKENDS:
            raise ValueError(f"backend={backend!r} is not a backend; allowed values: {', '.join(BACKENDS)}")
        self.requested_backend = backend
        self.backend = "torch"
        self.tcnn_encoding: Any = None  # a tinycudann.Encoding (no type information) on the tcnn backend
        table = torch.empty(self.n_table_rows * features_per_level, dtype=dtype).uniform_(-init_scale, init_scale)
        # flat: tcnn's params layout, so optimizer state fits either backend; None on the tcnn backend
        self.table: Optional[nn.Parameter] = nn.Parameter(table)
        self._make_constants()
        if backend == "tcnn":  # tcnn keeps its parameters on the current CUDA device from the start
            resolve_backend("tcnn", "cuda", dtype)
            self._use_tcnn(torch.device("cuda"))
        else:
            self._sync_backend()

    # -- where the parameters live --------------------------------------------------------------
    def _make_constants(self) -> None:
        """Per-level constants as non-persistent buffers on the parameters' device (remade after
        every move or cast, so ``.half()`` cannot round the level scales)."""
        device = self.table.device if self.table is not None else self.tcnn_encoding.params.device
        for name, value in level_constants(self.levels, self.n_input_dims, device)._asdict().items():
            self.register_buffer(f"_const_{name}", value, persistent=False)

    def _constants(self):
        return LevelConstants(*(getattr(self, f"_const_{name}") for name in LevelConstants._fields))

    def _parameter(self) -> Tensor:
        return self.table if self.table is not None else self.tcnn_encoding.params

    def _sync_backend(self) -> None:
        """Put the parameters in the backend that runs where they are now (``auto``), or check
        that the requested one can (``tcnn``). Moving between backends keeps the values; it
        replaces the Parameter object, so build optimizers after moving the module (as
        nerfstudio and the fitting tasks do)."""
        param = self._parameter()
        if self.requested_backend == "torch":
            return
        if self.requested_backend == "tcnn":
            if not tcnn_usable(param.device):
                raise ValueError(
                    f"HashGrid(backend='tcnn') cannot run on {param.device}: tiny-cuda-nn runs on CUDA devices only; "
                    "use backend='auto' to switch to the torch backend off the GPU"
                )
            return
        dtype = torch.float32 if self.backend == "tcnn" else param.dtype  # tcnn's params stay float32
        choice = resolve_backend("auto", param.device, dtype)
        if choice == "tcnn" and self.backend == "torch":
            self._use_tcnn()
        elif choice == "torch" and self.backend == "tcnn":
            self._use_torch()

    def _use_tcnn(self, device: Optional[torch.device] = None) -> None:
        """Hand the table to a ``tinycudann.Encoding`` on ``device`` (default: the table's); its flat
        ``params`` are ``table.reshape(-1)``."""
        tcnn = _import_tcnn()
        table = self.table
        assert table is not None  # called on the torch backend
        device = table.device if device is None else torch.device(device)
        if device.type == "cuda" and device.index is None:
            device = torch.device("cuda", torch.cuda.current_device())
        with on_device(device):
            encoding = tcnn.Encoding(n_input_dims=self.n_input_dims, encoding_config=self.tcnn_config())
        if encoding.params.numel() != table.numel():
            raise RuntimeError(
                f"tinycudann made {encoding.params.numel()} grid parameters where tcnn's documented layout gives "
                f"{table.numel()} ({self.tcnn_config()}): this tiny-cuda-nn version lays the grid out differently"
            )
        encoding = encoding.to(device)
        with torch.no_grad():
            encoding.params.copy_(table.detach())
        self.table = None
        self.tcnn_encoding = encoding
        self.backend = "tcnn"
        self._make_constants()

    def _use_torch(self) -> None:
        params = self.tcnn_encoding.params
        self.tcnn_encoding = None
        self.table = nn.Parameter(params.detach().clone())
        self.backend = "torch"
        self._make_constants()

    def _apply(self, fn, recurse: bool = True):
        module = super()._apply(fn, recurse)
        self._sync_backend()
        self._make_constants()
        return module

    def _load_from_state_dict(self, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs):
        """Checkpoints move between backends: the torch backend's ``table`` and tcnn's
        ``tcnn_encoding.params`` are the same flat vector (see the module docstring), so either
        loads into either."""
        table_key, tcnn_key = prefix + "table", prefix + "tcnn_encoding.params"
        n_values = self.n_table_rows * self.features_per_level
        source = tcnn_key if self.backend == "torch" else table_key
        target = table_key if self.backend == "torch" else tcnn_key
        if source in state_dict and target not in state_dict:
            value = state_dict.pop(source)
            if value.numel() != n_values:
                error_msgs.append(
                    f"HashGrid {prefix or '(root)'}: the checkpoint's {source!r} holds {value.numel()} grid values, this grid "
                    f"{n_values} ({self.num_levels} levels x {self.features_per_level} features, 2^{self.log2_hashmap_size} rows, "
                    f"resolutions {self.levels[0].resolution}..{self.levels[-1].resolution}): the grids differ"
                )
                return
            state_dict[target] = value.reshape(-1)
        super()._load_from_state_dict(state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs)

    # ----------------------------------------------------------------------------------------
    @classmethod
    def from_tcnn_config(
        cls, n_input_dims: int, encoding_config: Mapping[str, Any], backend: Backend = "auto"
    ) -> "HashGrid":
        """Build from a tcnn ``encoding_config`` dict (``otype`` HashGrid, DenseGrid or Grid)."""
        config = dict(encoding_config)
        otype = config.pop("otype", "Grid")
        if otype not in ("HashGrid", "DenseGrid", "Grid"):
            raise ValueError(f"encoding otype={otype!r}: only HashGrid, DenseGrid and Grid are supported")
        grid_type = config.pop("type", "Dense" if otype == "DenseGrid" else "Hash")
        hash_kind = config.pop("hash", "CoherentPrime")
        if hash_kind != "CoherentPrime":
            raise ValueError(f"encoding hash={hash_kind!r}: only tcnn's default 'CoherentPrime' is supported")
        if config.pop("stochastic_interpolation", False):
            raise ValueError("stochastic_interpolation=True is not supported")
        known = {"n_levels", "n_features_per_level", "log2_hashmap_size", "base_resolution", "per_level_scale", "interpolation"}
        unknown = set(config) - known
        if unknown:
            raise ValueError(f"unsupported keys in the tcnn encoding config: {sorted(unknown)}")
        return cls(
            num_levels=int(config.get("n_levels", 16)),
            features_per_level=int(config.get("n_features_per_level", 2)),
            log2_hashmap_size=int(config.get("log2_hashmap_size", 19)),
            base_resolution=int(config.get("base_resolution", 16)),
            per_level_scale=float(config.get("per_level_scale", 2.0)),
            interpolation=config.get("interpolation", "Linear"),
            grid_type=grid_type,
            backend=backend,
            n_input_dims=n_input_dims,
        )

    def tcnn_config(self) -> Dict[str, Any]:
        """The equivalent tcnn ``encoding_config``."""
        return {
            "otype": "Grid",
            "type": self.grid_type,
            "n_levels": self.num_levels,
            "n_features_per_level": self.features_per_level,
            "log2_hashmap_size": self.log2_hashmap_size,
            "base_resolution": self.base_resolution,
            "per_level_scale": self.per_level_scale,
            "interpolation": self.interpolation,
        }

    def set_active_levels(self, n: Optional[int]) -> None:
        """Coarse-to-fine: only the ``n`` coarsest levels contribute; finer ones output zeros (and
        receive no gradient). ``None`` re-enables all. The torch backend skips the masked levels'
        work entirely."""
        if n is None:
            n = self.num_levels
        if not 0 <= int(n) <= self.num_levels:
            raise ValueError(f"active levels n={n}: must be in [0, {self.num_levels}] or None")
        self.active_levels = int(n)

    def get_out_dim(self) -> int:
        return self.n_output_dims

    def forward(self, x: Float[Tensor, "*batch dims"]) -> Float[Tensor, "*batch out"]:
        if x.shape[-1] != self.n_input_dims:
            raise ValueError(f"positions have {x.shape[-1]} coordinates; this HashGrid expects {self.n_input_dims}")
        if not x.is_floating_point():
            raise ValueError(f"positions must be a floating-point tensor, got {x.dtype}")
        batch = x.shape[:-1]
        flat = x.reshape(-1, self.n_input_dims)
        n_active = self.active_levels
        if self.tcnn_encoding is not None:
            with on_device(self.tcnn_encoding.params.device):
                out = self.tcnn_encoding(flat).to(x.dtype)
            if n_active < self.num_levels:
                kept = n_active * self.features_per_level
                out = torch.cat([out[:, :kept], out.new_zeros(out.shape[0], self.n_output_dims - kept)], dim=-1)
            return out.reshape(*batch, self.n_output_dims)
        # positions need float32 at least: x * 2047 in half precision would snap to a coarse grid
        compute_dtype = x.dtype if x.dtype in (torch.float32, torch.float64) else torch.float32
        flat = flat.to(compute_dtype)
        param = self.table
        assert param is not None  # the torch backend (the tcnn one returned above)
        table = (param if param.dtype == compute_dtype else param.to(compute_dtype)).view(-1, self.features_per_level)
        if n_active == 0:
            out = flat.new_zeros(flat.shape[0], self.n_output_dims)
        else:
            out = hashgrid_encode(
                flat,
                table,
                self.levels[:n_active],
                2**self.log2_hashmap_size,
                smoothstep=self.interpolation == "Smoothstep",
                constants=self._constants().head(n_active),
            )
            if n_active < self.num_levels:
                pad = out.new_zeros(out.shape[0], (self.num_levels - n_active) * self.features_per_level)
                out = torch.cat([out, pad], dim=-1)
        return out.to(x.dtype).reshape(*batch, self.n_output_dims)

    def extra_repr(self) -> str:
        return (
            f"backend={self.backend}, dims={self.n_input_dims}, levels={self.num_levels}x{self.features_per_level}, "
            f"log2_T={self.log2_hashmap_size}, res={self.levels[0].resolution}..{self.levels[-1].resolution}, "
            f"per_level_scale={self.per_level_scale:.4f}, {self.interpolation}, dense_levels="
            f"{sum(not lv.hashed for lv in self.levels)}"
        )
