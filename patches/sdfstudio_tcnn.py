"""A pure-torch stand-in for the part of tiny-cuda-nn's API that sdfstudio's fields call.

Targets sdfstudio commit 370902a. Its modules do ``try: import tinycudann as tcnn`` and build
``tcnn.Encoding`` (``SDFField`` with ``encoding_type="hash"``: every SDF method with a grid),
``tcnn.NetworkWithInputEncoding`` (``HashMLPDensityField``: neus-facto's and bakedangelo's
proposal networks) and ``tcnn.Encoding`` / ``tcnn.Network`` (``TCNNNerfactoField``: bakedangelo's
``background_model="grid"``). Without tinycudann those calls fail with ``NameError: tcnn``.

After such a module executed *without* a ``tcnn`` global (the import failed), this module is
given to it as ``tcnn``; a module that imported the real tinycudann keeps it, and nothing is
registered under the name ``tinycudann``, so other code never mistakes the stand-in for tcnn.

What is covered (what the four SDF methods need):

- encodings ``HashGrid`` / ``DenseGrid`` / ``Grid`` on :class:`sp_plugins.encodings.HashGrid`
  (its torch backend, tcnn's semantics: inputs in [0, 1], same level scales);
  ``SphericalHarmonics`` (inputs in [0, 1] mapped to [-1, 1], sdfstudio's own SH basis);
  ``Frequency`` (sin and cos of ``2^i * pi * x``);
- networks ``FullyFusedMLP`` / ``CutlassMLP``: linear layers without biases (tcnn has none),
  activations ``ReLU``, ``None``, ``Sigmoid``, ``Softplus``, ``Exponential``.

Outputs are float32 (tcnn's are half precision). Anything else raises ``NotImplementedError``
naming the option.
"""

from __future__ import annotations

import math
from typing import Any, Mapping

import torch
from torch import Tensor, nn

import contextlib
from typing import Iterator

from sp_plugins.encodings import HashGrid
from sp_plugins.patches.registry import Patch
from sp_plugins.patches.sdfstudio_import_hook import HOST_COMMIT, expect_source, patching, sdfstudio_patch

__all__ = ["Encoding", "HOST_COMMIT", "Network", "NetworkWithInputEncoding", "PATCH"]

STAND_IN = True
"""Marks this module as the stand-in (a real tinycudann has no such attribute)."""

MODULES = (
    "nerfstudio.fields.sdf_field",
    "nerfstudio.fields.density_fields",
    "nerfstudio.fields.nerfacto_field",
    "nerfstudio.fields.instant_ngp_field",
    "nerfstudio.field_components.encodings",
)

_ACTIVATIONS = {
    "None": nn.Identity,
    "ReLU": nn.ReLU,
    "Sigmoid": nn.Sigmoid,
    "Softplus": nn.Softplus,
    "Exponential": lambda: _Exp(),
}


class _Exp(nn.Module):
    def forward(self, x: Tensor) -> Tensor:
        return torch.exp(x)


class _SphericalHarmonics(nn.Module):
    def __init__(self, n_input_dims: int, degree: int) -> None:
        super().__init__()
        if n_input_dims != 3 or not 1 <= degree <= 5:
            raise NotImplementedError(f"the torch stand-in for tinycudann has no SphericalHarmonics with n_input_dims={n_input_dims}, "
                                      f"degree={degree} (it has 3 inputs, degree 1-5); install tiny-cuda-nn")
        self.degree = degree
        self.n_output_dims = degree**2

    def forward(self, x: Tensor) -> Tensor:
        from nerfstudio.utils.math import components_from_spherical_harmonics

        return components_from_spherical_harmonics(self.degree, x * 2.0 - 1.0)


class _Frequency(nn.Module):
    def __init__(self, n_input_dims: int, n_frequencies: int) -> None:
        super().__init__()
        self.register_buffer("freqs", (2.0 ** torch.arange(n_frequencies)) * math.pi, persistent=False)
        self.n_output_dims = n_input_dims * n_frequencies * 2

    def forward(self, x: Tensor) -> Tensor:
        scaled = (x[..., :, None] * self.freqs).flatten(-2)
        return torch.cat([torch.sin(scaled), torch.cos(scaled)], dim=-1)


