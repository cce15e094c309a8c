"""A package's public names loaded on first use (PEP 562), shared by the packages whose import must stay cheap."""

from __future__ import annotations

import sys
from importlib import import_module
from typing import Any, Mapping


def lazy_attribute(package: str, where: Mapping[str, str], name: str) -> Any:
    """``package``'s public ``name``, imported from its submodule ``where[name]`` on first use (the package's module
    ``__getattr__``) and kept in the package's namespace, so that importing the package imports none of those
    submodules (nor torch, which most of them need); ``AttributeError`` for any other name."""
    if name not in where:
        raise AttributeError(f"module {package!r} has no attribute {name!r}")
    value = getattr(import_module(f"{package}.{where[name]}"), name)
    setattr(sys.modules[package], name, value)
    return value
