"""Let a host model build *our* field subclass with its own arguments (nerfstudio 1.1.5).

nerfstudio's models construct their fields inside ``populate_modules`` from a module-level name
(``nerfstudio.models.nerfacto.NerfactoField``, ...), with arguments computed there. To subclass the
field without copying ``populate_modules``, :func:`host_builds` points that one name at our
subclass while the host's ``populate_modules`` runs, and restores it afterwards. The subclass only
overrides ``forward`` (see :mod:`sp_plugins.nerfstudio.frustum_sp`), so the modules, parameter
names and checkpoints are the host's own.

:func:`model_builds_variants` does the same for a model we have never seen (another plugin's,
for ``with_sp``): every module-level ``Field`` class of the modules that define the model class
and its bases resolves to its SP variant while that model's ``populate_modules`` runs. A field
built any other way (from a config's ``_target``, or by a name imported inside a function) is
not reached; the model then refuses to train (see ``sp_plugins.nerfstudio.models``).

Targets nerfstudio 1.1.5; ``tests/patches/test_nerfstudio_host_fields_patch.py`` fails loudly when
a name moves or stops being the class the host constructs.
"""

from __future__ import annotations

import importlib
from contextlib import contextmanager
from typing import Callable, Iterator, List, Tuple

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


def module_field_classes(model_cls: type) -> List[Tuple[str, str, type]]:
    """``(module, name, class)`` for every module-level ``Field`` subclass of the modules that
    define ``model_cls`` and its bases (nerfstudio's base ``Model`` and ``torch.nn`` excluded)."""
    from nerfstudio.fields.base_field import Field
    from nerfstudio.models.base_model import Model

    found, seen = [], set()
    for cls in model_cls.__mro__:
        if cls is Model or not (isinstance(cls, type) and issubclass(cls, Model)) or cls.__module__ in seen:
            continue
        seen.add(cls.__module__)
        module = importlib.import_module(cls.__module__)
        if module.__name__.startswith("sp_plugins."):
            continue
        for name, obj in sorted(vars(module).items()):
            if isinstance(obj, type) and issubclass(obj, Field) and obj is not Field:
                found.append((module.__name__, name, obj))
    return found


@contextmanager
def model_builds_variants(model_cls: type, variant_of: Callable[[type], type]) -> Iterator[List[str]]:
    """While active, every name of :func:`module_field_classes` resolves to ``variant_of(class)``
    (a subclass of it); yields the ``module.name`` entries redirected. Restored on exit."""
    targets = [(m, n, c) for m, n, c in module_field_classes(model_cls) if not getattr(c, "__sp_variant__", False)]
    replaced = []
    try:
        for module_name, name, host in targets:
            variant = variant_of(host)
            if not issubclass(variant, host):
                raise RuntimeError(f"{variant!r} is not a subclass of {host!r}")
            setattr(importlib.import_module(module_name), name, variant)
            replaced.append((module_name, name, host))
        yield [f"{m}.{n}" for m, n, _ in replaced]
    finally:
        for module_name, name, host in replaced:
            setattr(importlib.import_module(module_name), name, host)
