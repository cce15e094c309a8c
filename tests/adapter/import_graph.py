"""The import graph of the ``sp_plugins`` package, read from its source (an ``ast`` walk; nothing is
imported), for the no-cycle test.

An edge ``a -> b`` is an import of ``sp_plugins`` module ``b`` in ``a``: at module level, or inside a
function, except where the function-level import defers a host (``a`` imports no host when it
loads, ``b`` does): that is what keeps a registration module cheap for a host's plugin discovery.
Any other import inside a function would only hide a cycle, so it counts as if at module level.
Imports under ``if TYPE_CHECKING:`` never run and are left out.
"""

from __future__ import annotations

import ast
from pathlib import Path
from typing import Dict, Iterator, List, Set, Tuple

PACKAGE = Path(__file__).resolve().parents[2] / "sp_plugins"
HOSTS = ("nerfstudio", "scripts")
"""The top-level packages of both hosts (sdfstudio's is also named ``nerfstudio``)."""


def module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _names(node: ast.AST, here: str, is_package: bool, modules: Set[str]) -> List[str]:
    """Dotted names an import statement loads (``from a import b``: ``a.b`` when that is a module, else ``a``)."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    if not isinstance(node, ast.ImportFrom):
        return []
    base = node.module or ""
    if node.level:
        parent = here.split(".") if is_package else here.split(".")[:-1]
        parent = parent[: len(parent) - (node.level - 1)]
        base = ".".join(parent + ([base] if base else []))
    return [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names]


def _statements(tree: ast.AST) -> Iterator[Tuple[ast.AST, bool]]:
    """``(import statement, inside a function)`` for every import not under ``if TYPE_CHECKING``."""

    def walk(node: ast.AST, in_function: bool) -> Iterator[Tuple[ast.AST, bool]]:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and _type_checking(child):
                for other in child.orelse:
                    yield from walk(other, in_function)
                continue
            if isinstance(child, (ast.Import, ast.ImportFrom)):
                yield child, in_function
            yield from walk(child, in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)))

    yield from walk(tree, False)


def _resolve(name: str, modules: Set[str]) -> str:
    """The ``sp_plugins`` module ``name`` loads ("" when none): ``a.b.c`` -> the longest module prefix."""
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name


def graph() -> Dict[str, Set[str]]:
    """module -> the ``sp_plugins`` modules it imports (edges as the module docstring says)."""
    paths = sorted(PACKAGE.rglob("*.py"))
    modules = {module_name(p) for p in paths}
    top: Dict[str, Set[str]] = {}
    lazy: Dict[str, Set[str]] = {}
    host_at_load: Set[str] = set()
    for path in paths:
        here = module_name(path)
        top[here], lazy[here] = set(), set()
        for node, in_function in _statements(ast.parse(path.read_text(), str(path))):
            for name in _names(node, here, path.name == "__init__.py", modules):
                if name.split(".")[0] in HOSTS and not in_function:
                    host_at_load.add(here)
                target = _resolve(name, modules) if name.startswith("sp_plugins") else ""
                if target and target != here:
                    (lazy if in_function else top)[here].add(target)
    changed = True  # a module loads a host when it, or a module it imports at load time, does
    while changed:
        changed = False
        for m, deps in top.items():
            if m not in host_at_load and deps & host_at_load:
                host_at_load.add(m)
                changed = True
    return {m: top[m] | {t for t in lazy[m] if m in host_at_load or t not in host_at_load} for m in top}


def cycles(g: Dict[str, Set[str]]) -> List[List[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: Dict[str, int] = {}
    low: Dict[str, int] = {}
    stack: List[str] = []
    on: Set[str] = set()
    out: List[List[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(g.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(g):
        if v not in index:
            visit(v)
    return out


if __name__ == "__main__":
    g = graph()
    for c in cycles(g):
        print(" <-> ".join(c))
        for m in c:
            print("   ", m, "->", sorted(x for x in g[m] if x in c))
