"""The mutation study's record of which test kills which mutants (``bench/results/mutation_study/kills.json``):
every key names a test the suite collects (a test function, a method of a test class, or a whole file), each
note is one line, and the notes live there, not in the tests' docstrings (a docstring says what behaviour its
test pins)."""

from __future__ import annotations

import ast
import json
import re
from pathlib import Path
from typing import Dict, Iterator, List, Tuple

ROOT = Path(__file__).resolve().parents[2]
KILLS = ROOT / "bench" / "results" / "mutation_study" / "kills.json"
PENDING: set = set()
"""Notes not moved yet (none)."""
FUNCTIONS = (ast.FunctionDef, ast.AsyncFunctionDef)


def kills() -> Dict[str, str]:
    return json.loads(KILLS.read_text())


def collected_ids(rel: str, source: str) -> List[str]:
    """The node ids pytest collects from the test file ``rel`` (its default rules: ``test*`` functions,
    ``Test*`` classes without ``__init__``, nested ones included), without parameters; the file's own id and
    each test class's too."""

    def walk(body: List[ast.stmt], prefix: str) -> Iterator[str]:
        for node in body:
            if isinstance(node, FUNCTIONS) and node.name.startswith("test"):
                yield f"{prefix}::{node.name}"
            elif isinstance(node, ast.ClassDef) and node.name.startswith("Test") and \
                    not any(isinstance(n, FUNCTIONS) and n.name == "__init__" for n in node.body):
                yield f"{prefix}::{node.name}"
                yield from walk(node.body, f"{prefix}::{node.name}")

    return [rel, *walk(ast.parse(source).body, rel)]


def docstrings(rel: str, source: str) -> Iterator[Tuple[str, str]]:
    """(id, docstring) of the file and of every class and function in it (``file::Class::name``)."""

    def walk(node: ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef, key: str) -> Iterator[Tuple[str, str]]:
        doc = ast.get_docstring(node, clean=False)
        if doc is not None:
            yield key, doc
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.ClassDef, *FUNCTIONS)):
                yield from walk(child, f"{key}::{child.name}")

    yield from walk(ast.parse(source), rel)


def test_every_key_names_a_test_the_suite_collects():
    record = kills()
    assert len(record) > 300
    known = set()
    for rel in {key.split("::")[0] for key in record}:
        path = ROOT / rel
        assert path.is_file() and path.name.startswith("test_") and path.suffix == ".py", f"{rel}: not a test file"
        known.update(collected_ids(rel, path.read_text()))
    unknown = sorted(key for key in record if key not in known)
    assert not unknown, f"kills.json names tests that do not exist: {unknown}"


def test_a_misspelt_or_misplaced_key_is_not_a_collected_test():
    """What the check above compares against: a name with a letter changed, a method named without its class,
    a method of a class pytest does not collect, and a helper are not test ids."""
    source = ("def test_one():\n    pass\n\ndef helper():\n    pass\n\nclass TestA:\n    def test_m(self):\n"
              "        pass\n\nclass Helper:\n    def test_n(self):\n        pass\n")
    ids = collected_ids("tests/x/test_y.py", source)
    assert ids == ["tests/x/test_y.py", "tests/x/test_y.py::test_one", "tests/x/test_y.py::TestA",
                   "tests/x/test_y.py::TestA::test_m"]
    for wrong in ("tests/x/test_y.py::test_on", "tests/x/test_y.py::test_m", "tests/x/test_y.py::Helper::test_n",
                  "tests/x/test_y.py::helper", "tests/x/test_z.py::test_one"):
        assert wrong not in ids


def test_each_note_is_one_line_naming_what_it_kills():
    for key, note in kills().items():
        assert note and note == " ".join(note.split()) and note.startswith("Kills"), key


def test_no_test_docstring_keeps_a_kills_note():
    left = []
    for path in sorted((ROOT / "tests").rglob("test_*.py")):
        rel = path.relative_to(ROOT).as_posix()
        left += [key for key, doc in docstrings(rel, path.read_text()) if re.search(r"\bKills\b", doc)]
    assert sorted(set(left) - PENDING) == [], f"move these notes to {KILLS.relative_to(ROOT)}"
