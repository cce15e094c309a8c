"""Reading a run's ``config.yml`` without running what it names (sp_plugins.adapter.safe_config), exactly and
in-process, without a host: what each tag check accepts and refuses at its edge (the package prefixes, a class
vs a function, a dataclass without its own ``__new__`` / ``__setstate__``, setting names, a path's parts, a
generic subscription of exactly two arguments, an enum of exactly one value), the whole one-line refusal for
each (file, line, tag, why), the other bad files (not YAML, a missing class, a value that does not fit, too
deep, not UTF-8, not the expected class), what a good file builds, the host's ``yaml`` stand-in and the
weights-only environment. The classes a file names live in small modules registered under the allowed
packages' names (``sp_plugins.sp_test_fixture``...). The mutants each test kills are listed in
``bench/results/mutation_study/kills.json``."""

from __future__ import annotations

import importlib
import io
import os
import pathlib
import sys
import types
import typing

import pytest
import torch
import yaml

from sp_plugins.adapter import safe_config as sc
from sp_plugins.adapter.errors import InputError, first_line
from sp_plugins.adapter.safe_config import ConfigRefused

Adam = importlib.import_module("torch.optim.adam").Adam

FIXTURE_SOURCE = '''
import dataclasses, enum, typing

BUILT = []

@dataclasses.dataclass
class Dc:
    lr: float = 1.0
    child: object = None
    def __post_init__(self):
        BUILT.append(self)

@dataclasses.dataclass
class Other:
    x: int = 0

@dataclasses.dataclass
class NewDc:
    x: int = 0
    def __new__(cls, *args, **kwargs):
        return object.__new__(cls)

@dataclasses.dataclass
class StateDc:
    x: int = 0
    def __setstate__(self, state):
        self.__dict__.update(state)

class Plain:
    pass

class Color(enum.Enum):
    red = "red"
    blue = "blue"

class Pair(enum.Enum):
    a = [1, 2]
    b = [3]

T = typing.TypeVar("T")

class G(typing.Generic[T]):
    pass

class Arg:
    pass

def fn(*args):
    return args

instance = Dc.__new__(Dc)
'''
FIXTURES = ["sp_plugins.sp_test_fixture", "nerfstudio.sp_test_fixture", "nerfacc.sp_test_fixture",
            "torch.optim.sp_test_fixture", "elsewhere_sp_test.fixture"]
SP = "sp_plugins.sp_test_fixture"


@pytest.fixture(autouse=True)
def fixture_modules():
    """A module of config classes under each allowed package's name (and one outside them), found by
    ``importlib.import_module`` in ``sys.modules`` (their parents are not imported)."""
    with pytest.MonkeyPatch.context() as mp:
        for name in FIXTURES:
            module = types.ModuleType(name)
            mp.setitem(sys.modules, name, module)
            exec(FIXTURE_SOURCE, module.__dict__)  # noqa: S102  (our own source)
        yield


def fx(name: str = SP) -> types.ModuleType:
    return sys.modules[name]


def fresh(word: str) -> str:
    """An equal string that is not the interned constant (``==`` -> ``is`` tells them apart)."""
    return "".join(list(word))


def cut(text: str, limit: int) -> str:
    return text[: limit - 3] + "..."


def load(text: str, where: str = "W", versions: str = ""):
    return sc.load_config_text(text, where, versions)


def refused(text: str, line: int, tag: str, why: str, where: str = "W") -> None:
    """``text`` is refused with the unsafe-tag line naming ``where``, ``line``, ``tag`` and ``why``."""
    with pytest.raises(ConfigRefused) as info:
        load(text, where)
    assert str(info.value) == f"{where}: refused line {line}: the tag {tag} {why}; {sc.UNTRUSTED}"


def missing(text: str, line: int, what: str, versions: str = "") -> None:
    with pytest.raises(ConfigRefused) as info:
        load(text, versions=versions)
    this = f" (this is {versions})" if versions else ""
    assert str(info.value) == (f"W: line {line}: {what}; it was written by another version of sp-plugins or the "
                               f"host{this}: load it with the version that wrote it, or retrain")


def does_not_fit(text: str, reason: str) -> None:
    with pytest.raises(ConfigRefused) as info:
        load(text)
    assert str(info.value) == (f"W: a value does not fit its type ({reason}); the file was edited or written by "
                               "another version: load it with the version that wrote it, or retrain")


