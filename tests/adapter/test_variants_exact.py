"""SP variants of host classes (sp_plugins.adapter.variants), exactly and host-neutrally: the reversible
name a saved ``config.yml`` carries, the class it resolves to in a fresh process, one variant per host
class, the refusals' lines, and the config conversion every ``with_sp`` starts with. Stand-in host
classes at this module's level (importable by path, as a host's are). The mutants each test kills are listed in
``bench/results/mutation_study/kills.json``."""

from __future__ import annotations

import dataclasses
import sys
import types
from typing import List

import pytest

from sp_plugins.adapter import variants as v


class HostModel:
    """A host's model class."""


class Outer:
    class NestedModel:
        """A class whose qualname has a dot (``Outer.NestedModel``)."""


class Mixin:
    pass


@dataclasses.dataclass
class HostConfig:
    _target: type = HostModel
    num_samples: int = 64
    names: List[str] = dataclasses.field(default_factory=lambda: ["a"])
    derived: int = dataclasses.field(default=0, init=False)


@dataclasses.dataclass
class SPHostConfig(HostConfig):
    sp: str = "off"


@pytest.mark.parametrize("path, text", [("a_b.C", "a_ub_dC"), ("x.y_z.W_", "x_dy_uz_dW_u"), ("plain", "plain"),
                                         ("__.._", "_u_u_d_d_u")])
def test_a_class_path_encodes_to_an_identifier_and_decodes_back(path, text):
    """``_`` -> ``_u`` (first: else the ``_`` of ``_d`` would be encoded too), ``.`` -> ``_d``."""
    assert v.encode_path(path) == text and text.isidentifier()
    assert v.decode_path(text) == path


def test_a_class_path_longer_than_256_characters_decodes_back():
    """Past 256 the decoder's index and ``len(text)`` are no longer CPython's cached small ints."""
    path = "pkg_" * 40 + "mod." + "Cls_" * 30
    text = v.encode_path(path)
    assert len(text) > 256 and v.decode_path(text) == path


@pytest.mark.parametrize("text", ["a_x", "a_", "_", "ab_dC_"])
def test_text_the_encoder_could_not_have_written_is_refused(text):
    """A lone ``_`` or one followed by anything but ``u`` / ``d``."""
    with pytest.raises(ValueError, match=rf"^not an encoded class path: {text!r}$"):
        v.decode_path(text)


def test_class_paths_import_back_to_the_same_class():
    """``module.qualname``, nested classes too; the longest importable module prefix wins, and every shorter
    one is tried after it."""
    assert v.class_path(HostModel) == f"{__name__}.HostModel"
    assert v.import_class(v.class_path(HostModel)) is HostModel
    assert v.import_class(v.class_path(Outer.NestedModel)) is Outer.NestedModel
    assert v.import_class("collections.OrderedDict") is __import__("collections").OrderedDict
    assert v.import_class("os.path.join.__class__") is types.FunctionType  # a function's attribute that is a type
    # a package whose name `sub` is rebound to something else than its submodule `sub`: the submodule lacks
    # the class, a shorter prefix finds it (the longest importable prefix is tried first, not only)
    package, submodule = _holder("_sp_variants_pkg"), _holder("_sp_variants_pkg.sub")
    try:
        package.sub = types.SimpleNamespace(Model=HostModel)
        assert v.import_class("_sp_variants_pkg.sub.Model") is HostModel
        assert submodule is sys.modules["_sp_variants_pkg.sub"]
        submodule.Model = Mixin  # both resolve: the longest importable prefix (the submodule) wins
        assert v.import_class("_sp_variants_pkg.sub.Model") is Mixin
        # a nested class in a submodule its package does not expose as an attribute: only the cut just
        # before the class's qualname finds it (every cut is tried, not every other one)
        submodule.Outer = Outer
        del package.sub
        assert v.import_class("_sp_variants_pkg.sub.Outer.NestedModel") is Outer.NestedModel
    finally:
        del sys.modules["_sp_variants_pkg"], sys.modules["_sp_variants_pkg.sub"]
    for missing in (f"{__name__}.NoSuchModel", "no_such_module.Model", f"{__name__}.HostModel.__doc__", "os.sep"):
        with pytest.raises(ImportError, match=rf"^no class importable at {missing!r}$"):
            v.import_class(missing)


