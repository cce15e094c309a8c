"""Every command of the README and the docs at the budget it writes, to the end, in order.

The suite (``tests/test_readme.py``) runs the same blocks with their budget flags lowered: that shows a
command works, not what it costs or whether it reaches its last step at the budget the text gives. This
study runs them as written, in one folder and one shell session per document (so ``outputs/.../config.yml``
is the run a command before wrote, as for a user), and records for each command its exit status, its wall
time and the cost the text states beside it.

    python -m bench.readme_as_written                     # every document, resuming where it stopped
    python -m bench.readme_as_written --only 'sp-neus'    # the blocks whose text matches a regex
    python -m bench.readme_as_written --list              # the blocks, their commands and stated costs

What differs from typing the blocks, all declared here: ``outputs/.../config.yml`` is filled as the suite
fills it (:data:`tests.helpers.readme_runner.PLACEHOLDERS`); ``fox`` is a link to the real capture
(``../shared/data/real/fox``, or ``SP_FOX_CAPTURE``); the blocks of the sdfstudio guide run with
sdfstudio's environment first on ``PATH``; one torch thread per command (``OMP_NUM_THREADS=1``). Blocks
marked ``readme-runner: skip`` are skipped with their reason; Python blocks are API examples (run by the
suite), not recipes.

A stated cost is declared where the text states it, by a comment right after the block's closing fence:
``<!-- stated: ns-train sp-neus-hashgrid=7 min; sp-export-mesh=1 min -->`` (a key is a piece of the command's
text, as the shell traced it). A command that takes more than 1.5x its stated cost is flagged.

Resumable: each block's record is kept in ``bench/out/readme_as_written/state.json`` under its document's name and
a hash of its text (not its line: an edit above a block keeps its record),
and a block that passed is not run again while its text is unchanged (``--fresh`` starts over). Writes
``docs/results/readme-as-written.md`` (the site's page of this study) and ``bench/results/readme_as_written.json``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
from tests.helpers import readme_runner as rr  # noqa: E402  (the suite's block parser: one definition of a block)

OUT = Path(os.environ.get("SP_BENCH_OUT", REPO / "bench" / "out")) / "readme_as_written"
RESULTS = REPO / "bench" / "results"
PAGE = REPO / "docs" / "results" / "readme-as-written.md"
STATED = re.compile(r"<!--\s*stated:\s*(?P<body>.+?)\s*-->")
TRACE = re.compile(r"^\+ (?P<t>\d+[.,]\d+) (?P<cmd>.*)$")
SLOW = 1.5
"""A command slower than this multiple of its stated cost is flagged."""


def seconds(text: str) -> float:
    """``"7 min"`` -> 420.0 (``s``, ``min``, ``h``)."""
    m = re.fullmatch(r"\s*(\d+(?:\.\d+)?)\s*(s|min|h)\s*", text)
    if not m:
        raise ValueError(f"a stated cost must read like '90 s', '7 min' or '1.5 h', got {text!r}")
    return float(m[1]) * {"s": 1, "min": 60, "h": 3600}[m[2]]


@dataclass
class Item:
    block: rr.Block
    stated: Dict[str, float]

    @property
    def key(self) -> str:
        """The document and the block's text: a block keeps its record when lines above it change."""
        return f"{self.block.path.name}:" + hashlib.sha256(self.block.source.encode()).hexdigest()[:12]


def by_text(state: Dict[str, Dict]) -> Dict[str, Dict]:
    """``state`` keyed as :attr:`Item.key` (records written before keyed ``name:line:hash``; the newest wins)."""
    out: Dict[str, Dict] = {}
    for key, record in sorted(state.items(), key=lambda kv: kv[1].get("date", "")):
        parts = key.split(":")
        out[f"{parts[0]}:{parts[-1]}"] = record
    return out


