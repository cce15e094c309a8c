"""SP subclasses of host classes, made on demand and importable by path.

SP on *any* method means subclassing classes we have never seen (a plugin's model and field).
Such a subclass is made when a method is wrapped, but a saved ``config.yml`` names classes by
``module.qualname`` (PyYAML's ``!!python/object:`` and ``!!python/name:`` tags), and ``ns-eval``,
``ns-export``, ``ns-render`` load it in a fresh process. So every variant lives in one module of
ours under a name that *encodes its host class's path*; that module's ``__getattr__`` (PEP 562)
decodes a name it does not hold yet, imports the host class and makes the same variant again.

Names read ``SP<kind>__<path>``, where ``<path>`` is the host class's ``module.qualname`` with
``_`` written ``_u`` and ``.`` written ``_d`` (reversible, a valid identifier)::

    SPModel__nerfstudio_dmodels_dnerfacto_dNerfactoModel
"""

from __future__ import annotations

import importlib
import sys
import copy
import dataclasses
from typing import Any, Callable, Dict, Optional, Tuple

PREFIX = "SP"
SEPARATOR = "__"


def encode_path(path: str) -> str:
    """``a_b.C`` -> ``a_ub_dC``."""
    return path.replace("_", "_u").replace(".", "_d")


def decode_path(text: str) -> str:
    """Inverse of :func:`encode_path`; ValueError on text it could not have written."""
    out, i = [], 0
    while i < len(text):
        ch = text[i]
        if ch != "_":
            out.append(ch)
            i += 1
            continue
        code = text[i + 1 : i + 2]
        if code not in ("u", "d"):
            raise ValueError(f"not an encoded class path: {text!r}")
        out.append("_" if code == "u" else ".")
        i += 2
    return "".join(out)


def class_path(cls: type) -> str:
    return f"{cls.__module__}.{cls.__qualname__}"


def import_class(path: str) -> type:
    """The class at ``module.qualname`` (the longest importable module prefix wins)."""
    parts = path.split(".")
    for cut in reversed(range(1, len(parts))):  # every module prefix, the longest first
        try:
            obj = importlib.import_module(".".join(parts[:cut]))
        except ImportError:
            continue
        try:
            for attr in parts[cut:]:
                obj = getattr(obj, attr)
        except AttributeError:
            continue
        if isinstance(obj, type):
            return obj
    raise ImportError(f"no class importable at {path!r}")


class VariantFactory:
    """Makes, caches and resolves the SP variants of host classes for one module.

    The factory is a leaf: it imports none of the host adapter's modules. The mixin each kind of
    variant puts first among its bases (a host's ``SPModel``, its seam field) is registered with it
    by the module that defines that mixin (:meth:`register`, at that module's import); ``providers``
    names those modules, so that a saved ``config.yml`` naming a variant, read in a fresh process
    where they are not imported yet, still finds the mixin (:meth:`mixin`).

    Args:
        module: the module that holds the variants and resolves them in its ``__getattr__``.
        builders: for each kind (``"Model"``, ``"ModelConfig"``, ``"Field"``...), a function
            ``(host_class, name, module) -> class`` that makes the subclass under that name.
        providers: kind -> the module that registers that kind's mixin when it is imported.

    A kind is an identifier without ``__`` (the separator), so a name starts with at most one kind's head.
    """

    def __init__(self, module: str, builders: Dict[str, Callable[[type, str, str], type]],
                 providers: Optional[Dict[str, str]] = None) -> None:
        bad = [kind for kind in builders if SEPARATOR in kind or not kind.isidentifier()]
        if bad:
            raise ValueError(f"variant kinds must be identifiers without {SEPARATOR!r}: {bad}")
        self.module = module
        self.builders = builders
        self.providers = dict(providers or {})
        self._mixins: Dict[str, type] = {}
        self._made: Dict[Tuple[str, type], type] = {}

    def register(self, kind: str, mixin: type) -> type:
        """Make ``mixin`` the first base of every ``kind`` variant; returns it."""
        self._mixins[kind] = mixin
        return mixin

    def mixin(self, kind: str) -> type:
        """The mixin registered for ``kind``, importing its provider module first if needed."""
        if kind not in self._mixins and kind in self.providers:
            importlib.import_module(self.providers[kind])
        try:
            return self._mixins[kind]
        except KeyError:
            raise LookupError(f"no {kind} mixin is registered with {self.module}") from None

    def name(self, kind: str, host: type) -> str:
        return f"{PREFIX}{kind}{SEPARATOR}{encode_path(class_path(host))}"

    def get(self, kind: str, host: type) -> type:
        """The ``kind`` variant of ``host`` (made once per process)."""
        key = (kind, host)
        if key in self._made:
            return self._made[key]
        try:
            found = import_class(class_path(host))
        except ImportError:
            found = None
        if found is not host:
            raise ValueError(
                f"{class_path(host)} is not importable by that path, so a saved config.yml naming its SP variant could "
                "not be loaded again; define the class at module level of an importable module"
            )
        name = self.name(kind, host)
        cls = self.builders[kind](host, name, self.module)
        if not (issubclass(cls, host) and cls.__qualname__ == name and cls.__module__ == self.module):
            raise TypeError(f"the {kind} builder made {cls!r}, not a subclass of {host!r} named {self.module}.{name}")
        self._made[key] = cls
        setattr(sys.modules[self.module], name, cls)
        return cls

    def resolve(self, name: str) -> type:
        """The variant a name written by :meth:`name` stands for (AttributeError otherwise, as
        ``getattr`` on a module expects)."""
        for kind in self.builders:
            head = f"{PREFIX}{kind}{SEPARATOR}"
            if name.startswith(head):
                try:
                    host = import_class(decode_path(name[len(head) :]))
                except (ImportError, ValueError) as err:
                    raise AttributeError(f"module {self.module!r} cannot make {name!r}: {err}") from None
                return self.get(kind, host)
        raise AttributeError(f"module {self.module!r} has no attribute {name!r}")


