"""Reading a saved run's ``config.yml`` without running anything the file names.

``ns-train``, ``sp-train`` and sdfstudio's ``ns-train`` write ``config.yml`` with ``yaml.dump`` of
the trainer config; the hosts read it back with PyYAML's full ``yaml.Loader``, which builds any
Python object a file names: a one-line file ``!!python/object/apply:os.system ["..."]`` runs a
shell command. A real ``config.yml`` holds only these tags (every registered method of both hosts,
ours and ``sp-train``'s variants checked: tests/nerfstudio/test_safe_config_ns.py,
tests/sdfstudio/test_safe_config_sdf.py):

- ``!!python/object:<class>``: the config dataclasses of the host's ``nerfstudio`` package and ours;
- ``!!python/name:<class>``: the classes the configs instantiate (``_target``), from those two
  packages and ``torch.optim`` (optimizers, learning-rate schedulers), and nerfstudio's collate function;
- ``!!python/object/apply:<class>``: ``pathlib`` paths and enums (also sdfstudio's ``nerfacc``
  ``ContractionType``), and ``operator.getitem`` of a generic data manager by its dataset class
  (``VanillaDataManager[DepthDataset]``);
- ``!!python/tuple`` and YAML's own plain tags.

:class:`RunConfigLoader` is a ``yaml.SafeLoader`` with constructors for exactly those. It composes
the whole document first and checks every node's tag against the allow-list before it builds any
object (:meth:`RunConfigLoader.get_single_data`): anything else is refused in one line naming the
file, the line, the tag and why (:class:`ConfigRefused`). Names are looked up only inside the
allowed packages (importing their modules, as the full loader would), and nothing a file names is
called except a path class, an enum lookup and the generic subscription.

:func:`load_run_config` reads a file with it (our commands' own reading, one line for every bad
file); :func:`reading_configs_safely` makes a host function that reads ``config.yml`` itself
(``eval_setup``, ``ns-train --load-config``) read it through the same loader while our command
runs it; :func:`weights_only_checkpoints` keeps the host's checkpoint loads weights-only there even
when the environment says otherwise (``TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD``).

Imports no host: the host's classes are imported when a file names them.
"""

from __future__ import annotations

import contextlib
import dataclasses
import enum
import importlib
import os
import pathlib
import re
import typing
from pathlib import Path
from types import ModuleType
from typing import Any, Iterator, NamedTuple, Optional, Tuple

import yaml
from yaml.nodes import MappingNode, Node, ScalarNode, SequenceNode

from sp_plugins.adapter import hosts as host_registry
from sp_plugins.adapter.errors import InputError, first_line

__all__ = ["Allowed", "ConfigRefused", "allowed", "RunConfigLoader", "load_run_config", "reading_configs_safely", "weights_only_checkpoints"]

PYTHON = "tag:yaml.org,2002:python/"
CLASS_EXTRA = ("torch.optim",)
"""Where else a ``!!python/name`` class may come from (``torch.optim.adam.Adam``, ``torch.optim.lr_scheduler.MultiStepLR``)."""
ENUM_EXTRA = ("nerfacc",)
"""Where else an enum may come from (sdfstudio's instant-ngp stores ``nerfacc.contraction.ContractionType``)."""


class Allowed(NamedTuple):
    """The packages each kind of tag may name."""

    objects: Tuple[str, ...]
    """Config dataclasses, enums and instantiated classes: ours and every registered host's
    (:func:`sp_plugins.adapter.hosts.packages`; sdfstudio's is also named ``nerfstudio``)."""
    classes: Tuple[str, ...]
    enums: Tuple[str, ...]


def allowed() -> Allowed:
    """The allow-list, from the host registry."""
    objects = host_registry.packages()
    return Allowed(objects, objects + CLASS_EXTRA, objects + ENUM_EXTRA)
FUNCTIONS = frozenset({"nerfstudio.data.utils.nerfstudio_collate.nerfstudio_collate"})
"""The only functions a config names (the data manager's ``collate_fn``); it is stored, not called."""
PATHS = frozenset({"pathlib.PosixPath", "pathlib.WindowsPath", "pathlib.Path", "pathlib.PurePosixPath",
                   "pathlib.PureWindowsPath"})
GETITEM = frozenset({"_operator.getitem", "operator.getitem"})
PLAIN = frozenset({PYTHON + "tuple"})
"""The python/ tags besides those that name something: ``yaml.dump`` writes tuples so."""


