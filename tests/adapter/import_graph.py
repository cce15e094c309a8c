"""The import graph of the ``sp_plugins`` package, read from its source (an ``ast`` walk; nothing is
imported), for the no-cycle test.

An edge ``a -> b`` is an import of ``sp_plugins`` module ``b`` in ``a``, of one of three kinds: at
module level, inside a function, or under ``if TYPE_CHECKING:`` (:data:`KINDS`). The no-cycle test
counts all three: an import moved into a function or under ``TYPE_CHECKING`` still ties the two
modules together, it only hides the cycle. Imports of the *hosts'* packages inside functions (a
cheap registration module deferring a heavy host) are not edges of this graph at all.
"""

from __future__ import annotations

import ast
from pathlib import Path
from typing import Dict, Iterable, Iterator, List, Set, Tuple

from sp_plugins.adapter import hosts

PACKAGE = Path(__file__).resolve().parents[2] / "sp_plugins"
HOSTS = tuple(sorted({p for h in hosts.hosts().values() for p in h.packages + h.imports}))
"""The top-level packages of every registered host (sdfstudio's is also named ``nerfstudio``)."""


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


KINDS = ("module", "function", "type_checking")
"""Where an import statement sits: at module level, inside a function, under ``if TYPE_CHECKING:``."""


def _statements(tree: ast.AST) -> Iterator[Tuple[ast.AST, str]]:
    """``(import statement, kind)`` for every import of the module (:data:`KINDS`; a
    ``TYPE_CHECKING`` import inside a function counts as ``type_checking``)."""

    def walk(node: ast.AST, kind: str) -> Iterator[Tuple[ast.AST, str]]:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and _type_checking(child):
                for stmt in child.body:
                    yield from visit(stmt, "type_checking")
                for stmt in child.orelse:
                    yield from visit(stmt, kind)
                continue
            yield from visit(child, kind)

    def visit(child: ast.AST, kind: str) -> Iterator[Tuple[ast.AST, str]]:
        if isinstance(child, (ast.Import, ast.ImportFrom)):
            yield child, kind
        inner = "function" if kind == "module" and isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)) else kind
        yield from walk(child, inner)

    yield from walk(tree, "module")


def _resolve(name: str, modules: Set[str]) -> str:
    """The ``sp_plugins`` module ``name`` loads ("" when none): ``a.b.c`` -> the longest module prefix."""
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name


def edges() -> Dict[Tuple[str, str], Set[str]]:
    """``(importer, imported)`` -> the kinds of statement that import it, over every ``sp_plugins`` module."""
    paths = sorted(PACKAGE.rglob("*.py"))
    modules = {module_name(p) for p in paths}
    out: Dict[Tuple[str, str], Set[str]] = {}
    for path in paths:
        here = module_name(path)
        out.setdefault((here, here), set())  # every module is a node
        for node, kind in _statements(ast.parse(path.read_text(), str(path))):
            for name in _names(node, here, path.name == "__init__.py", modules):
                target = _resolve(name, modules) if name.startswith("sp_plugins") else ""
                if target and target != here:
                    out.setdefault((here, target), set()).add(kind)
    return out


def graph(kinds: Iterable[str] = KINDS) -> Dict[str, Set[str]]:
    """module -> the ``sp_plugins`` modules it imports by a statement of one of ``kinds``."""
    wanted = set(kinds)
    g: Dict[str, Set[str]] = {}
    for (a, b), found in edges().items():
        g.setdefault(a, set())
        if a != b and found & wanted:
            g[a].add(b)
    return g


def host_loaders() -> Set[str]:
    """Modules that import a host package when they load (themselves or through a module-level import)."""
    loads: Set[str] = set()
    for path in sorted(PACKAGE.rglob("*.py")):
        here = module_name(path)
        for node, kind in _statements(ast.parse(path.read_text(), str(path))):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""] if node.level == 0 else []
            if kind == "module" and any(n.split(".")[0] in HOSTS for n in names):
                loads.add(here)
    top = graph(["module"])
    changed = True
    while changed:
        changed = False
        for m, deps in top.items():
            if m not in loads and deps & loads:
                loads.add(m)
                changed = True
    return loads


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
    for upto in range(1, len(KINDS) + 1):
        print(f"cycles counting {' + '.join(KINDS[:upto])} imports: {len(cycles(graph(KINDS[:upto])))}")
    g = graph()
    for c in cycles(g):
        print(" <-> ".join(c))
        for m in c:
            print("   ", m, "->", sorted(x for x in g[m] if x in c))
