"""The sweep's table (CSV + markdown), the paper-style histogram (baseline vs SP), success rates
and per-axis medians, from the trials' ``result.json`` files."""

from __future__ import annotations

import csv
import json
import math
import operator
import statistics
from pathlib import Path
from typing import Dict, List, Optional, Sequence

from sp_plugins.sweeps.spec import SweepSpec, Trial, parse_criterion, short_name
from sp_plugins.sweeps.trial import RESULT

_OPS = {">=": operator.ge, "<=": operator.le, ">": operator.gt, "<": operator.lt, "==": operator.eq, "!=": operator.ne}
SIDES = {False: "baseline", True: "SP", None: "-"}


def _read(folder: Path, trials: Sequence[Trial]):
    for t in trials:
        path = Path(folder) / t.key / RESULT
        if path.is_file():
            try:
                yield t, json.loads(path.read_text())
            except json.JSONDecodeError:  # a half-written file from a killed run: rerun it
                continue


def load_results(folder: Path, trials: Sequence[Trial]) -> Dict[str, dict]:
    """Finished trials (those with a ``result.json`` from the trial's own device), by key. A result
    that records no device was written before results did, when sweeps here ran on CPUs: cpu."""
    return {t.key: r for t, r in _read(folder, trials) if r.get("device", "cpu") == t.device}


def other_devices(folder: Path, trials: Sequence[Trial]) -> Dict[str, int]:
    """Trials of ``trials`` that have a result from another device: device -> how many."""
    found: Dict[str, int] = {}
    for t, r in _read(folder, trials):
        device = r.get("device", "cpu")
        if device != t.device:
            found[device] = found.get(device, 0) + 1
    return found


def succeeded(result: Optional[dict], criteria: Sequence[str]) -> Optional[bool]:
    """True / False for a finished trial (a failed one never succeeds); None without criteria."""
    if not criteria:
        return None
    if not result or result.get("status") != "ok":
        return False
    for c in criteria:
        name, op, value = parse_criterion(c)
        v = result["metrics"].get(name)
        if v is None or (isinstance(v, float) and math.isnan(v)) or not _OPS[op](float(v), value):
            return False
    return True


def rows(spec: SweepSpec, trials: Sequence[Trial], results: Dict[str, dict]) -> List[dict]:
    """One row per trial: every grid flag, SP side, seed, status, error and the metrics."""
    out = []
    flags = list(trials[0].params) if trials else []
    names = {f: short_name(f, flags) for f in flags}
    for t in trials:
        r = results.get(t.key)
        row = {"trial": t.key, "sp": SIDES[t.sp], **{names[f]: v for f, v in t.params.items()}, "seed": t.seed}
        row["status"] = r["status"] if r else "pending"
        row.update(r["metrics"] if r else {})
        ok = succeeded(r, spec.success)
        if ok is not None:
            row["success"] = int(ok) if r else None
        row["error"] = (r or {}).get("error") or ""
        out.append(row)
    return out


def _columns(table: List[dict]) -> List[str]:
    cols: List[str] = []
    for row in table:
        cols += [k for k in row if k not in cols and k != "error"]
    return cols + ["error"]


def _fmt(v) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        if v.is_integer() and abs(v) < 1e6:
            return str(int(v))
        return f"{v:.4g}" if abs(v) < 1e-2 or abs(v) >= 1e4 else f"{v:.4f}".rstrip("0").rstrip(".")
    return str(v).replace("|", "/")


def write_csv(table: List[dict], path: Path) -> None:
    cols = _columns(table)
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=cols)
        w.writeheader()
        for row in table:
            w.writerow({c: row.get(c, "") for c in cols})


# the markdown table's metric columns (the CSV has all of them)
MD_METRICS = {"ns-train": ("psnr", "ssim", "lpips", "train_seconds"),
              "sp-fit": ("chamfer", "fscore", "normal_consistency", "area_ratio", "negative_fraction", "sound", "psnr",
                         "seconds")}


def markdown_table(table: List[dict], metrics: Optional[Sequence[str]] = None, lead: Sequence[str] = ()) -> str:
    """Every column, or the ``lead`` columns (trial, SP side, flags, seed), ``metrics``, then
    status, success and error."""
    cols = _columns(table)
    if metrics is not None:
        tail = [c for c in ("status", "success", "error") if c in cols]
        cols = [c for c in lead if c in cols] + [m for m in metrics if m in cols] + tail
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for row in table:
        lines.append("| " + " | ".join(_fmt(row.get(c)) for c in cols) + " |")
    return "\n".join(lines)


