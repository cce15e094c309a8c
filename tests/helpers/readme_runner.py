"""Runs the fenced command blocks of the README (and docs pages) as a user types them.

The blocks are found by Sybil (``sybil.parsers.markdown``), the Markdown example runner from PyPI:
its ``CodeBlockParser`` takes a language and an evaluator of our own, so ``bash`` blocks run in a
shell and ``python`` blocks in an interpreter, in document order, and its lexer gives each block's
position and line, which places the ``readme-runner`` markers and the section a block sits in.
(pytest-markdown-docs and mktestdocs evaluate Python only; phmdoctest turns blocks into a generated
test file, with no place for a shell evaluator.)

What may differ from the text, all declared here and nothing else:

* ``BUDGET``: the budget flags a command may be run with at a lower value (steps, rays per batch,
  mesh resolution, sample counts); a flag the command leaves at its default is added at that value.
* ``PLACEHOLDERS``: ``outputs/.../config.yml`` is the newest such file the commands before it wrote
  (resolved when the line runs). Blocks run in order in one folder and one shell session (variables
  a block sets are set in the next): ``my-scene`` is what the README's ``sp-scene spot my-scene`` made.
* ``FIXTURES``: inputs a block names that the README does not make: ``fox`` (a tiny crop of
  ``../shared/data/real/fox``, tests/helpers/fox_crop.py).
* ``PYTHON``: what a Python block needs defined (``x``, ``field``, ``loss_fn``; the ``my_plugin``
  the plugin example imports from, and a one-step training run of the method it registers).

* ``Runner(env=...)``: ``tests/test_readme.py`` puts the fork shims first on ``PATH``
  (:mod:`tests.helpers.forkshim`): each ``ns-*`` / ``sp-train`` / ``sp-export-mesh`` / ``sp-fit`` /
  ``sp-scene`` / ``nerfbaselines`` command the shell starts is forked from one interpreter that imported
  nerfstudio once, with the command line, folder, environment and output streams of the shell's; the real
  scripts run everywhere else (``sp-sweep``'s trials, which start the console scripts of the sweep's own
  environment).

A block that cannot run here carries ``<!-- readme-runner: skip (reason) -->`` on the line before
its fence; a block with no language (a directory tree) is not a command. Every other ``bash`` /
``python`` block runs; a command that fails (or prints a traceback) fails the run.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Dict, List, Optional, Tuple

REPO = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent
MARKER = re.compile(r"<!--\s*readme-runner:\s*skip\s*\((?P<reason>.+?)\)\s*-->\s*$")
SDFSTUDIO_PAGE = REPO / "docs" / "guides" / "sdfstudio.md"
"""Blocks of this page run in sdfstudio's environment (tests/sdfstudio/test_readme_sdfstudio.py)."""

# (command, flag, value): the command's text (a regex; the flag goes before its dataparser
# subcommand, else at the end of the command; for HEAD_PLACED commands right after their name),
# the flag, the value it runs with.
_TRAIN = r"\b(?:ns-train|sp-train) (?!--help)\S+"
BUDGET: Tuple[Tuple[str, str, str], ...] = (
    (r"\bsp-scene \S+ \S+", "--resolution", "32"),  # the scene every later block trains and evaluates on
    (r"\bsp-scene \S+ \S+", "--views", "8"),
    (r"\bsp-scene \S+ \S+", "--test-views", "2"),
    (_TRAIN, "--max-num-iterations", "2"),
    (_TRAIN, "--pipeline.datamanager.train-num-rays-per-batch", "64"),
    (r"\bsp-export-mesh\b", "--resolution", "128"),  # its smallest
    (r"\bsp-compare\b", "--mesh-resolution", "32"),
    (r"\bsp-compare\b", "--max-views", "2"),
    (r"\bns-export pointcloud\b", "--num-points", "2000"),
    (r"\bsp-fit (?:pointcloud|sdf)\b", "--steps", "2"),
    (r"\bsp-fit (?:pointcloud|sdf)\b", "--mesh-resolution", "32"),
    (r"\bsp-fit pointcloud\b", "--n-points", "5000"),
    (r"\bsp-fit (?:pointcloud|sdf)\b", "--metric-points", "2000"),
    (r"\bsp-fit image\b", "--steps", "2"),
    (r"\bsp-sweep\b", "--sample", "1"),  # one grid point of the sweep: its baseline and SP trials
    (r"\bsp-sdfstudio-train \S+", "--trainer.max-num-iterations", "2"),
    (r"\bsp-sdfstudio-train \S+", "--pipeline.datamanager.train-num-rays-per-batch", "64"),
    (r"\bsp-sdfstudio-extract-mesh\b", "--resolution", "64"),
    (r"\bnerfbaselines train\b", "--set max_num_iterations", "2"),  # (--set key=value: the value after "=")
    (r"\bnerfbaselines train\b", "--set pipeline.datamanager.train_num_rays_per_batch", "64"),
)
HEAD_PLACED = (r"\bsp-sweep\b",)