def Encoding(n_input_dims: int, encoding_config: Mapping[str, Any], dtype: Any = None, **_: Any) -> nn.Module:
    """``tcnn.Encoding``: a module with ``n_output_dims``."""
    config = dict(encoding_config)
    otype = config.get("otype")
    if otype in ("HashGrid", "DenseGrid", "Grid"):
        return HashGrid.from_tcnn_config(n_input_dims, config, backend="torch")
    if otype == "SphericalHarmonics":
        return _SphericalHarmonics(n_input_dims, int(config.get("degree", 4)))
    if otype == "Frequency":
        return _Frequency(n_input_dims, int(config.get("n_frequencies", 12)))
    raise NotImplementedError(f"the torch stand-in for tinycudann has no encoding otype={otype!r}; install tiny-cuda-nn")


class Network(nn.Module):
    """``tcnn.Network``: an MLP without biases, ``n_hidden_layers`` layers of ``n_neurons``."""

    def __init__(self, n_input_dims: int, n_output_dims: int, network_config: Mapping[str, Any], **_: Any) -> None:
        super().__init__()
        otype = network_config.get("otype", "FullyFusedMLP")
        if otype not in ("FullyFusedMLP", "CutlassMLP"):
            raise NotImplementedError(f"the torch stand-in for tinycudann has no network otype={otype!r}; install tiny-cuda-nn")
        act, out_act = network_config.get("activation", "ReLU"), network_config.get("output_activation", "None")
        for name in (act, out_act):
            if name not in _ACTIVATIONS:
                raise NotImplementedError(f"the torch stand-in for tinycudann has no activation {name!r}; install tiny-cuda-nn")
        width, hidden = int(network_config.get("n_neurons", 64)), int(network_config.get("n_hidden_layers", 1))
        dims = [n_input_dims] + [width] * hidden + [n_output_dims]
        layers: list = []
        for i in range(len(dims) - 1):
            layers.append(nn.Linear(dims[i], dims[i + 1], bias=False))
            layers.append(_ACTIVATIONS[act if i < len(dims) - 2 else out_act]())
        self.layers = nn.Sequential(*layers)
        self.n_input_dims, self.n_output_dims = n_input_dims, n_output_dims

    def forward(self, x: Tensor) -> Tensor:
        return self.layers(x.float())


class NetworkWithInputEncoding(nn.Module):
    """``tcnn.NetworkWithInputEncoding``: :func:`Encoding` followed by :class:`Network`."""

    def __init__(
        self, n_input_dims: int, n_output_dims: int, encoding_config: Mapping[str, Any], network_config: Mapping[str, Any], **_: Any
    ) -> None:
        super().__init__()
        self.encoding = Encoding(n_input_dims, encoding_config)
        self.network = Network(self.encoding.n_output_dims, n_output_dims, network_config)
        self.n_input_dims, self.n_output_dims = n_input_dims, n_output_dims

    def forward(self, x: Tensor) -> Tensor:
        return self.network(self.encoding(x))


def _give_stand_in(module, rebind=None) -> None:
    if "tcnn" not in vars(module):
        import sys

        (rebind or setattr)(module, "tcnn", sys.modules[__name__])


@contextlib.contextmanager
def tcnn_stand_in_for_sdfstudio() -> Iterator[None]:
    with patching(after={name: _give_stand_in for name in MODULES}):
        yield


def _check(patch: Patch) -> None:
    expect_source(patch, "nerfstudio/fields/sdf_field.py", "import tinycudann as tcnn", "tcnn.Encoding(")


PATCH = sdfstudio_patch(
    "sdfstudio_tcnn", _check, tcnn_stand_in_for_sdfstudio, "nerfstudio/fields/sdf_field.py",
    changes="`tcnn` global of sdfstudio's field modules whose tinycudann import failed: this pure-torch stand-in",
    scope_text="those sdfstudio modules; process-wide (those modules) in sp-sdfstudio-* / the hook")
