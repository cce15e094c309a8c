"""``--set key=value`` for a nerfstudio trainer config: each value typed to the field it names.

nerfbaselines hands its ``--set`` values over as strings and its nerfstudio wrapper sets them as
they come (``pipeline.model.sp.enabled=False`` would be the truthy string ``"False"``). Here a value
is cast to the field's annotation (bool, int, float, str, Path, Literal, Optional, Tuple, enums);
a key that names no field is refused with the keys that exist where the lookup stopped.
"""

from __future__ import annotations

import dataclasses
import difflib
import enum
import typing
from pathlib import Path
from typing import Any, Dict, List

__all__ = ["OverrideError", "apply_overrides", "cast"]

_TRUE, _FALSE = {"true", "1", "yes", "on"}, {"false", "0", "no", "off"}


class OverrideError(ValueError):
    """A ``--set`` that cannot apply: one line naming it and what would."""


def _hints(obj: Any) -> Dict[str, Any]:
    try:
        return typing.get_type_hints(type(obj))
    except Exception:  # a forward reference the host never resolves: the field's own annotation
        return {f.name: f.type for f in dataclasses.fields(obj)}


def _split(text: str) -> List[str]:
    text = text.strip()
    if text[:1] in "([" and text[-1:] in ")]":
        text = text[1:-1]
    return [part.strip() for part in text.split(",") if part.strip()]


def cast(tp: Any, value: Any) -> Any:
    """``value`` (a string from the command line, or a preset's value) as type ``tp``."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if tp is Any:
        return value
    if origin is typing.Literal:
        for choice in args:
            try:
                if cast(type(choice), value) == choice:
                    return choice
            except (TypeError, ValueError):
                pass
        raise ValueError(f"one of {', '.join(map(repr, args))}")
    if origin is typing.Union:
        if value is None or (isinstance(value, str) and value.lower() == "none" and type(None) in args):
            if type(None) in args:
                return None
        for option in (a for a in args if a is not type(None)):
            try:
                return cast(option, value)
            except (TypeError, ValueError):
                pass
        raise ValueError(" or ".join(getattr(a, "__name__", str(a)) for a in args))
    if origin in (tuple, list):
        items = _split(value) if isinstance(value, str) else list(value)
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(items) != len(args):
                raise ValueError(f"{len(args)} comma-separated values")
            return tuple(cast(a, v) for a, v in zip(args, items))
        item = args[0] if args else Any
        return origin(cast(item, v) for v in items)
    if tp is bool:
        if isinstance(value, bool):
            return value
        text = str(value).strip().lower()
        if text in _TRUE | _FALSE:
            return text in _TRUE
        raise ValueError("True or False")
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        if isinstance(value, tp):
            return value
        for member in tp:
            if str(value) in (member.name, str(member.value)):
                return member
        raise ValueError(f"one of {', '.join(m.name for m in tp)}")
    if tp in (int, float):
        if isinstance(value, bool):
            raise ValueError(tp.__name__)
        if tp is int and isinstance(value, float) and not value.is_integer():
            raise ValueError("an integer")
        number = float(value) if tp is int and isinstance(value, str) and "e" in value.lower() else value
        return tp(number)
    if tp is str or tp is Path:
        return tp(value)
    if isinstance(tp, type) and isinstance(value, tp):
        return value
    raise ValueError(f"a {getattr(tp, '__name__', tp)} (not settable from text)")


def _describe(tp: Any) -> str:
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")


def apply_overrides(config: Any, overrides: Dict[str, Any], method: str) -> None:
    """Set each ``dotted.key`` of ``overrides`` on ``config``, typed; :class:`OverrideError` names
    the first that names no field or whose value does not fit."""
    for key, value in overrides.items():
        target, path = config, key.split(".")
        for depth, name in enumerate(path):
            if not dataclasses.is_dataclass(target):
                where = ".".join(path[:depth])
                raise OverrideError(f"--set {key}: {where} is a {type(target).__name__}, not a config with fields")
            fields = {f.name: f for f in dataclasses.fields(target) if not f.name.startswith("_")}
            if name not in fields:
                where = ".".join(path[:depth]) or "the top level"
                near = difflib.get_close_matches(name, list(fields), n=3)
                hint = f" (did you mean {', '.join(near)}?)" if near else ""
                raise OverrideError(
                    f"--set {key}: {method} has no key {name!r} at {where}{hint}; the keys there are: "
                    f"{', '.join(sorted(fields))}")
            if depth < len(path) - 1:
                target = getattr(target, name)
        tp = _hints(target).get(path[-1], fields[path[-1]].type)
        try:
            typed = cast(tp, value)
        except (TypeError, ValueError) as err:
            raise OverrideError(f"--set {key}={value}: {key} takes {err} ({_describe(tp)})") from None
        setattr(target, path[-1], typed)