class ConfigRefused(InputError):
    """One line for the user: the file, the line, the tag or setting, and why."""


class _Refusal(Exception):
    """Raised inside the loader (which does not know the file's name); :func:`load_run_config` names it."""

    def __init__(self, node: Node, what: str, kind: str = "unsafe"):
        super().__init__(what)
        self.node, self.what, self.kind = node, what, kind


def short_tag(tag: str) -> str:
    return "!!" + tag[len("tag:yaml.org,2002:"):] if tag.startswith("tag:yaml.org,2002:") else tag


def _within(name: str, packages) -> bool:
    return any(name == p or name.startswith(p + ".") for p in packages)


class RunConfigLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` plus the Python tags a saved trainer config holds, each checked against
    the allow-list of this module, for the whole document before any object is built."""

    def __init__(self, stream: Any) -> None:
        super().__init__(stream)
        self._names: dict = {}
        self._allowed = allowed()
        self._renamed = host_registry.renamed()

    # -- the check, on the composed nodes -----------------------------------------------------------
    def get_single_data(self) -> Any:
        node = self.get_single_node()
        if node is None:
            return None
        self.vet(node)
        return self.construct_document(node)

    def vet(self, root: Node) -> None:
        """Every node of ``root`` (aliases once) has a tag this loader may build; else :class:`_Refusal`."""
        seen, todo = set(), [root]
        while todo:
            node = todo.pop()
            if id(node) in seen:
                continue
            seen.add(id(node))
            self._vet_tag(node)
            if isinstance(node, SequenceNode):
                todo.extend(node.value)
            elif isinstance(node, MappingNode):
                for key, value in node.value:
                    todo.extend((key, value))

    def _vet_tag(self, node: Node) -> None:
        tag = node.tag
        if not tag.startswith(PYTHON):
            if tag in self.yaml_constructors:
                return
            raise _Refusal(node, "is not a tag PyYAML or a run's config uses")
        if tag in PLAIN:
            if not isinstance(node, SequenceNode):
                raise _Refusal(node, "must hold a list")
            return
        for prefix, check in ((PYTHON + "name:", self._vet_name), (PYTHON + "object:", self._vet_object),
                              (PYTHON + "object/apply:", self._vet_apply)):
            if tag.startswith(prefix):
                check(tag[len(prefix):], node)
                return
        raise _Refusal(node, "builds Python objects a run's config.yml never holds")

    def _vet_name(self, name: str, node: Node) -> None:
        if not isinstance(node, ScalarNode) or node.value:
            raise _Refusal(node, "must have an empty value (it names a class)")
        if name in FUNCTIONS:
            self._resolve(name, node)
            return
        if not _within(name, self._allowed.classes):
            raise _Refusal(node, "names something outside the host's and sp-plugins' packages")
        if not isinstance(self._resolve(name, node), type):
            raise _Refusal(node, "names something that is not a class")

    def _vet_object(self, name: str, node: Node) -> None:
        if not _within(name, self._allowed.objects):
            raise _Refusal(node, "would build an object from outside the host's and sp-plugins' packages")
        cls = self._resolve(name, node)
        if not (isinstance(cls, type) and dataclasses.is_dataclass(cls)):
            raise _Refusal(node, "would build something that is not a config dataclass")
        if cls.__new__ is not object.__new__ or hasattr(cls, "__setstate__"):
            raise _Refusal(node, "would run the class's own __new__ / __setstate__")
        if not isinstance(node, MappingNode):
            raise _Refusal(node, "must hold the dataclass's settings as a mapping")
        for key, _ in node.value:
            if not (isinstance(key, ScalarNode) and key.tag == "tag:yaml.org,2002:str" and key.value.isidentifier()
                    and not re.fullmatch(r"__.*__", key.value)):
                raise _Refusal(key, f"is not a setting name ({key.value!r}) of {name}")

    def _vet_apply(self, name: str, node: Node) -> None:
        if not isinstance(node, SequenceNode):
            raise _Refusal(node, "must hold a list of arguments")
        if name in PATHS:
            if not all(isinstance(arg, ScalarNode) for arg in node.value):
                raise _Refusal(node, "must hold the path's parts as plain strings")
            return
        if name in GETITEM:  # a generic data manager subscripted by its dataset class
            first = node.value[0] if len(node.value) == 2 else None
            if first is None or not first.tag.startswith(PYTHON + "name:"):
                raise _Refusal(node, "may only subscribe a generic class the config names")
            generic = first.tag[len(PYTHON + "name:"):]
            if not _within(generic, self._allowed.classes):  # checked before _resolve imports it (an import runs its module)
                raise _Refusal(first, "names something outside the host's and sp-plugins' packages")
            cls = self._resolve(generic, first)
            if not (isinstance(cls, type) and issubclass(cls, typing.Generic)):
                raise _Refusal(node, "may only subscribe a generic class")
            return
        if not _within(name, self._allowed.enums):
            raise _Refusal(node, f"would call {name}")
        cls = self._resolve(name, node)
        if not (isinstance(cls, type) and issubclass(cls, enum.Enum)):
            raise _Refusal(node, f"would call {name}, which is not an enum")
        if len(node.value) != 1:
            raise _Refusal(node, "must hold the enum member's value")

    def _resolve(self, name: str, node: Node) -> Any:
        """``module.attr`` imported, only for names the callers checked are in an allowed package."""
        if name not in self._names:  # a class a host renamed since the run was saved: its new path
            module_name, _, attr = self._renamed.get(name, name).rpartition(".")
            if not module_name or not attr:
                raise _Refusal(node, "needs a dotted name (module.Class)")
            try:
                module = importlib.import_module(module_name)
                self._names[name] = getattr(module, attr)
            except Exception as exc:  # noqa: BLE001  (a module of the allowed packages that does not import here)
                raise _Refusal(node, f"names {name}, which this installation lacks ({first_line(exc, 120)})",
                               kind="missing") from None
        return self._names[name]

    # -- the constructors (run only after the check) -------------------------------------------------
    def _construct_name(self, suffix: str, node: Node) -> Any:
        self._vet_name(suffix, node)
        return self._resolve(suffix, node)

    def _construct_object(self, suffix: str, node: Node) -> Iterator[Any]:
        self._vet_object(suffix, node)
        cls = self._resolve(suffix, node)
        instance = object.__new__(cls)
        yield instance  # filled in after its children: recursive configs (anchors) work as with yaml.Loader
        instance.__dict__.update(self.construct_mapping(node))

    def _construct_apply(self, suffix: str, node: Node) -> Any:
        self._vet_apply(suffix, node)
        args = self.construct_sequence(node, deep=True)
        if suffix in PATHS:
            return getattr(pathlib, suffix.rpartition(".")[2])(*args)
        if suffix in GETITEM:
            return args[0][args[1]]
        return self._resolve(suffix, node)(*args)  # an enum's lookup by value

    def _construct_tuple(self, node: Node) -> tuple:
        return tuple(self.construct_sequence(node))


RunConfigLoader.add_constructor(PYTHON + "tuple", RunConfigLoader._construct_tuple)
RunConfigLoader.add_multi_constructor(PYTHON + "name:", RunConfigLoader._construct_name)
RunConfigLoader.add_multi_constructor(PYTHON + "object:", RunConfigLoader._construct_object)
RunConfigLoader.add_multi_constructor(PYTHON + "object/apply:", RunConfigLoader._construct_apply)

UNTRUSTED = ("a training run's config.yml holds only config classes, paths, enums and plain values: this file was not "
             "written by one (or was edited); nothing was built or run, do not load it")


def _line(node: Optional[Node]) -> str:
    return f"line {node.start_mark.line + 1}: " if node is not None and node.start_mark is not None else ""


def load_config_text(text: str, where: str, versions: str = "") -> Any:
    """The object ``text`` (the contents of ``where``, a file or flag and file) holds, built by
    :class:`RunConfigLoader`; :class:`ConfigRefused` with one line for anything else."""
    try:
        return yaml.load(text, Loader=RunConfigLoader)  # noqa: S506  (the restricted loader)
    except _Refusal as refused:
        tag = short_tag(refused.node.tag)
        if refused.kind == "missing":
            this = f" (this is {versions})" if versions else ""
            raise ConfigRefused(f"{where}: {_line(refused.node)}{refused.what}; it was written by another version of "
                                f"sp-plugins or the host{this}: load it with the version that wrote it, or retrain") from None
        raise ConfigRefused(f"{where}: refused {_line(refused.node)}the tag {tag} {refused.what}; {UNTRUSTED}") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        at = f"line {mark.line + 1}: " if mark is not None else ""
        problem = getattr(exc, "problem", None) or first_line(exc)
        raise ConfigRefused(f"{where}: not a valid config.yml ({at}{' '.join(str(problem).split())[:160]}); "
                            "give the config.yml a training run wrote") from None
    except RecursionError:
        raise ConfigRefused(f"{where}: not a config.yml (nested too deeply to read); give the config.yml a training run "
                            "wrote") from None
    except (TypeError, ValueError, NotImplementedError) as exc:  # a path of numbers, no such enum member, a WindowsPath
        raise ConfigRefused(f"{where}: a value does not fit its type ({first_line(exc, 160)}); the file was edited or "
                            "written by another version: load it with the version that wrote it, or retrain") from None


def load_run_config(path: Path, flag: str = "--load-config", expect: Optional[type] = None, versions: str = "") -> Any:
    """The trainer config in the ``config.yml`` at ``path`` (``flag``: how the user gave it), or
    :class:`ConfigRefused` naming the file and the problem: unreadable, not YAML, a tag outside the
    allow-list (refused before anything is built), a class this installation lacks, or (``expect``)
    not the trainer config class a training run writes."""
    where = f"{flag} {path}" if flag else str(path)
    try:
        text = Path(path).read_bytes().decode("utf-8")
    except OSError as exc:
        raise ConfigRefused(f"{where}: cannot be read ({exc.strerror or first_line(exc)}); give the config.yml a training "
                            "run wrote") from None
    except UnicodeDecodeError:
        raise ConfigRefused(f"{where}: not a config.yml (not UTF-8 text: a binary file?); give the config.yml a training "
                            "run wrote") from None
    config = load_config_text(text, where, versions)
    if expect is not None and not isinstance(config, expect):
        raise ConfigRefused(f"{where}: holds a {type(config).__name__}, not the {expect.__name__} a training run writes "
                            "(config.yml in the run folder)")
    return config


class _SafeYaml:
    """Stands in for the ``yaml`` module inside one host module: its ``load`` builds with
    :class:`RunConfigLoader` whatever loader the host names; everything else is PyYAML's."""

    def __init__(self, real: ModuleType, where: str, versions: str):
        self._real, self._where, self._versions = real, where, versions
        self.loads = 0
        self.Loader = self.FullLoader = self.UnsafeLoader = RunConfigLoader

    def load(self, stream, Loader=None):  # noqa: N803  (yaml.load's signature)
        self.loads += 1
        text = stream.read() if hasattr(stream, "read") else stream
        if isinstance(text, bytes):
            text = text.decode("utf-8", errors="replace")
        return load_config_text(text, self._where, self._versions)

    unsafe_load = full_load = load

    def __getattr__(self, name: str) -> Any:
        return getattr(self._real, name)


@contextlib.contextmanager
def reading_configs_safely(module: ModuleType, where: str, versions: str = "") -> Iterator[_SafeYaml]:
    """While the block runs, ``module`` (a host module that reads ``config.yml`` with
    ``yaml.load(..., Loader=yaml.Loader)``: ``eval_utils`` for ``eval_setup``, ``scripts.train`` for
    ``--load-config``) reads it with :class:`RunConfigLoader`; a refusal names ``where`` (the flag and
    file the user gave; check that file with :func:`load_run_config` first, for a refusal before the
    host starts). Yields the stand-in, whose ``loads`` counts the host's reads (tests check that the
    host still reads through it)."""
    real = getattr(module, "yaml")  # getattr / setattr: a ModuleType declares no `yaml` for the type checker
    if isinstance(real, _SafeYaml):  # already inside such a block
        yield real
        return
    proxy = _SafeYaml(real, where, versions)
    setattr(module, "yaml", proxy)
    try:
        yield proxy
    finally:
        setattr(module, "yaml", real)


@contextlib.contextmanager
def weights_only_checkpoints() -> Iterator[None]:
    """While the block runs, every ``torch.load`` is weights-only (``TORCH_FORCE_WEIGHTS_ONLY_LOAD``;
    ``TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD`` set by the user is lifted): a checkpoint that carries a
    pickled callable is refused by torch's weights-only unpickler, never run."""
    names = ("TORCH_FORCE_WEIGHTS_ONLY_LOAD", "TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD")
    saved = {name: os.environ.get(name) for name in names}
    os.environ["TORCH_FORCE_WEIGHTS_ONLY_LOAD"] = "1"
    os.environ.pop("TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD", None)
    try:
        yield
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value