def items(path: Path) -> List[Item]:
    """The bash blocks of ``path`` with the costs stated after them."""
    text = path.read_text()
    lines = text.splitlines()
    out = []
    for block in rr.blocks(path):
        if block.language != "bash":
            continue
        close = next(i for i in range(block.line, len(lines)) if lines[i].startswith("```"))
        after = lines[close + 1] if close + 1 < len(lines) else ""
        stated: Dict[str, float] = {}
        m = STATED.search(after)
        if m:
            for part in m["body"].split(";"):
                key, _, cost = part.partition("=")
                stated[key.strip()] = seconds(cost)
        out.append(Item(block, stated))
    return out


def prepare(work: Path) -> None:
    """The inputs the text names but does not make: ``fox``."""
    fox = Path(os.environ.get("SP_FOX_CAPTURE", REPO.parent / "shared" / "data" / "real" / "fox"))
    if fox.is_dir() and not (work / "fox").exists():
        (work / "fox").symlink_to(fox.resolve())


def block_env(block: rr.Block) -> Dict[str, str]:
    env = rr.block_env()
    env["OMP_NUM_THREADS"] = "1"
    if block.path == rr.SDFSTUDIO_PAGE:
        sdf = Path(os.environ.get("SP_SDFSTUDIO_VENV", REPO / ".venv-sdfstudio")) / "bin"
        env["PATH"] = f"{sdf}{os.pathsep}{env['PATH']}"
    return env


def run(item: Item, work: Path, log_dir: Path) -> Dict:
    """Run one block as written; per-command wall times from the shell's own trace."""
    block = item.block
    body = "\n".join(rr.fill(line) for line in rr._logical_lines(block.source))
    assigned = re.findall(r"^([A-Za-z_]\w*)=", block.source, flags=re.M)
    keep = "".join(f"declare -p {name} >> .readme_state\n" for name in assigned)
    script = work / f"as_written_{block.path.stem}_{block.line}.sh"
    script.write_text(rr.BASH_PRELUDE + "PS4='+ ${EPOCHREALTIME} '\nset -x\n" + body + "\nset +x\n" + keep)
    log = log_dir / f"{block.path.stem}_{block.line}.log"
    start = time.time()
    with log.open("w") as f:
        rc = subprocess.run(["bash", str(script)], cwd=work, env=block_env(block), stdout=f, stderr=subprocess.STDOUT).returncode
    end = time.time()
    traced = [(float(m["t"].replace(",", ".")), m["cmd"]) for m in map(TRACE.match, log.read_text(errors="replace").splitlines()) if m]
    traced = [(t, c) for t, c in traced if c != "set +x"] + [(end, "")]
    commands = [{"command": cmd, "seconds": round(t_next - t, 1)} for (t, cmd), (t_next, _) in zip(traced, traced[1:])]
    return restate({"key": item.key, "where": block.where, "section": block.section, "rc": rc,
                    "seconds": round(end - start, 1), "commands": commands, "log": str(log.relative_to(OUT)),
                    "date": time.strftime("%Y-%m-%d %H:%M")}, item)


def restate(record: Dict, item: Item) -> Dict:
    """``record`` with the block's place and the costs the text states today (lines above a block and a figure in
    the text may change after the run; the record is the block's while its text is unchanged)."""
    record["where"] = item.block.where
    for c in record["commands"]:
        c["stated_s"] = next((s for key, s in item.stated.items() if key in c["command"]), None)
        c["slow"] = c["stated_s"] is not None and c["seconds"] > SLOW * c["stated_s"]
    record["unmatched_stated"] = [key for key in item.stated if not any(key in c["command"] for c in record["commands"])]
    return record