# -- the small helpers --------------------------------------------------------------------------------
def test_short_tag():
    """YAML's own tags are shortened to ``!!``; any other tag is kept as written."""
    assert sc.short_tag("tag:yaml.org,2002:python/object:a.B") == "!!python/object:a.B"
    assert sc.short_tag("tag:yaml.org,2002:str") == "!!str"
    assert sc.short_tag("!custom") == "!custom"
    assert sc.short_tag("tag:example.com,2000:x") == "tag:example.com,2000:x"


def test_within_a_package_is_the_package_or_below_it():
    """A name is within a package when it is the package or below it (a name read at run time included), not a
    prefix of it."""
    A = sc.allowed()  # noqa: N806  (the allow-list, short)
    assert sc._within(fresh("nerfstudio"), A.objects)
    assert sc._within(fresh("sp_plugins.core.config"), A.objects)
    assert sc._within("torch.optim", A.classes) and sc._within("torch.optim.adam.Adam", A.classes)
    assert sc._within("nerfacc.contraction.ContractionType", A.enums)
    for outside, packages in [("nerfstudiox.a", A.objects), ("sp_plugins_evil.a", A.objects), ("torch.optimx", A.classes),
                              ("torch.nn.Linear", A.classes), ("nerfacc.x", A.classes), ("torch.optim.x", A.objects),
                              ("os.system", A.enums), ("nerf", A.objects), ("", A.objects)]:
        assert not sc._within(outside, packages), outside


def test_the_allow_lists_are_ours_and_the_registered_hosts_packages():
    """sp_plugins first, then each registered host's packages once (both hosts' is ``nerfstudio``); a host
    registered at run time adds its own, and is gone again with it."""
    from sp_plugins.adapter import hosts

    A = sc.allowed()  # noqa: N806  (the allow-list, short)
    assert A.objects == ("sp_plugins", "nerfstudio")
    assert A.classes == ("sp_plugins", "nerfstudio", "torch.optim")
    assert A.enums == ("sp_plugins", "nerfstudio", "nerfacc")
    hosts.register(hosts.Host(name="third", packages=("thirdhost", "nerfstudio"), table="thirdhost.table"))
    try:
        assert sc.allowed().objects == ("sp_plugins", "nerfstudio", "thirdhost")
    finally:
        hosts.unregister("third")
    assert sc.allowed() == A


# -- what a good file builds ----------------------------------------------------------------------
def test_a_config_written_by_yaml_dump_reads_back_equal():
    """A dataclass holding a path, an enum, a tuple, an optimizer class and a nested dataclass, as ``yaml.dump``
    writes it."""
    m = fx()
    config = m.Dc(lr=0.5, child=m.Dc(lr=pathlib.PurePosixPath("a/b"), child=[m.Color.blue, (1, 2), Adam,
                                                                           pathlib.Path("/c/d"), m.Pair.a]))
    text = yaml.dump(config)
    built = load(text)
    assert type(built) is m.Dc and type(built.child) is m.Dc
    assert built == config
    assert type(built.child.lr) is pathlib.PurePosixPath
    assert built.child.child[0] is m.Color.blue and built.child.child[2] is Adam
    assert built.child.child[1] == (1, 2) and type(built.child.child[1]) is tuple
    assert type(built.child.child[3]) is type(pathlib.Path("/c/d")) and built.child.child[4] is m.Pair.a


def test_a_dataclass_is_built_without_running_its_init():
    """``object.__new__`` and the settings set: ``__init__`` / ``__post_init__`` do not run; the settings the
    file omits stay the class's defaults."""
    m = fx()
    built = load(f"!!python/object:{SP}.Dc {{lr: 2.0}}")
    assert m.BUILT == [] and type(built) is m.Dc and built.__dict__ == {"lr": 2.0}
    assert built.child is None


def test_a_recursive_config_and_a_shared_node_are_read_once():
    """An anchor its own child refers to (a cycle) and a node used twice."""
    built = load(f"&a !!python/object:{SP}.Dc {{lr: 1.0, child: *a}}")
    assert built.child is built
    seq = load("&s [1, *s]")
    assert seq[1] is seq
    assert load("[&x {a: 1}, *x, *x]") == [{"a": 1}] * 3