def _holder(name: str) -> types.ModuleType:
    module = types.ModuleType(name)
    sys.modules[name] = module
    return module


@pytest.fixture
def factory():
    """A factory over a fresh holder module, with a ``Model`` builder (mixin first) and a ``ModelConfig`` one."""
    name = f"_sp_variants_holder_{id(object())}"
    module = _holder(name)
    made = []

    def model(host, cls_name, mod):
        made.append(host)
        return v.subclass((f.mixin("Model"), host), cls_name, mod, marker="model")

    def model_config(host, cls_name, mod):
        return v.subclass((host,), cls_name, mod)

    f = v.VariantFactory(name, {"Model": model, "ModelConfig": model_config})
    f.register("Model", Mixin)
    module.__getattr__ = f.resolve
    yield f, module, made
    del sys.modules[name]


def test_a_variant_is_named_by_its_host_path_made_once_and_placed_in_the_module(factory):
    """A variant is named by its host's encoded path, made once per process with the mixin first and placed in its
    module."""
    f, module, made = factory
    name = f.name("Model", HostModel)
    assert name == "SPModel__" + v.encode_path(f"{__name__}.HostModel")
    cls = f.get("Model", HostModel)
    assert cls.__name__ == cls.__qualname__ == name and cls.__module__ == module.__name__
    assert cls.__mro__[1:3] == (Mixin, HostModel) and cls.marker == "model"
    assert f.get("Model", HostModel) is cls and made == [HostModel]  # once per process
    assert module.__dict__[name] is cls
    config = f.get("ModelConfig", HostModel)
    assert config is not cls and config.__name__.startswith("SPModelConfig__") and made == [HostModel]


def test_a_name_in_a_fresh_process_resolves_to_the_same_variant(factory):
    """What PyYAML does with ``!!python/name:holder.SPModel__...``: ``getattr(module, name)``; ``ModelConfig``
    and ``Model`` names each resolve to their own kind."""
    f, module, _ = factory
    name = f.name("ModelConfig", Outer.NestedModel)
    cls = getattr(module, name)
    assert issubclass(cls, Outer.NestedModel) and cls.__name__ == name and getattr(module, name) is cls
    assert getattr(module, f.name("Model", HostModel)).__mro__[2] is HostModel
    with pytest.raises(AttributeError, match=r"^module '.*' has no attribute 'Unrelated'$"):
        getattr(module, "Unrelated")
    with pytest.raises(AttributeError, match=r"cannot make 'SPModel__a_x': not an encoded class path"):
        getattr(module, "SPModel__a_x")
    with pytest.raises(AttributeError, match=r"cannot make 'SPModel__no_umodule_dM': no class importable"):
        getattr(module, "SPModel__no_umodule_dM")


def test_a_kind_must_be_an_identifier_without_the_separator():
    """Else one name could start with two kinds' heads (``Model`` and ``Model__Config``)."""
    for kinds in (["Model", "Model__Config"], ["Model", "Field config"]):
        with pytest.raises(ValueError, match=r"^variant kinds must be identifiers without '__': \['(Model__Config|Field config)'\]$"):
            v.VariantFactory("holder", {k: None for k in kinds})
    v.VariantFactory("holder", {"ModelConfig": None, "Model": None, "Field": None})  # the hosts' kinds


def test_a_host_class_not_importable_by_its_path_is_refused_in_one_line(factory):
    """A class made in a function: a saved config naming its variant could not be loaded."""
    f, _, _ = factory

    class Local:
        pass

    with pytest.raises(ValueError, match=r"Local is not importable by that path, so a saved config\.yml naming its SP variant"):
        f.get("Model", Local)