def report(records: List[Dict], skipped: List[Dict]) -> str:
    def fmt(s: Optional[float]) -> str:
        if s is None:
            return "-"
        return f"{s:.0f} s" if s < 120 else f"{s / 60:.1f} min"

    lines = ["| where | command (as written) | exit | measured | stated | |", "|---|---|---:|---:|---:|---|"]
    for r in records:
        for i, c in enumerate(r["commands"]):
            failed = r["rc"] != 0 and i == len(r["commands"]) - 1
            flag = "**failed**" if failed else ("**slower than stated**" if c["slow"] else "")
            text = c["command"] if len(c["command"]) <= 140 else c["command"][:137] + "..."
            lines.append(f"| {r['where']} | `{text}` | {r['rc'] if failed else 0} | {fmt(c['seconds'])} | {fmt(c['stated_s'])} | {flag} |")
        for key in r["unmatched_stated"]:
            lines.append(f"| {r['where']} | stated for `{key}`: no command matched | | | | **stale marker** |")
    for s in skipped:
        lines.append(f"| {s['where']} | skipped: {s['reason']} | | | | |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--only", help="run only the blocks whose text matches this regex (the others keep their records)")
    parser.add_argument("--document", action="append", help="run only this document's blocks (README.md, docs/guides/nerfstudio.md, ...; "
                        "repeatable); the others keep their records")
    parser.add_argument("--list", action="store_true", help="list the blocks, their commands and stated costs, run nothing")
    parser.add_argument("--fresh", action="store_true", help="forget the records and the work folder first")
    args = parser.parse_args(argv)
    docs = rr.documents()
    if args.document:
        wanted_docs = {(REPO / d).resolve() for d in args.document}
        unknown = wanted_docs - {d.resolve() for d in docs}
        if unknown:
            parser.error(f"--document {', '.join(sorted(str(u.relative_to(REPO)) for u in unknown))}: not a page of the "
                         "README or the docs' tables of contents")
    all_items = [item for doc in docs for item in items(doc)]
    if args.list:
        for item in all_items:
            b = item.block
            print(f"{b.where:18} {'skip: ' + b.skip if b.skip else 'runs'}  stated: {item.stated or '-'}")
        return 0
    if args.fresh and OUT.exists():
        shutil.rmtree(OUT)
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "logs").mkdir(exist_ok=True)
    state_path = OUT / "state.json"
    state: Dict[str, Dict] = by_text(json.loads(state_path.read_text())) if state_path.is_file() else {}
    work = OUT / "work"
    work.mkdir(exist_ok=True)
    prepare(work)
    records, skipped, failed = [], [], 0
    for item in all_items:
        b = item.block
        if b.skip:
            skipped.append({"where": b.where, "reason": b.skip})
            continue
        wanted = (args.only is None or re.search(args.only, b.source)) and (
            not args.document or b.path.resolve() in wanted_docs)
        if item.key in state and (state[item.key]["rc"] == 0 or not wanted):
            records.append(restate(state[item.key], item))
            continue
        if not wanted:
            continue
        print(f"[as written] {b.where} ({b.section}) runs", flush=True)
        record = run(item, work, OUT / "logs")
        state[item.key] = record
        state_path.write_text(json.dumps(state, indent=1))
        records.append(record)
        failed += record["rc"] != 0
        for c in record["commands"]:
            print(f"  {c['seconds']:8.1f} s  {c['command'][:120]}", flush=True)
        print(f"  exit {record['rc']}, {record['seconds']:.0f} s", flush=True)
        write_results(records, skipped)
    print(write_results(records, skipped))
    return 1 if failed else 0


def write_results(records: List[Dict], skipped: List[Dict]) -> str:
    """``docs/results/readme-as-written.md`` and ``bench/results/readme_as_written.json`` from the records so far
    (after every block: a study stopped midway keeps what it measured)."""
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "readme_as_written.json").write_text(json.dumps({"records": records, "skipped": skipped}, indent=1))
    text = report(records, skipped)
    PAGE.write_text(f"# The README and docs as written (`bench/readme_as_written.py`)\n\n{page_header()}\n\n{text}\n")
    return text


def page_header() -> str:
    """The page's command, machine and date."""
    import platform

    cpu = next((line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                if line.startswith("model name")), platform.processor()) if Path("/proc/cpuinfo").exists() else platform.processor()
    return (f"Command: `python -m bench.readme_as_written` (every block of the README and the docs at the budget it writes, "
            f"to the end, one torch thread per command). Machine: {cpu}, {os.cpu_count()} cores, {platform.system()}. "
            f"Written {time.strftime('%Y-%m-%d')}; each row keeps the time of the run that measured it.")


if __name__ == "__main__":
    sys.exit(main())