def test_an_empty_file_is_none():
    """An empty document (or one of comments only) loads as ``None``; a full one is built."""
    assert load("") is None
    assert load("# only a comment\n") is None
    assert load("a: 1") == {"a": 1}


def test_the_plain_tags_and_a_tuple():
    assert load("!!python/tuple [1, a, [2]]") == (1, "a", [2])
    assert load("{a: !!str 1, b: !!int '2', c: !!float 3, d: !!bool true, e: !!null '', f: !!binary aGk=}") == \
        {"a": "1", "b": 2, "c": 3.0, "d": True, "e": None, "f": b"hi"}
    assert load("!!set {a, b}") == {"a", "b"}


# -- refusals of tags ------------------------------------------------------------------------------
def test_a_tag_neither_pyyaml_nor_a_config_uses_is_refused_wherever_it_is():
    """In a list, a mapping's key and value, after an alias: each node is checked before anything is built (the
    constructor would say "could not determine a constructor")."""
    why = "is not a tag PyYAML or a run's config uses"
    refused("!custom x", 1, "!custom", why)
    refused("- 1\n- !custom x\n", 2, "!custom", why)
    refused("a: 1\nb:\n  c: !custom x\n", 3, "!custom", why)
    refused("a: 1\n!custom k: 1\n", 2, "!custom", why)
    refused("- !custom y\n- &a 1\n- *a\n", 1, "!custom", why)
    refused("- !custom y\n- &a [1]\n- *a\n", 1, "!custom", why)
    refused("!<tag:example.com,2000:x> 1", 1, "tag:example.com,2000:x", why)


def test_a_python_tag_a_config_never_holds_is_refused():
    """Each Python tag a run's config.yml never holds is refused, naming the tag."""
    why = "builds Python objects a run's config.yml never holds"
    refused("!!python/object/new:os.system [ls]", 1, "!!python/object/new:os.system", why)
    refused("!!python/module:os ''", 1, "!!python/module:os", why)
    refused("x: !!python/str abc", 1, "!!python/str", why)
    refused("!!python/object/apply ''", 1, "!!python/object/apply", why)


def test_a_tuple_must_hold_a_list():
    """A ``!!python/tuple`` that does not hold a list is refused, naming its line."""
    refused("!!python/tuple {a: 1}", 1, "!!python/tuple", "must hold a list")
    refused("\n!!python/tuple abc", 2, "!!python/tuple", "must hold a list")


# -- !!python/name --------------------------------------------------------------------------------
def test_a_class_of_the_allowed_packages_is_named():
    """A ``!!python/name`` of a class in the allowed packages loads as that class."""
    m = fx()
    assert load("!!python/name:torch.optim.adam.Adam ''") is Adam
    assert load(f"!!python/name:{SP}.Plain ''") is m.Plain
    assert load("!!python/name:nerfstudio.sp_test_fixture.Dc ''") is fx("nerfstudio.sp_test_fixture").Dc
    assert load("!!python/name:torch.optim.sp_test_fixture.Arg ''") is fx("torch.optim.sp_test_fixture").Arg


def test_a_name_must_have_an_empty_value():
    """A ``!!python/name`` with a value (a scalar or a list) is refused."""
    why = "must have an empty value (it names a class)"
    refused("!!python/name:torch.optim.adam.Adam x", 1, "!!python/name:torch.optim.adam.Adam", why)
    refused("!!python/name:torch.optim.adam.Adam []", 1, "!!python/name:torch.optim.adam.Adam", why)
    refused("!!python/name:torch.optim.adam.Adam [a]", 1, "!!python/name:torch.optim.adam.Adam", why)


def test_a_name_outside_the_packages_is_refused_before_it_is_imported():
    """A ``!!python/name`` outside the allowed packages is refused before its module is imported."""
    why = "names something outside the host's and sp-plugins' packages"
    refused("!!python/name:os.system ''", 1, "!!python/name:os.system", why)
    refused("!!python/name:torch.nn.Linear ''", 1, "!!python/name:torch.nn.Linear", why)
    refused("!!python/name:nerfacc.sp_test_fixture.Arg ''", 1, "!!python/name:nerfacc.sp_test_fixture.Arg", why)
    refused("!!python/name:sp_never_imported_module.X ''", 1, "!!python/name:sp_never_imported_module.X", why)
    assert "sp_never_imported_module" not in sys.modules