PLACEHOLDERS: Tuple[Tuple[str, object], ...] = (
    # outputs/.../x/.../config.yml, outputs/sp/.../config.yml -> the newest file matching the path with each
    # ``...`` a ``**`` (outputs/**/x/**/config.yml), when the line runs
    (r"\boutputs/(?=[\w./-]*\.\.\.)(?P<rest>[\w./-]*)",
     lambda m: "\"$(_readme_newest 'outputs/%s')\"" % m["rest"].replace("...", "**")),
)

BASH_PRELUDE = """\
set -euo pipefail
shopt -s globstar nullglob
# outputs/.../config.yml in the README: the newest file of that pattern (the run a command before wrote)
_readme_newest() { local f; f=$(ls -td $1 2>/dev/null | head -n 1); [ -n "$f" ] || { echo "readme-runner: nothing matches $1" >&2; return 1; }; echo "$f"; }
# one terminal session: the variables earlier blocks set (spot=...) are set here too
[ -f .readme_state ] && source .readme_state
"""

PYTHON: Dict[str, Tuple[str, str]] = {
    # a block that uses these names -> (prelude, epilogue)
    "loss_fn(field(sp(x)))": (
        "import torch\nx = torch.rand(256, 3) * 2 - 1\nfield = torch.nn.Linear(3, 1)\n"
        "loss_fn = lambda y: y.square().mean()\n",
        "assert sp.alpha == 0 and torch.equal(sp(x), x), 'alpha did not reach 0 by the end'\n"
        "assert not torch.equal(x_train, x)\n",
    ),
    "from my_plugin.config import mymethod": (
        # the plugin's method: nerfstudio's own nerfacto (a contracted scene), by the host's config
        "import sys, types\nfrom nerfstudio.configs.method_configs import method_configs\n"
        "sys.modules['my_plugin'] = types.ModuleType('my_plugin')\n"
        "sys.modules['my_plugin.config'] = config = types.ModuleType('my_plugin.config')\n"
        "config.mymethod = method_configs['nerfacto']\n",
        # one training step of the registered method on the README's scene (SP's checks run in it)
        "from pathlib import Path\n"
        "from nerfstudio.data.dataparsers.blender_dataparser import BlenderDataParserConfig\n"
        "from nerfstudio.scripts.train import main\n"
        "c = sp_mymethod.config\n"
        "c.max_num_iterations, c.vis, c.machine.device_type, c.output_dir = 1, 'tensorboard', 'cpu', Path('outputs')\n"
        "c.pipeline.datamanager.train_num_rays_per_batch = 64\n"
        "c.pipeline.datamanager.dataparser = BlenderDataParserConfig(data=Path('my-scene/blender'))\n"
        "if __name__ == '__main__':\n    main(c)\n",
    ),
}


def fox_fixture(workdir: Path) -> Optional[str]:
    """``fox``: a 20-view crop of the real capture at 1/5 size; the skip reason when it is missing."""
    from tests.helpers.fox_crop import fox_missing, make_fox_crop

    why = fox_missing()
    if why is None and not (workdir / "fox").exists():
        make_fox_crop(workdir / "fox", views=20, factor=5)  # instant-ngp-data holds out 2 (ns-eval fails on 1)
    return why


FIXTURES: Dict[str, Callable[[Path], Optional[str]]] = {r"--data fox\b": fox_fixture}


@dataclass
class Block:
    path: Path
    line: int
    language: str
    source: str
    section: str
    skip: Optional[str] = None
    lowered: List[str] = field(default_factory=list)

    @property
    def where(self) -> str:
        return f"{self.path.name}:{self.line}"


def _parsers(evaluator: Optional[Callable] = None) -> list:
    from sybil.parsers.markdown import CodeBlockParser

    return [CodeBlockParser(language=language, evaluator=evaluator) for language in ("bash", "python")]


def _block(path: Path, text: str, start: int, line: int, language: str, source: str) -> Block:
    before = text[:start].rstrip("\n").rsplit("\n", 1)[-1]
    mark = MARKER.search(before)
    assert mark or "readme-runner:" not in before, f"{path.name}:{line}: a readme-runner marker without a reason: {before}"
    headings = re.findall(r"^##+ .*$", text[:start], flags=re.M)
    return Block(path, line, language.strip(), source, headings[-1] if headings else "",
                 mark.group("reason") if mark else None)


