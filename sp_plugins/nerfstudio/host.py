"""nerfstudio 1.x as the adapter's registry sees it (entry point ``sp_plugins.hosts``: ``nerfstudio``)."""

from __future__ import annotations

from sp_plugins.adapter.hosts import Flags, Host
from sp_plugins.sdfstudio.detect import is_sdfstudio, nerfstudio_dir


def _installed() -> bool:
    """nerfstudio 1.x is the importable ``nerfstudio`` (not sdfstudio's, which shares the name)."""
    return nerfstudio_dir() is not None and not is_sdfstudio()


HOST = Host(
    name="nerfstudio",
    packages=("nerfstudio",),
    table="sp_plugins.nerfstudio.table",
    flags=Flags(steps="--max-num-iterations", device="--machine.device-type", devices="--machine.num-devices"),
    docs_page="docs/guides/any-method.md",
    renamed={  # our SDF field in earlier releases (it perturbs nothing itself), in run folders saved then
        "sp_plugins.nerfstudio.sdf_field.SPSDFFieldConfig": "sp_plugins.nerfstudio.sdf_field.CoarseToFineSDFFieldConfig",
        "sp_plugins.nerfstudio.sdf_field.SPSDFField": "sp_plugins.nerfstudio.sdf_field.CoarseToFineSDFField",
    },
    available=_installed,
)