def test_a_name_that_is_not_a_class_is_refused():
    """A ``!!python/name`` of a function or an instance (other than the collate function) is refused."""
    why = "names something that is not a class"
    refused(f"!!python/name:{SP}.fn ''", 1, f"!!python/name:{SP}.fn", why)
    refused(f"a:\n  - !!python/name:{SP}.instance ''", 2, f"!!python/name:{SP}.instance", why)
    refused("!!python/name:sp_plugins.adapter.errors.first_line ''", 1, "!!python/name:sp_plugins.adapter.errors.first_line", why)


def test_the_collate_function_is_the_one_function_a_config_names():
    """nerfstudio's collate function is the one function a config may name, and it loads."""
    from nerfstudio.data.utils import nerfstudio_collate

    assert sc.FUNCTIONS == {"nerfstudio.data.utils.nerfstudio_collate.nerfstudio_collate"}
    assert load("!!python/name:nerfstudio.data.utils.nerfstudio_collate.nerfstudio_collate ''") is \
        nerfstudio_collate.nerfstudio_collate


def test_a_name_that_is_not_dotted_is_refused():
    """``sp_plugins`` and ``sp_plugins.`` are inside the packages but name no attribute of a module."""
    why = "needs a dotted name (module.Class)"
    refused(f"!!python/name:{fresh('sp_plugins')} ''", 1, "!!python/name:sp_plugins", why)
    refused("!!python/name:sp_plugins. ''", 1, "!!python/name:sp_plugins.", why)
    refused("!!python/name:nerfstudio ''", 1, "!!python/name:nerfstudio", why)


def test_a_class_this_installation_lacks_is_named_with_the_reason():
    """A class this installation lacks is named with the import's reason, and the versions that wrote the config
    when known."""
    missing("!!python/name:sp_plugins.sp_no_such_module.X ''", 1,
            "names sp_plugins.sp_no_such_module.X, which this installation lacks (No module named "
            "'sp_plugins.sp_no_such_module')")
    missing(f"a: 1\nb: !!python/name:{SP}.Gone ''", 2,
            f"names {SP}.Gone, which this installation lacks (module '{SP}' has no attribute 'Gone')",
            versions="sp-plugins 9.9, nerfstudio 1.1")


@pytest.mark.parametrize("excess", [0, 1])
def test_a_missing_class_reason_is_cut_past_120_characters(excess):
    """The reason a class is missing is given whole up to 120 characters and cut past them."""
    base = len(f"module '{SP}' has no attribute ''")
    attr = "A" * (120 - base + excess)
    reason = f"module '{SP}' has no attribute '{attr}'"
    assert len(reason) == 120 + excess
    missing(f"!!python/name:{SP}.{attr} ''", 1,
            f"names {SP}.{attr}, which this installation lacks ({reason if not excess else cut(reason, 120)})")


# -- !!python/object ------------------------------------------------------------------------------
def test_an_object_outside_the_packages_is_refused():
    """Only the host's and our packages (not ``torch.optim``, not ``nerfacc``)."""
    why = "would build an object from outside the host's and sp-plugins' packages"
    for name in ("collections.OrderedDict", "torch.optim.sp_test_fixture.Dc", "nerfacc.sp_test_fixture.Dc",
                 "elsewhere_sp_test.fixture.Dc"):
        refused(f"!!python/object:{name} {{}}", 1, f"!!python/object:{name}", why)


def test_an_object_must_be_a_plain_config_dataclass():
    """A ``!!python/object`` must name a config dataclass without its own ``__new__`` or ``__setstate__``; such a
    dataclass is built."""
    not_dc = "would build something that is not a config dataclass"
    refused(f"!!python/object:{SP}.Plain {{}}", 1, f"!!python/object:{SP}.Plain", not_dc)
    refused(f"!!python/object:{SP}.instance {{}}", 1, f"!!python/object:{SP}.instance", not_dc)
    refused(f"!!python/object:{SP}.fn {{}}", 1, f"!!python/object:{SP}.fn", not_dc)
    own = "would run the class's own __new__ / __setstate__"
    refused(f"!!python/object:{SP}.NewDc {{x: 1}}", 1, f"!!python/object:{SP}.NewDc", own)
    refused(f"!!python/object:{SP}.StateDc {{x: 1}}", 1, f"!!python/object:{SP}.StateDc", own)
    assert load(f"!!python/object:{SP}.Other {{x: 1}}") == fx().Other(x=1)