def test_a_builder_that_makes_the_wrong_class_is_refused(factory):
    """A builder that makes a class that is not a subclass of the host, or has another name or module, is refused."""
    f, _, _ = factory
    for wrong in (lambda host, n, m: v.subclass((object,), n, m),  # not a subclass
                  lambda host, n, m: v.subclass((host,), n + "X", m),  # another name
                  lambda host, n, m: v.subclass((host,), n, "elsewhere"),  # another module
                  lambda host, n, m: v.subclass((host,), n, m[:-1]),  # one that sorts before it
                  lambda host, n, m: v.subclass((host,), n[:-1], m)):  # a name that sorts before it
        f.builders["Model"] = wrong
        f._made.clear()
        with pytest.raises(TypeError, match=r"^the Model builder made .*, not a subclass of .*HostModel"):
            f.get("Model", HostModel)


def test_a_builder_may_name_its_class_with_an_equal_string_of_its_own(factory):
    """A builder that spells the name it was given anew (an equal string, another object) makes the right class."""
    f, _, _ = factory
    f.builders["Model"] = lambda host, n, m: v.subclass((host,), "".join(list(n)), "".join(list(m)))
    f._made.clear()
    made = f.get("Model", HostModel)
    assert issubclass(made, HostModel) and made.__qualname__ == f.name("Model", HostModel)


def test_a_mixin_is_found_through_its_provider_module_or_refused():
    """A mixin is found by importing its provider module; one registered with another factory, or without a
    provider, is refused in one line."""
    name = "_sp_variants_provider_probe"
    provider = _holder(name)
    holder = _holder("_sp_variants_holder_mixins")
    try:
        f = v.VariantFactory(holder.__name__, {}, providers={"Field": name})
        provider.registered = f.register("Field", Mixin)  # what the provider does when it is imported
        assert f.mixin("Field") is Mixin
        g = v.VariantFactory(holder.__name__, {}, providers={"Field": name})
        with pytest.raises(LookupError, match=r"^no Field mixin is registered with _sp_variants_holder_mixins$"):
            g.mixin("Field")  # its provider imported, but registered with another factory
        with pytest.raises(LookupError, match=r"^no Model mixin"):
            g.mixin("Model")
    finally:
        del sys.modules[name], sys.modules[holder.__name__]


PENDING: list = []
"""The factory a provider module written by the next test registers its mixin with when it is imported."""


