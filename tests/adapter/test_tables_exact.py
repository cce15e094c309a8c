"""The host method tables' lookups (sp_plugins.adapter.tables), exactly: ``lookup`` takes the most derived
class a table names, and ``merged`` gathers the entries of every class with the same rule where two name
one key (the two used to disagree)."""

from __future__ import annotations

from sp_plugins.adapter.tables import lookup, merged
from sp_plugins.adapter.variants import class_path


class Base:
    pass


class Middle(Base):
    pass


class Leaf(Middle):
    pass


def test_lookup_takes_the_most_derived_class_the_table_names():
    table = {class_path(Base): "base", class_path(Middle): "middle"}
    assert lookup(table, Leaf) == (class_path(Middle), "middle")
    assert lookup(table, Base) == (class_path(Base), "base")
    assert lookup({class_path(Leaf): 1}, Middle) is None  # a subclass's entry does not apply to its base
    assert lookup(table, None) is None and lookup({}, Leaf) is None


def test_merged_gathers_every_class_and_the_most_derived_wins_as_in_lookup():
    table = {class_path(Base): {"field": "base's", "a": 1}, class_path(Leaf): {"field": "leaf's", "b": 2}}
    assert merged(table, Leaf) == {"field": "leaf's", "a": 1, "b": 2}
    assert merged(table, Middle) == {"field": "base's", "a": 1}
    flat = {class_path(Base): "base's", class_path(Leaf): "leaf's"}
    assert lookup(flat, Leaf)[1] == merged({k: {"field": v} for k, v in flat.items()}, Leaf)["field"]
    assert merged({}, Leaf) == {}
