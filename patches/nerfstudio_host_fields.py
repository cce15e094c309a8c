"""Let a host model build *our* field subclass with its own arguments (nerfstudio 1.1.5).

nerfstudio's models construct their fields inside ``populate_modules`` from a module-level name
(``nerfstudio.models.nerfacto.NerfactoField``, ...), with arguments computed there. To subclass the
field without copying ``populate_modules``, :func:`host_builds` points that one name at our
subclass while the host's ``populate_modules`` runs, and restores it afterwards. The subclass only
overrides ``forward`` (see :mod:`sp_plugins.nerfstudio.frustum_sp`), so the modules, parameter
names and checkpoints are the host's own.

Targets nerfstudio 1.1.5; ``tests/patches/test_nerfstudio_host_fields_patch.py`` fails loudly when
a name moves or stops being the class the host constructs.
"""

from __future__ import annotations

import importlib
from contextlib import contextmanager
from typing import Iterator

TARGET_VERSION = "1.1.5"

HOST_FIELDS = {
    "nerfstudio.models.vanilla_nerf": "NeRFField",
    "nerfstudio.models.mipnerf": "NeRFField",
    "nerfstudio.models.nerfacto": "NerfactoField",
    "nerfstudio.models.tensorf": "TensoRFField",
}
"""Where each host model looks up the field class it constructs."""


@contextmanager
def host_builds(module_name: str, subclass: type) -> Iterator[None]:
    """While active, ``module_name``'s field name resolves to ``subclass`` (a subclass of it)."""
    if module_name not in HOST_FIELDS:
        raise ValueError(f"{module_name}: not a host model module this patch knows ({', '.join(HOST_FIELDS)})")
    name = HOST_FIELDS[module_name]
    module = importlib.import_module(module_name)
    host = getattr(module, name, None)
    if host is subclass:  # nested use
        yield
        return
    if not (isinstance(host, type) and issubclass(subclass, host)):
        raise RuntimeError(
            f"sp-plugins expected {module_name}.{name} to be the field class its model builds (nerfstudio "
            f"{TARGET_VERSION}); found {host!r}. This nerfstudio version is not supported by this sp-plugins release."
        )
    setattr(module, name, subclass)
    try:
        yield
    finally:
        setattr(module, name, host)