def test_a_mixin_not_registered_yet_is_registered_by_importing_its_provider(tmp_path, monkeypatch):
    """A saved config read in a fresh process: the variant module is imported, its mixin's module is not."""
    (tmp_path / "_sp_variants_provider_file.py").write_text(
        f"import {__name__} as t\nt.PENDING[-1].register('Field', t.Mixin)\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    f = v.VariantFactory("holder", {}, providers={"Field": "_sp_variants_provider_file"})
    PENDING.append(f)
    try:
        assert f.mixin("Field") is Mixin
    finally:
        PENDING.clear()
        sys.modules.pop("_sp_variants_provider_file", None)


def test_field_default_calls_the_factory_and_refuses_a_field_without_one():
    """A field's default comes from its factory (called anew each time) or its value; a field without one is
    refused."""
    first, second = v.field_default(HostConfig, "names"), v.field_default(HostConfig, "names")
    assert first == ["a"] and first is not second
    assert v.field_default(HostConfig, "num_samples") == 64

    @dataclasses.dataclass
    class Required:
        n: int

    with pytest.raises(ValueError, match=r"^Required\.n has no default$"):
        v.field_default(Required, "n")


def test_convert_copies_every_init_field_but_the_target_and_applies_changes():
    """Deep copies (the SP config does not share lists with the host's), ``_target`` the new class's default
    unless given, non-init fields left to the class."""
    host = HostConfig(num_samples=8, names=["x"])
    host.derived = 5
    out = v.convert(host, SPHostConfig, sp="on")
    assert type(out) is SPHostConfig and (out.num_samples, out.names, out.sp, out.derived) == (8, ["x"], "on", 0)
    assert out.names is not host.names and out._target is HostModel
    assert v.convert(host, SPHostConfig, _target=Mixin)._target is Mixin


def test_field_default_finds_a_field_named_by_a_parsed_string_and_a_default_equal_to_anything():
    """A field named as a flag hands it over (an equal string, not the literal); a default whose ``==`` says yes to
    everything (a wildcard) is still a default."""

    class Wildcard:
        def __eq__(self, other):
            return True

        __hash__ = object.__hash__

    anything = Wildcard()

    @dataclasses.dataclass
    class WithWildcard:
        w: object = anything

    assert v.field_default(HostConfig, "".join(list("num_samples"))) == 64
    assert v.field_default(WithWildcard, "w") is anything


def test_convert_copies_a_field_whose_name_sorts_before_the_target():
    """``convert`` copies every field but ``_target``, names that sort before it included."""

    @dataclasses.dataclass
    class Host:
        _target: type = HostModel
        _a: int = 1
        Upper: int = 2

    @dataclasses.dataclass
    class SPHost(Host):
        sp: str = "off"

    out = v.convert(Host(_a=7, Upper=9), SPHost)
    assert (out._a, out.Upper, out.sp) == (7, 9, "off")


def test_target_class_is_the_type_a_config_instantiates_or_none():
    assert v.target_class(HostConfig()) is HostModel
    assert v.target_class(types.SimpleNamespace(_target="nerfstudio.models.X")) is None
    assert v.target_class(types.SimpleNamespace()) is None


def test_table_refusal_names_the_first_reason_along_the_model_classes_mro():
    """A table names a class or a base; a reason may be a callable (asked only then) giving a reason or None."""

    class Derived(HostModel):
        pass

    host_path = v.class_path(HostModel)
    config = types.SimpleNamespace(_target=HostModel)
    assert v.table_refusal(types.SimpleNamespace(_target=Derived), {host_path: "a base's"}) == (Derived, "a base's")
    assert v.table_refusal(types.SimpleNamespace(_target=Derived), {host_path: "a base's", v.class_path(Derived): "its own"}) == (Derived, "its own")
    assert v.table_refusal(config, {host_path: "detaches positions"}) == (HostModel, "detaches positions")
    assert v.table_refusal(config, {host_path: lambda: None}, {host_path: lambda: "the second table's"}) == (HostModel, "the second table's")
    assert v.table_refusal(config, {"elsewhere.Model": "no"}) == (HostModel, None)
    assert v.table_refusal(config, {host_path: ""}) == (HostModel, None)
    ours = types.SimpleNamespace(_target=HostModel, sp="config")
    assert v.table_refusal(ours, {host_path: "never asked"}) == (HostModel, None)
    assert v.table_refusal(types.SimpleNamespace(), {}) == (None, "its model config has no model class (_target) to subclass")


def test_with_sp_starts_by_refusing_or_switching_an_sp_method_on():
    """A method SP cannot be put on is refused with its reason; a plain method is left off; an SP method gets a copy
    of its ``sp`` switched on, or the ``sp`` given explicitly."""
    with pytest.raises(ValueError, match=r"^SP cannot be put on nerfacto: it has no field$"):
        v.refuse_or_switch_on("nerfacto", HostConfig(), "it has no field", None)
    assert v.refuse_or_switch_on("nerfacto", HostConfig(), None, None) is False

    @dataclasses.dataclass
    class SP:
        enabled: bool = False
        alpha0: float = 0.1

    ours = types.SimpleNamespace(sp=SP())
    before = ours.sp
    assert v.refuse_or_switch_on("sp-nerfacto", ours, None, None) is True
    assert ours.sp == SP(enabled=True) and before.enabled is False  # a copy, switched on
    explicit = SP(enabled=True, alpha0=0.5)
    assert v.refuse_or_switch_on("sp-nerfacto", ours, None, explicit) is True
    assert ours.sp == explicit and ours.sp is not explicit