def test_an_object_must_hold_a_mapping():
    """A ``!!python/object`` that does not hold a mapping is refused."""
    why = "must hold the dataclass's settings as a mapping"
    refused(f"!!python/object:{SP}.Other [1]", 1, f"!!python/object:{SP}.Other", why)
    refused(f"!!python/object:{SP}.Other x", 1, f"!!python/object:{SP}.Other", why)


@pytest.mark.parametrize("key,tag", [("__class__", "!!str"), ("__init__", "!!str"), ("____", "!!str"), ("'1x'", "!!str"),
                                     ("'a b'", "!!str"), ("1", "!!int"), ("null", "!!null"), ("[a]", "!!seq"),
                                     ("!!timestamp abc", "!!timestamp"), ("!<tag:zzz> abc", "tag:zzz")])
def test_a_setting_name_must_be_a_plain_identifier(key, tag):
    """The key's line and tag; identifiers of another tag sort below (``null``) and above (``timestamp``,
    ``tag:zzz``) ``str``."""
    text = f"!!python/object:{SP}.Other\n? {key}\n: 1\n"
    node = yaml.compose(f"? {key}\n: 1\n").value[0][0]  # the key as the file holds it
    refused(text, 2, tag, f"is not a setting name ({node.value!r}) of {SP}.Other")


def test_setting_names_just_inside_the_rule_are_taken():
    assert load(f"!!python/object:{SP}.Other {{x: 1, _p: 2, __q: 3, r__: 4, ___: 5, __: 6}}").__dict__ == \
        {"x": 1, "_p": 2, "__q": 3, "r__": 4, "___": 5, "__": 6}


# -- !!python/object/apply ------------------------------------------------------------------------
def test_an_apply_must_hold_a_list():
    """A ``!!python/object/apply`` that does not hold a list is refused."""
    why = "must hold a list of arguments"
    refused("!!python/object/apply:os.system {args: [ls]}", 1, "!!python/object/apply:os.system", why)
    refused("!!python/object/apply:pathlib.PosixPath x", 1, "!!python/object/apply:pathlib.PosixPath", why)


def test_a_path_is_built_from_plain_strings():
    """A path is built from its parts when they are plain strings, and refused otherwise."""
    assert load("!!python/object/apply:pathlib.PosixPath [a, b]") == pathlib.PosixPath("a/b")
    assert load("!!python/object/apply:pathlib.PurePosixPath ['/', x]") == pathlib.PurePosixPath("/x")
    assert load("!!python/object/apply:pathlib.Path []") == pathlib.Path()
    refused("!!python/object/apply:pathlib.PosixPath [a, [b]]", 1, "!!python/object/apply:pathlib.PosixPath",
            "must hold the path's parts as plain strings")


def test_a_path_of_numbers_or_of_another_system_does_not_fit():
    """A path of numbers, or of another operating system, is refused as not fitting, with Python's reason."""
    for text, build in [("!!python/object/apply:pathlib.PosixPath [1]", lambda: pathlib.PosixPath(1)),
                        ("!!python/object/apply:pathlib.WindowsPath [a]", lambda: pathlib.WindowsPath("a"))]:
        with pytest.raises((TypeError, NotImplementedError)) as info:
            build()
        does_not_fit(text, first_line(info.value, 160))


def test_an_enum_member_by_its_value():
    """An enum of the allowed packages is built as its member from the value (a list value included)."""
    assert load(f"!!python/object/apply:{SP}.Color [blue]") is fx().Color.blue
    assert load("!!python/object/apply:nerfacc.sp_test_fixture.Color [red]") is fx("nerfacc.sp_test_fixture").Color.red
    assert load("!!python/object/apply:nerfstudio.sp_test_fixture.Pair [[1, 2]]") is fx("nerfstudio.sp_test_fixture").Pair.a


def test_an_apply_of_anything_but_an_enum_is_refused():
    """A ``!!python/object/apply`` of anything but an enum of the allowed packages is refused as a call."""
    refused("!!python/object/apply:os.system [ls]", 1, "!!python/object/apply:os.system", "would call os.system")
    refused("!!python/object/apply:torch.optim.sp_test_fixture.Color [red]", 1,
            "!!python/object/apply:torch.optim.sp_test_fixture.Color", "would call torch.optim.sp_test_fixture.Color")
    for name in (f"{SP}.Plain", f"{SP}.fn", f"{SP}.Dc", "sp_plugins.adapter.errors.InputError"):
        refused(f"!!python/object/apply:{name} [x]", 1, f"!!python/object/apply:{name}", f"would call {name}, which is not an enum")


