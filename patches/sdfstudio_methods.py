"""Our methods in sdfstudio's ``ns-train`` list (registry entry ``sdfstudio_methods``).

Targets sdfstudio commit 370902a, which has no plugin mechanism: ``nerfstudio/configs/method_configs.py``
fills the dicts ``method_configs`` / ``descriptions`` and builds the tyro union
``AnnotatedBaseConfigUnion`` from them at import, and ``scripts/train.py`` copies that union at its
own import. Once ``scripts.train`` has executed, :func:`sp_plugins.sdfstudio.registration.add_methods`
adds our methods to both dicts and rebuilds the union in both modules. Leaving the scope takes
them out again: the dicts hold what they held (the same dict objects) and both modules have their
union back.
"""

from __future__ import annotations

import contextlib
from typing import Iterator, List, Tuple

from sp_plugins.patches.registry import Patch
from sp_plugins.patches.sdfstudio_import_hook import (
    expect_attribute, expect_source, patching, sdfstudio_patch,
)

__all__ = ["PATCH", "our_methods_in_ns_train"]

UNION = "AnnotatedBaseConfigUnion"


@contextlib.contextmanager
def our_methods_in_ns_train() -> Iterator[None]:
    snapshots: List[Tuple[dict, dict]] = []

    def add(module, rebind) -> None:
        import nerfstudio.configs.method_configs as host

        from sp_plugins.sdfstudio.registration import add_methods  # defers torch (entries() imports every patch)

        for table in (expect_attribute(PATCH, host, "method_configs"), expect_attribute(PATCH, host, "descriptions")):
            snapshots.append((table, dict(table)))
        rebind(host, UNION, expect_attribute(PATCH, host, UNION))  # (remembers the host's union)
        rebind(module, UNION, expect_attribute(PATCH, module, UNION))
        add_methods(module)

    try:
        with patching(after={"scripts.train": add}):
            yield
    finally:
        for table, before in snapshots:
            table.clear()
            table.update(before)


def _check(patch: Patch) -> None:
    expect_source(patch, "nerfstudio/configs/method_configs.py", "method_configs: Dict[str, Config] = {}", f"{UNION} =")
    expect_source(patch, "scripts/train.py", UNION)


PATCH = sdfstudio_patch(
    "sdfstudio_methods", _check, our_methods_in_ns_train, "nerfstudio/configs/method_configs.py", "scripts/train.py",
    changes="method_configs / descriptions dicts and the tyro union AnnotatedBaseConfigUnion (method_configs, scripts.train): our methods added",
    scope_text="process-wide in sp-sdfstudio-train and, opt-in, in sdfstudio's ns-train with the .pth hook")