def success_line(spec: SweepSpec, trials: Sequence[Trial], results: Dict[str, dict]) -> str:
    """'success (psnr >= 24): baseline 3/9 (33%), SP 7/9 (78%)' over finished trials."""
    if not spec.success:
        return "success: no criterion given (spec field `success`, or --success 'psnr >= 24')"
    parts = []
    for side in (False, True, None):
        done = [t for t in trials if t.sp is side and t.key in results]
        if not done:
            continue
        n = sum(bool(succeeded(results[t.key], spec.success)) for t in done)
        parts.append(f"{SIDES[side]} {n}/{len(done)} ({100 * n / len(done):.0f}%)")
    return f"success ({' and '.join(spec.success)}): " + ", ".join(parts)


def axis_medians(spec: SweepSpec, trials: Sequence[Trial], results: Dict[str, dict]) -> str:
    """Per grid axis and value: the median metric and the success count, baseline vs SP."""
    metric = spec.primary_metric
    sides = [s for s in (False, True, None) if any(t.sp is s for t in trials)]
    head = ["axis", "value"] + [f"{SIDES[s]} median {metric}" for s in sides]
    if spec.success:
        head += [f"{SIDES[s]} success" for s in sides]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    flags = list(trials[0].params) if trials else []
    for flag in flags:
        listed = next((vs for f, vs in spec.grid.items() if "--" + f.lstrip("-") == flag), [])
        seen = dict.fromkeys(t.params[flag] for t in trials)
        for value in [v for v in listed if v in seen] + [v for v in seen if v not in listed]:  # the spec's order
            cells = [short_name(flag, flags), value]
            group = {s: [t for t in trials if t.sp is s and t.params[flag] == value and t.key in results] for s in sides}
            for s in sides:
                vals = [results[t.key]["metrics"].get(metric) for t in group[s] if results[t.key]["status"] == "ok"]
                vals = [v for v in vals if v is not None]
                cells.append(_fmt(statistics.median(vals)) if vals else "-")
            if spec.success:
                for s in sides:
                    n = sum(bool(succeeded(results[t.key], spec.success)) for t in group[s])
                    cells.append(f"{n}/{len(group[s])}")
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def histogram(spec: SweepSpec, trials: Sequence[Trial], results: Dict[str, dict], path: Path,
              title: Optional[str] = None) -> Optional[Path]:
    """Histogram of the primary metric over the finished trials, baseline and SP overlaid; failed
    trials are counted in the legend (they have no value)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    metric = spec.primary_metric
    data, failed = {}, {}
    for side in (False, True, None):
        done = [results[t.key] for t in trials if t.sp is side and t.key in results]
        if not done:
            continue
        vals = [r["metrics"].get(metric) for r in done if r["status"] == "ok"]
        data[side] = [float(v) for v in vals if v is not None and math.isfinite(v)]
        failed[side] = len(done) - len(data[side])
    values = [v for vs in data.values() for v in vs]
    if not values:
        return None
    lo, hi = min(values), max(values)
    bins = 20 if hi > lo else 1
    edges = [lo + (hi - lo) * i / bins for i in range(bins + 1)] if hi > lo else [lo - 0.5, hi + 0.5]
    fig, ax = plt.subplots(figsize=(5.5, 3.4))
    colors = {False: "#888888", True: "#d62728", None: "#1f77b4"}
    for side, vs in data.items():
        label = f"{SIDES[side]} (n={len(vs)}" + (f", {failed[side]} failed)" if failed[side] else ")")
        ax.hist(vs, bins=edges, alpha=0.55, color=colors[side], label=label, edgecolor="white")
    for c in spec.success:
        name, _, value = parse_criterion(c)
        if name == metric:
            ax.axvline(value, color="k", ls="--", lw=1)
    ax.set_xlabel(metric)
    ax.set_ylabel("trials")
    ax.set_title(title or f"{spec.command[0]} {spec.command[1]}: {metric} over the sweep", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_report(spec: SweepSpec, trials: Sequence[Trial], results: Dict[str, dict], out: Path) -> dict:
    """``results.csv``, ``results.md`` (table, success line, per-axis medians), ``histogram.png``."""
    out = Path(out)
    table = rows(spec, trials, results)
    write_csv(table, out / "results.csv")
    flags = list(trials[0].params) if trials else []
    lead = ["trial", "sp", *(short_name(f, flags) for f in flags), "seed"]
    n_failed = sum(1 for r in results.values() if r["status"] != "ok")
    summary = (f"{len(results)} of {len(trials)} trials finished, {n_failed} failed. "
               + success_line(spec, trials, results))
    plot = histogram(spec, trials, results, out / "histogram.png")
    md = [f"# sweep: `{' '.join(spec.command)}`", "", summary, "",
          f"## per-axis medians ({spec.primary_metric})", "", axis_medians(spec, trials, results), "",
          "## trials", "", markdown_table(table, MD_METRICS.get(spec.program), lead)]
    if plot is not None:
        md[2:2] = [f"![histogram]({plot.name})", ""]
    (out / "results.md").write_text("\n".join(md) + "\n")
    return {"summary": summary, "table": table, "histogram": plot}