@pytest.mark.parametrize("args", ["[]", "[red, blue]", "[red, blue, x]"])
def test_an_enum_takes_exactly_one_value(args):
    """An enum given no value, or more than one, is refused."""
    refused(f"!!python/object/apply:{SP}.Color {args}", 1, f"!!python/object/apply:{SP}.Color",
            "must hold the enum member's value")


@pytest.mark.parametrize("size", [10, 160, 161])
def test_an_enum_value_it_lacks_does_not_fit(size):
    """An enum value the enum lacks does not fit, with Python's reason cut at 160 characters."""
    value = "v" * size
    with pytest.raises(ValueError) as info:
        fx().Color(value)
    reason = str(info.value) if len(str(info.value)) <= 160 else cut(str(info.value), 160)
    does_not_fit(f"!!python/object/apply:{SP}.Color [{value}]", reason)


def test_a_generic_class_is_subscripted_by_its_dataset_class():
    """``operator.getitem`` of a generic class and its dataset class builds the subscripted class."""
    m = fx()
    for getitem in ("operator.getitem", "_operator.getitem"):
        built = load(f"!!python/object/apply:{getitem} [!!python/name:{SP}.G '', !!python/name:{SP}.Arg '']")
        assert built == m.G[m.Arg] and typing.get_origin(built) is m.G and typing.get_args(built) == (m.Arg,)


@pytest.mark.parametrize("args", ["[!!python/name:{SP}.G '']", "[!!python/name:{SP}.G '', !!python/name:{SP}.Arg '', x]", "[]",
                                  "[x, !!python/name:{SP}.G '']", "[!!str x, 1]"])
def test_a_subscription_must_name_its_generic_class_first_of_two(args):
    """A subscription must hold exactly two names, the generic class first."""
    refused(f"!!python/object/apply:operator.getitem {args.format(SP=SP)}", 1, "!!python/object/apply:operator.getitem",
            "may only subscribe a generic class the config names")


@pytest.mark.parametrize("first", ["Arg", "fn", "instance"])
def test_only_a_generic_class_is_subscripted(first):
    """Only a generic class is subscripted; anything else is refused."""
    refused(f"!!python/object/apply:operator.getitem [!!python/name:{SP}.{first} '', !!python/name:{SP}.G '']", 1,
            "!!python/object/apply:operator.getitem", "may only subscribe a generic class")


def test_a_subscription_of_a_class_outside_the_packages_is_refused_before_its_module_imports():
    """The subscripted class is checked against the allowed packages before anything imports its module (an
    import runs the module's code: ``this`` prints, ``antigravity`` opens a browser). A regression test for
    that defect, found by the mutation study's review."""
    import sys

    sys.modules.pop("this", None)
    with pytest.raises(ConfigRefused) as info:
        load(f"!!python/object/apply:operator.getitem [!!python/name:this.x '', !!python/name:{SP}.Arg '']")
    assert str(info.value) == (f"W: refused line 1: the tag !!python/name:this.x names something outside the host's and "
                               f"sp-plugins' packages; {sc.UNTRUSTED}")
    assert "this" not in sys.modules


# -- the other bad files ---------------------------------------------------------------------------
def yaml_error(text: str) -> yaml.YAMLError:
    with pytest.raises(yaml.YAMLError) as info:
        yaml.safe_load(text)
    return info.value


def not_valid(where: str, at: str, problem: str) -> str:
    return f"{where}: not a valid config.yml ({at}{problem}); give the config.yml a training run wrote"


@pytest.mark.parametrize("text", ["a: [1, 2\n", "a: 1\nb: 2\n  c: 3\n", "\n\n- *nowhere\n", "a: 1\n---\nb: 2\n"])
def test_text_that_is_not_yaml_names_the_line_and_the_problem(text):
    """Text that is not YAML is refused naming the line and YAML's problem."""
    exc = yaml_error(text)
    with pytest.raises(ConfigRefused) as info:
        load(text)
    assert str(info.value) == not_valid("W", f"line {exc.problem_mark.line + 1}: ", " ".join(exc.problem.split()))