def blocks(path: Path) -> List[Block]:
    """Every fenced block of ``path`` in order (Sybil's lexer for ``bash`` / ``python``; a fence with
    another or no language, a directory tree, by a regex, to be counted), with marker and section."""
    from sybil import Sybil

    text = path.read_text()
    found: Dict[int, Block] = {}
    for example in Sybil(parsers=_parsers()).parse(path):
        region = example.region
        found[region.start] = _block(path, text, region.start, example.line, region.lexemes["arguments"],
                                     region.lexemes["source"].text)
    for m in re.finditer(r"^```(\{[\w-]+\}|\w*)\n(.*?)^```$", text, flags=re.M | re.S):  # {eval-rst}: a MyST directive
        if m.start() not in found:
            found[m.start()] = _block(path, text, m.start(), text[: m.start()].count("\n") + 1, m.group(1), m.group(2))
    return [found[k] for k in sorted(found)]


class Runner:
    """Runs a document's blocks in order in one working folder (Sybil calls :meth:`evaluate` for
    each ``bash`` / ``python`` block); ``mine(block)`` says which blocks this suite runs (the rest
    are counted as run elsewhere)."""

    def __init__(self, workdir: Path, mine: Callable[[Block], bool], timeout: float = 600,
                 env: Optional[Dict[str, str]] = None):
        self.workdir, self.mine, self.timeout = workdir, mine, timeout
        self.env = env or {}
        """Variables set for every block (the fork shims' ``PATH`` and socket: tests/helpers/forkshim.py)."""
        self.outcomes: List[Outcome] = []

    def run(self, path: Path) -> List[Outcome]:
        from sybil import Sybil

        text = path.read_text()
        document = Sybil(parsers=_parsers(self.evaluate)).parse(path)
        document.namespace["text"] = text
        for example in document:
            example.evaluate()
        done = {(o.block.path, o.block.line) for o in self.outcomes}
        for block in blocks(path):  # the fences Sybil does not run: no language, or another one
            if block.language not in ("bash", "python") and (block.path, block.line) not in done:
                self.outcomes.append(Outcome(block, "not a command", f"a ```{block.language} block"))
        self.outcomes.sort(key=lambda o: (str(o.block.path), o.block.line))
        return self.outcomes

    def evaluate(self, example) -> None:
        region = example.region
        block = _block(Path(example.path), example.namespace["text"], region.start, example.line,
                       region.lexemes["arguments"], region.lexemes["source"].text)
        if not self.mine(block):
            self.outcomes.append(Outcome(block, "elsewhere", "run by the other environment's suite"))
            return
        self.outcomes.append(run_block(block, self.workdir, self.timeout, self.env))


def _logical_lines(source: str) -> List[str]:
    return source.replace("\\\n", " ").splitlines()


def lower(line: str) -> Tuple[str, List[str]]:
    """``line`` with every ``BUDGET`` flag of the commands in it at its budget value; what changed."""
    changes: List[str] = []
    code, hash_, comment = _split_comment(line)
    for command, flag, value in BUDGET:
        for m in reversed(list(re.finditer(command, code))):
            end = _command_end(code, m.start(), m.end())
            segment = code[m.end():end]
            present = re.search(rf"(?<=\s){re.escape(flag)}(?:[ =])(?P<v>\S+)", segment)
            if present:
                if present.group("v") == value:
                    continue
                segment = segment[: present.start("v")] + value + segment[present.end("v"):]
            else:
                parser = re.search(r"\s(?=[a-z][a-z-]*-data\b)", segment)
                at = 0 if command in HEAD_PLACED else parser.start() if parser else len(segment.rstrip())
                segment = f"{segment[:at]} {flag} {value}{segment[at:]}"
            code = code[: m.end()] + segment + code[end:]
            changes.append(f"{m.group(0).split()[0]} {flag} {value}")
    return (code + hash_ + comment if changes else line), changes


def _split_comment(line: str) -> Tuple[str, str, str]:
    """(code, '#', comment): the first ``#`` outside quotes that starts a word."""
    quote = None
    for i, ch in enumerate(line):
        if quote:
            quote = None if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch == "#" and (i == 0 or line[i - 1].isspace()):
            return line[:i].rstrip() + " ", "#", line[i + 1:]
    return line, "", ""


def _command_end(code: str, begin: int, start: int) -> int:
    """Where the command at ``begin`` ends: its closing quote when it is quoted (``--command "..."``),
    else ``&&``, ``;``, ``|`` or the line's end."""
    quoted = code[:begin].count('"') % 2 == 1
    m = re.compile(r'"' if quoted else r"&&|;|\|").search(code, start)
    return m.start() if m else len(code.rstrip())