def subclass(bases: tuple, name: str, module: str, **namespace: Any) -> type:
    """``type(name, bases, namespace)`` placed in ``module`` (for :class:`VariantFactory` builders)."""
    return type(name, bases, {**namespace, "__module__": module, "__qualname__": name})


def field_default(cls: type, name: str) -> Any:
    """The default of dataclass field ``name`` of ``cls`` (its factory called)."""
    (f,) = [f for f in dataclasses.fields(cls) if f.name == name]
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    if f.default is not dataclasses.MISSING:
        return f.default
    raise ValueError(f"{cls.__name__}.{name} has no default")


def target_class(config: Any) -> Any:
    """The class a host config instantiates (its ``_target``), or None when it names none."""
    target = getattr(config, "_target", None)
    return target if isinstance(target, type) else None


def convert(config: Any, cls: type, **changes: Any) -> Any:
    """``config`` as an instance of ``cls`` (a subclass of its class): every init field copied
    except ``_target`` (unless given in ``changes``), then ``changes`` applied."""
    values: Dict[str, Any] = {
        f.name: copy.deepcopy(getattr(config, f.name))
        for f in dataclasses.fields(config)
        if f.init and f.name != "_target"
    }
    values.update(changes)
    return cls(**values)


def table_refusal(model_config: Any, *tables: Any) -> Tuple[Optional[type], Optional[str]]:
    """``(model class, reason)`` for a host ``model_config``: why SP cannot be put on it as far as
    classes tell (no model class; the first entry of ``tables``, dicts of class path -> reason or
    of class path -> callable giving a reason or None, that names the model class or a base), or
    ``(model class, None)``. A method that is ours already (its model config has ``sp``) passes."""
    model = target_class(model_config)
    if model is None:
        return None, "its model config has no model class (_target) to subclass"
    if hasattr(model_config, "sp"):
        return model, None
    for cls in model.__mro__:
        for table in tables:
            reason = table.get(class_path(cls))
            reason = reason() if callable(reason) else reason
            if reason:
                return model, reason
    return model, None


def refuse_or_switch_on(method_name: str, model_config: Any, reason: Optional[str], sp: Any) -> bool:
    """The start of each host's ``with_sp`` (the same in both): raise ``ValueError("SP cannot be put
    on <method_name>: <reason>")`` when ``reason`` is set; for a ``model_config`` that is ours already
    (it has ``sp``), switch SP on (an explicit ``sp`` wins) and return True; else return False, and
    the host converts the model config to its SP variant."""
    if reason:
        raise ValueError(f"SP cannot be put on {method_name}: {reason}")
    if not hasattr(model_config, "sp"):
        return False
    model_config.sp = copy.deepcopy(sp) if sp is not None else dataclasses.replace(model_config.sp, enabled=True)
    return True