def test_an_unreadable_character_has_no_line():
    """A reader error has no mark and no problem: its first line."""
    exc = yaml_error("a: \x00\n")
    assert getattr(exc, "problem_mark", None) is None
    with pytest.raises(ConfigRefused) as info:
        load("a: \x00\n")
    assert str(info.value) == not_valid("W", "", first_line(exc))


@pytest.mark.parametrize("excess", [0, 1])
def test_a_yaml_problem_is_cut_at_160_characters(excess):
    """YAML's problem is cut at 160 characters."""
    base = len(yaml_error("*a").problem) - 1
    alias = "a" * (160 - base + excess)
    problem = yaml_error(f"*{alias}").problem
    assert len(problem) == 160 + excess
    with pytest.raises(ConfigRefused) as info:
        load(f"*{alias}")
    assert str(info.value) == not_valid("W", "line 1: ", problem[:160])


def test_a_document_nested_too_deeply():
    """A document nested too deeply to read is refused in one line."""
    depth = sys.getrecursionlimit() + 100
    with pytest.raises(ConfigRefused) as info:
        load("[" * depth + "]" * depth)
    assert str(info.value) == "W: not a config.yml (nested too deeply to read); give the config.yml a training run wrote"


# -- load_run_config -------------------------------------------------------------------------------
def test_load_run_config_names_the_flag_and_the_file(tmp_path):
    """A config that cannot be read is refused naming the flag (when one is given), the file and the OS's reason."""
    path = tmp_path / "config.yml"
    with pytest.raises(ConfigRefused) as info:
        sc.load_run_config(path)
    assert str(info.value) == (f"--load-config {path}: cannot be read (No such file or directory); give the config.yml "
                               "a training run wrote")
    with pytest.raises(ConfigRefused) as info:
        sc.load_run_config(tmp_path, flag="")
    assert str(info.value) == f"{tmp_path}: cannot be read (Is a directory); give the config.yml a training run wrote"
    path.write_text("!custom x\n")
    with pytest.raises(ConfigRefused) as info:
        sc.load_run_config(str(path), flag="--config")
    assert str(info.value).startswith(f"--config {path}: refused line 1: the tag !custom ")


def test_load_run_config_of_a_binary_file(tmp_path):
    """A binary file is refused as not UTF-8 text."""
    path = tmp_path / "config.yml"
    path.write_bytes(b"a: \xff\xfe\n")
    with pytest.raises(ConfigRefused) as info:
        sc.load_run_config(path)
    assert str(info.value) == (f"--load-config {path}: not a config.yml (not UTF-8 text: a binary file?); give the "
                               "config.yml a training run wrote")


def test_load_run_config_expects_the_trainer_class(tmp_path):
    """A config that holds another class than the one expected is refused naming both; without one expected, any is
    loaded."""
    m = fx()
    path = tmp_path / "config.yml"
    path.write_text(yaml.dump(m.Dc(lr=3.0)))
    assert sc.load_run_config(path, expect=m.Dc) == m.Dc(lr=3.0)
    assert sc.load_run_config(path) == m.Dc(lr=3.0)
    with pytest.raises(ConfigRefused) as info:
        sc.load_run_config(path, expect=m.Other)
    assert str(info.value) == (f"--load-config {path}: holds a Dc, not the Other a training run writes (config.yml in "
                               "the run folder)")
    path.write_text("a: 1\n")
    assert sc.load_run_config(path) == {"a": 1}
    with pytest.raises(ConfigRefused, match=r": holds a dict, not the Dc a training run writes"):
        sc.load_run_config(path, expect=m.Dc)


def test_a_refusal_is_an_input_error_with_versions_only_for_a_missing_class(tmp_path):
    path = tmp_path / "config.yml"
    path.write_text("!!python/name:sp_plugins.sp_no_such_module.X ''\n")
    with pytest.raises(InputError) as info:
        sc.load_run_config(path, versions="sp-plugins 1.0")
    assert str(info.value).endswith("host (this is sp-plugins 1.0): load it with the version that wrote it, or retrain")
    path.write_text("!custom x\n")
    with pytest.raises(ConfigRefused) as info:
        sc.load_run_config(path, versions="sp-plugins 1.0")
    assert "sp-plugins 1.0" not in str(info.value)