def fill(line: str) -> str:
    for pattern, replacement in PLACEHOLDERS:
        line = re.sub(pattern, replacement, line)  # type: ignore[arg-type]
    return line


@dataclass
class Outcome:
    block: Block
    status: str  # "as written", "lowered", "skipped", "not a command", "elsewhere"
    detail: str = ""
    seconds: float = 0.0


def run_block(block: Block, workdir: Path, timeout: float = 600, extra_env: Optional[Dict[str, str]] = None) -> Outcome:
    """Run one block in ``workdir`` (the blocks before it ran there); raises AssertionError on failure."""
    if block.skip:
        return Outcome(block, "skipped", block.skip)
    if block.language not in ("bash", "python"):
        return Outcome(block, "not a command", f"a ```{block.language or ''} block")
    for pattern, fixture in FIXTURES.items():
        if re.search(pattern, block.source):
            why = fixture(workdir)
            if why:
                if os.environ.get("CI") == "true":
                    raise AssertionError(f"{block.where}: CI=true and its input is missing: {why}")
                return Outcome(block, "skipped", why)
    # the host's environment with this interpreter's commands first; no checkout on the path (a user
    # who installed the package has no bench/ or tests/ to import)
    env = block_env()
    env.update(extra_env or {})
    changes: List[str] = []
    if block.language == "bash":
        lines = []
        for line in _logical_lines(block.source):
            lowered, changed = lower(line)
            changes += changed
            lines.append(fill(lowered))
        assigned = re.findall(r"^([A-Za-z_]\w*)=", block.source, flags=re.M)
        keep = "".join(f"declare -p {name} >> .readme_state\n" for name in assigned)
        script = workdir / f"readme_{block.line}.sh"
        script.write_text(BASH_PRELUDE + "\n".join(lines) + "\n" + keep)
        args = ["bash", str(script)]
    else:
        prelude, epilogue = next(((p, e) for key, (p, e) in PYTHON.items() if key in block.source), ("", ""))
        script = workdir / f"readme_{block.line}.py"
        script.write_text(prelude + block.source + epilogue)
        args = [sys.executable, str(script)]
    start = time.monotonic()
    print(f"readme-runner: {block.where} runs ({', '.join(sorted(set(changes))) or 'as written'})", file=sys.stderr, flush=True)
    proc = subprocess.run(args, cwd=workdir, env=env, capture_output=True, text=True, timeout=timeout)
    output = proc.stdout + proc.stderr
    report = f"{block.where} ({block.section}) failed, exit status {proc.returncode}:\n{script.read_text()}\n--- output\n{output[-6000:]}"
    assert proc.returncode == 0, report
    assert "Traceback (most recent call last)" not in output, "printed a traceback: " + report
    block.lowered = changes
    return Outcome(block, "lowered" if changes else "as written", "; ".join(sorted(set(changes))), time.monotonic() - start)


def block_env() -> Dict[str, str]:
    """The environment blocks run in: the host's, with this interpreter's commands first."""
    return dict(os.environ, OMP_NUM_THREADS="1", PATH=f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}")


def summary(outcomes: List[Outcome]) -> str:
    counts: Dict[str, int] = {}
    for o in outcomes:
        counts[o.status] = counts.get(o.status, 0) + 1
    head = f"{len(outcomes)} fenced blocks: " + ", ".join(f"{n} {s}" for s, n in counts.items())
    rows = [f"  {o.block.where:16} {o.block.language or '-':7} {f'{o.seconds:5.0f} s' if o.seconds else '':7} {o.status}"
            f"{': ' + o.detail if o.detail else ''}" for o in outcomes]
    return "\n".join([head, *rows])


def documents() -> List[Path]:
    """README.md, then the docs pages in the order of ``docs/index.md``'s tables of contents (``<!-- toctree``
    comments, docs/conf.py; a page is read after the pages before it, as a reader goes through the site), then
    any page no table lists."""
    docs = REPO / "docs"
    listed: List[Path] = []
    for body in re.findall(r"^<!-- toctree\n(.*?)^-->$", (docs / "index.md").read_text(), flags=re.M | re.S):
        listed += [docs / f"{line.strip()}.md" for line in body.splitlines() if line.strip() and not line.startswith(":")]
    rest = sorted(p for p in docs.rglob("*.md") if p not in listed and p.name != "index.md" and "_build" not in p.parts)
    return [REPO / "README.md", docs / "index.md", *listed, *rest]

