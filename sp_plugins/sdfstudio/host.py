"""sdfstudio (commit 370902a) as the adapter's registry sees it (entry point ``sp_plugins.hosts``: ``sdfstudio``)."""

from __future__ import annotations

from sp_plugins.adapter.hosts import Flags, Host
from sp_plugins.sdfstudio.detect import is_sdfstudio

HOST = Host(
    name="sdfstudio",
    packages=("nerfstudio",),  # sdfstudio's package is also named nerfstudio
    table="sp_plugins.sdfstudio.table",
    imports=("scripts",),
    flags=Flags(steps="--trainer.max-num-iterations", device="--machine.device-type", devices="--machine.num-gpus"),
    docs_page="docs/guides/sdfstudio.md",
    renamed={  # the seam's names in earlier releases, in run folders saved then
        "sp_plugins.sdfstudio.seam.SPSDFFieldConfig": "sp_plugins.sdfstudio.seam.SeamSDFFieldConfig",
        "sp_plugins.sdfstudio.seam.SPSDFField": "sp_plugins.sdfstudio.seam.SeamSDFField",
    },
    available=is_sdfstudio,
)