# -- the host's yaml stand-in ---------------------------------------------------------------------
def host_module() -> types.ModuleType:
    host = types.ModuleType("host_eval_utils")
    host.yaml = yaml
    return host


def test_a_host_module_reads_through_the_loader_while_the_block_runs():
    """While the block runs, the host module's ``yaml`` is a stand-in whose loads (text, streams, bytes) go through
    the safe loader and are counted; the module's ``yaml`` is restored after."""
    host = host_module()
    m = fx()
    text = yaml.dump(m.Dc(lr=4.0))
    with sc.reading_configs_safely(host, "--load-config cfg.yml") as proxy:
        assert host.yaml is proxy and proxy.loads == 0
        assert host.yaml.load(text, Loader=host.yaml.Loader) == m.Dc(lr=4.0)
        assert proxy.loads == 1
        assert host.yaml.load(io.StringIO(text), Loader=yaml.FullLoader) == m.Dc(lr=4.0)
        assert host.yaml.unsafe_load(io.BytesIO(text.encode())) == m.Dc(lr=4.0)
        assert host.yaml.full_load(b"a: \xff") == {"a": "\ufffd"}
        assert proxy.loads == 4
        assert proxy.Loader is proxy.FullLoader is proxy.UnsafeLoader is sc.RunConfigLoader
        assert proxy.dump is yaml.dump and proxy.safe_load is yaml.safe_load
        with pytest.raises(ConfigRefused) as info:
            host.yaml.load("!!python/object/apply:os.system [echo]", Loader=yaml.Loader)
        assert str(info.value).startswith("--load-config cfg.yml: refused line 1: the tag !!python/object/apply:os.system ")
    assert host.yaml is yaml


def test_the_stand_in_names_the_versions_and_is_removed_after_an_error():
    host = host_module()
    with pytest.raises(ConfigRefused) as info:
        with sc.reading_configs_safely(host, "W", "sp-plugins 2.0"):
            host.yaml.load("!!python/name:sp_plugins.sp_no_such_module.X ''")
    assert "(this is sp-plugins 2.0)" in str(info.value)
    assert host.yaml is yaml


def test_a_block_inside_another_keeps_the_outer_stand_in():
    """A block inside another keeps the outer stand-in and its place in the refusals."""
    host = host_module()
    with sc.reading_configs_safely(host, "outer") as outer:
        with sc.reading_configs_safely(host, "inner") as inner:
            assert inner is outer and host.yaml is outer
            with pytest.raises(ConfigRefused, match=r"^outer: refused"):
                host.yaml.load("!custom x")
        assert host.yaml is outer
    assert host.yaml is yaml


# -- weights_only_checkpoints ------------------------------------------------------------------------
NAMES = ("TORCH_FORCE_WEIGHTS_ONLY_LOAD", "TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD")


@pytest.mark.parametrize("before", [(None, None), ("0", "1"), (None, "1"), ("1", None)])
def test_weights_only_checkpoints_sets_and_restores_the_environment(monkeypatch, before):
    """The block forces weights-only loads and restores the environment as it was after, also after an exception."""
    for name, value in zip(NAMES, before):
        if value is None:
            monkeypatch.delenv(name, raising=False)
        else:
            monkeypatch.setenv(name, value)
    with sc.weights_only_checkpoints():
        assert os.environ["TORCH_FORCE_WEIGHTS_ONLY_LOAD"] == "1"
        assert "TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD" not in os.environ
    assert tuple(os.environ.get(n) for n in NAMES) == before
    with pytest.raises(ZeroDivisionError):
        with sc.weights_only_checkpoints():
            1 / 0
    assert tuple(os.environ.get(n) for n in NAMES) == before


def test_a_pickled_callable_is_refused_inside_the_block_even_when_the_user_lifted_weights_only(monkeypatch, tmp_path):
    path = tmp_path / "evil.ckpt"
    torch.save({"call": os.system}, path)
    monkeypatch.setenv("TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD", "1")
    monkeypatch.delenv("TORCH_FORCE_WEIGHTS_ONLY_LOAD", raising=False)
    assert torch.load(path)["call"] is os.system  # (a reference: nothing is called)
    with sc.weights_only_checkpoints():
        with pytest.raises(Exception, match="Weights only load failed"):
            torch.load(path)
