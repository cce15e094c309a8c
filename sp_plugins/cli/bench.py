"""``sp-bench NAME [options]``: run one of the repository's benchmarks (``python -m bench.NAME``, or
``bench.speed.NAME`` for the speed benchmarks).

Benchmarks live in the source checkout's ``bench/`` folder (they are not part of the wheel);
``sp-bench`` finds it next to an editable install or in the current directory.
"""

from __future__ import annotations

import ast
import runpy
import sys
from pathlib import Path
from typing import List, Optional


def find_bench_dir() -> Optional[Path]:
    for root in (Path.cwd(), Path(__file__).resolve().parents[2]):
        if (root / "bench" / "__init__.py").is_file():
            return root / "bench"
    return None


def available(bench_dir: Path) -> dict:
    """Benchmark name -> first line of its docstring (the studies in ``bench/``, the speed benchmarks in ``bench/speed/``)."""
    return {name: doc for name, (_, doc) in _modules(bench_dir).items()}


def _modules(bench_dir: Path) -> dict:
    out = {}
    for path in sorted(bench_dir.glob("*.py")) + sorted(bench_dir.glob("speed/*.py")):
        if path.name.startswith("_") or path.stem == "common":
            continue
        doc = ast.get_docstring(ast.parse(path.read_text())) or ""
        if "__main__" in path.read_text():
            module = ".".join(("bench", *path.relative_to(bench_dir).with_suffix("").parts))
            out[path.stem] = (module, doc.strip().splitlines()[0] if doc.strip() else "")
    return out


def main(argv: Optional[List[str]] = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    bench_dir = find_bench_dir()
    if bench_dir is None:
        print(
            "sp-bench: no bench/ folder found. Benchmarks ship with the source checkout: run sp-bench "
            "from the repository root (git clone ...; pip install -e .).",
            file=sys.stderr,
        )
        return 2
    modules = _modules(bench_dir)
    names = {name: doc for name, (_, doc) in modules.items()}
    if not argv or argv[0] in ("-h", "--help", "list"):
        print("usage: sp-bench NAME [options]   (options: sp-bench NAME --help)\n\nbenchmarks:")
        for name, doc in names.items():
            print(f"  {name:<22} {doc}")
        return 0
    name, rest = argv[0], argv[1:]
    if name not in names:
        print(f"sp-bench: unknown benchmark {name!r}; available: {', '.join(names)}", file=sys.stderr)
        return 2
    sys.path.insert(0, str(bench_dir.parent))
    sys.argv = [f"sp-bench {name}", *rest]
    runpy.run_module(modules[name][0], run_name="__main__")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
