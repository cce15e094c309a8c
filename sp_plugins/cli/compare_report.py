"""The report of ``sp-compare`` (:mod:`sp_plugins.cli.compare`): a pair's figures, table and offline page, and over seeds
the summary (each side's mean and spread, the paired difference with its interval and verdict), its figure and page.

Pure functions of what :mod:`~sp_plugins.cli.compare` measured (a :class:`Run` per run, or each pair's JSON): nothing
here opens a run folder or renders a model.
"""

from __future__ import annotations

import base64
import html
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Sequence

from sp_plugins.stats import paired_difference, spread


@dataclass
class Run:
    label: str
    config_path: Path
    config: object
    pipeline: object = None
    step: int = 0
    views: List[dict] = field(default_factory=list)
    overall: Dict[str, float] = field(default_factory=dict)
    curves: Dict[str, List[List[float]]] = field(default_factory=dict)
    mesh: Optional[dict] = None


def sp_summary(config) -> str:
    sp = getattr(config.pipeline.model, "sp", None)
    if sp is None:
        return "no SP"
    return f"SP alpha0 {sp.alpha0:g} to 0 by {sp.end:g}" if sp.enabled else "SP off"


HELD_OUT = "held-out views"


def views_figure(images_a, images_b, runs: Sequence[Run], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    rows = len(images_a)
    errors = [[np.abs(p - t).mean(-1) for p, t in images] for images in (images_a, images_b)]
    vmax = max(0.05, max(float(e.max()) for es in errors for e in es))
    fig, axes = plt.subplots(rows, 5, figsize=(12, 2.5 * rows + 0.4), squeeze=False)
    titles = ["ground truth", runs[0].label, runs[1].label, f"|error| {runs[0].label}", f"|error| {runs[1].label}"]
    for r in range(rows):
        (pa, truth), (pb, _) = images_a[r], images_b[r]
        panels = [truth, pa, pb, errors[0][r], errors[1][r]]
        for c, panel in enumerate(panels):
            ax = axes[r][c]
            ax.imshow(panel, cmap="magma" if c >= 3 else None, vmin=0, vmax=vmax if c >= 3 else None)
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title("\n".join(_wrap(titles[c], 28)), fontsize=8)
        axes[r][0].set_ylabel(f"view {r}\n{runs[0].views[r].get('psnr', float('nan')):.2f} / "
                              f"{runs[1].views[r].get('psnr', float('nan')):.2f} dB", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _wrap(text: str, width: int) -> List[str]:
    import textwrap

    return textwrap.wrap(text, width) or [text]


def curves_figure(runs: Sequence[Run], path: Path) -> bool:
    """Both runs' loss and PSNR, SP's alpha dotted; a panel only where a run logged two steps or more of it
    (MipNeRF logs no training PSNR); False (no figure) when there is none."""
    panels = [(key, title) for key, title in (("loss", "training loss"), ("psnr", "training PSNR (dB)"))
              if any(len(run.curves.get(key, [])) > 1 for run in runs)]
    if not panels:
        return False
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(panels), figsize=(5.5 * len(panels), 3.6), squeeze=False)
    for ax, (key, title) in zip(axes[0], panels):
        for run, colour in zip(runs, ("tab:blue", "tab:orange")):
            points = sorted(run.curves.get(key, []))
            if points:
                ax.plot([p[0] for p in points], [p[1] for p in points], color=colour, label=run.label, lw=1,
                        marker="o" if len(points) < 20 else None, ms=3)
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("step")
        if key == "loss":
            ax.set_yscale("log")
        alphas = [(run, sorted(run.curves.get("alpha", []))) for run in runs]
        if any(points for _, points in alphas):
            twin = ax.twinx()
            for (run, points), colour in zip(alphas, ("tab:blue", "tab:orange")):
                if points:
                    twin.plot([p[0] for p in points], [p[1] for p in points], color=colour, ls=":", lw=1)
            twin.set_ylabel("SP alpha (dotted)", fontsize=8)
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def table(runs: Sequence[Run], kind: str = HELD_OUT) -> List[List[str]]:
    """Rows of the overall comparison: metric, run A, run B, B - A (or B / A for mesh distances)."""
    rows = [["", runs[0].label, runs[1].label, "B - A"]]
    for key, label in (("psnr", "PSNR (dB)"), ("ssim", "SSIM"), ("lpips", "LPIPS")):
        if key in runs[0].overall and key in runs[1].overall:
            a, b = runs[0].overall[key], runs[1].overall[key]
            rows.append([f"{label}, {len(runs[0].views)} {kind}", f"{a:.4g}", f"{b:.4g}", f"{b - a:+.3g}"])
    if runs[0].mesh and runs[1].mesh:
        for key, label in (("chamfer", "Chamfer (of the true diagonal)"), ("fscore", "F-score @1%"),
                           ("normal_consistency", "normal consistency"), ("area_ratio", "area / true area")):
            if key in runs[0].mesh and key in runs[1].mesh:
                a, b = runs[0].mesh[key], runs[1].mesh[key]
                rows.append([label, f"{a:.4g}", f"{b:.4g}", f"{b - a:+.3g}"])
    rows.append(["trained steps", str(runs[0].step), str(runs[1].step), ""])
    return rows


def _inline(path: Path) -> str:
    return "data:image/png;base64," + base64.b64encode(path.read_bytes()).decode()


def write_html(runs: Sequence[Run], rows: List[List[str]], figures: Dict[str, Path], notes: List[str], path: Path,
               kind: str = HELD_OUT) -> None:
    esc = html.escape
    head = "".join(f"<th>{esc(c)}</th>" for c in rows[0])
    body = "".join("<tr>" + "".join(f"<td>{esc(c)}</td>" for c in row) + "</tr>" for row in rows[1:])
    per_view = "".join(
        f"<tr><td>{i}</td>" + "".join(f"<td>{v.get(k, float('nan')):.4g}</td>" for v in (runs[0].views[i], runs[1].views[i])
                                      for k in ("psnr", "ssim")) + "</tr>" for i in range(len(runs[0].views)))
    images = "".join(f"<h2>{esc(title)}</h2><img alt=\"{esc(title)}\" src=\"{_inline(p)}\">" for title, p in figures.items())
    runs_list = "".join(f"<li><b>{esc(r.label)}</b>: <code>{esc(str(r.config_path))}</code>, step {r.step}, "
                        f"{esc(sp_summary(r.config))}</li>" for r in runs)
    text = f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>sp-compare: {esc(runs[0].label)} vs {esc(runs[1].label)}</title>
<style>body{{font-family:sans-serif;max-width:1200px;margin:2em auto;padding:0 1em}}table{{border-collapse:collapse}}
td,th{{border:1px solid #ccc;padding:.3em .6em;text-align:right}}td:first-child,th:first-child{{text-align:left}}
img{{max-width:100%}}</style></head>
<body><h1>sp-compare</h1><ul>{runs_list}</ul>
<h2>Overall</h2><table><tr>{head}</tr>{body}</table>
{images}
<h2>Per view ({esc(kind)})</h2><table><tr><th>view</th><th>PSNR A</th><th>SSIM A</th><th>PSNR B</th><th>SSIM B</th></tr>{per_view}</table>
<p>{"<br>".join(esc(n) for n in notes)}</p>
</body></html>
"""
    path.write_text(text)


def print_table(rows: List[List[str]]) -> None:
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    for n, row in enumerate(rows):
        print("  ".join(cell.ljust(w) if i == 0 else cell.rjust(w) for i, (cell, w) in enumerate(zip(row, widths))))
        if n == 0:
            print("  ".join("-" * w for w in widths))


SUMMARY_METRICS = (
    ("psnr", "PSNR (dB)", "overall", True), ("ssim", "SSIM", "overall", True), ("lpips", "LPIPS", "overall", False),
    ("chamfer", "Chamfer (of the true diagonal)", "mesh", False), ("fscore", "F-score @1%", "mesh", True),
    ("normal_consistency", "normal consistency", "mesh", True),
)
"""(key, label, where in a run's JSON, higher is better) of the metrics summarised over seeds."""


def seed_summary(pairs: Sequence[tuple]) -> List[dict]:
    """Per metric both runs of every pair have: each side's values by seed, mean and sd, and the paired
    difference SP - baseline with its interval and verdict. ``pairs``: ``(seed, payload)`` as
    :func:`compare_pair` returns them (run 0 the baseline, run 1 SP)."""
    out = []
    for key, label, where, higher in SUMMARY_METRICS:
        values = [[(run.get(where) or {}).get(key) for run in payload["runs"]] for _, payload in pairs]
        if not values or any(v is None or not math.isfinite(v) for pair in values for v in pair):
            continue
        a, b = [v[0] for v in values], [v[1] for v in values]
        (ma, sa), (mb, sb) = spread(a), spread(b)
        out.append({"metric": key, "label": label, "higher_is_better": higher, "seeds": [seed for seed, _ in pairs],
                    "baseline": a, "sp": b, "baseline_mean": ma, "baseline_sd": sa, "sp_mean": mb, "sp_sd": sb,
                    "difference": paired_difference(a, b, higher_is_better=higher).as_dict()})
    return out


def _mean_sd(mean: float, sd: Optional[float]) -> str:
    return f"{mean:.4g}" + (f" ± {sd:.2g}" if sd is not None else "")


def summary_table(summary: Sequence[dict], kind: str) -> List[List[str]]:
    """Rows of the over-seeds table: metric, baseline mean ± sd, SP mean ± sd, SP - baseline [95% interval], verdict."""
    n = len(summary[0]["seeds"]) if summary else 0
    rows = [["", f"baseline ({n} seeds)", f"SP ({n} seeds)", "SP - baseline [95% t interval]", "verdict for SP"]]
    for item in summary:
        d = item["difference"]
        label = f"{item['label']}, {kind}" if item["metric"] in ("psnr", "ssim", "lpips") else item["label"]
        interval = f"{d['mean']:+.3g}" + (f" [{d['low']:+.3g}, {d['high']:+.3g}]" if d["low"] is not None else "")
        rows.append([label, _mean_sd(item["baseline_mean"], item["baseline_sd"]), _mean_sd(item["sp_mean"], item["sp_sd"]),
                     interval, d["verdict"]])
    return rows


def per_seed_table(summary: Sequence[dict]) -> List[List[str]]:
    """One row per seed: each metric's baseline -> SP."""
    rows = [["seed"] + [item["label"] + " (baseline -> SP)" for item in summary]]
    for i, seed in enumerate(summary[0]["seeds"] if summary else []):
        rows.append([str(seed)] + [f"{item['baseline'][i]:.4g} -> {item['sp'][i]:.4g}" for item in summary])
    return rows


def seeds_figure(summary: Sequence[dict], path: Path) -> None:
    """Per metric, every seed's baseline and SP value joined by a line (the pairing), and each side's mean."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(summary), figsize=(2.6 * len(summary), 3.2), squeeze=False)
    for ax, item in zip(axes[0], summary):
        for seed, a, b in zip(item["seeds"], item["baseline"], item["sp"]):
            ax.plot([0, 1], [a, b], color="0.6", lw=1, marker="o", ms=4)
            ax.annotate(str(seed), (1.03, b), fontsize=7, va="center")
        ax.plot([0, 1], [item["baseline_mean"], item["sp_mean"]], color="tab:red", lw=2, marker="_", ms=16, label="mean")
        d = item["difference"]
        ax.set_title(f"{item['label']}\n{d['verdict']}", fontsize=8)
        ax.set_xticks([0, 1], ["baseline", "SP"])
        ax.set_xlim(-0.3, 1.3)
        ax.tick_params(labelsize=7)
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_seed_report(pairs: Sequence[tuple], out: Path) -> None:
    esc = html.escape
    kinds = {payload["scored_views"] for _, payload in pairs}
    kind = kinds.pop() if len(kinds) == 1 else "views"
    summary = seed_summary(pairs)
    rows, seed_rows = summary_table(summary, kind), per_seed_table(summary)
    figure = out / "seeds.png"
    if summary:
        seeds_figure(summary, figure)
    payload = {"seeds": [seed for seed, _ in pairs], "scored_views": kind, "summary": summary, "table": rows,
               "per_seed": seed_rows, "pairs": {str(seed): f"seed-{seed}/compare.json" for seed, _ in pairs},
               "interval": "95% Student t over the seed pairs (n - 1 degrees of freedom)"}
    (out / "compare.json").write_text(json.dumps(payload, indent=1))

    def html_table(table_rows):
        head = "".join(f"<th>{esc(c)}</th>" for c in table_rows[0])
        body = "".join("<tr>" + "".join(f"<td>{esc(c)}</td>" for c in row) + "</tr>" for row in table_rows[1:])
        return f"<table><tr>{head}</tr>{body}</table>"

    links = "".join(f'<li><a href="seed-{seed}/compare.html">seed {seed}</a>: '
                    + ", ".join(f"<code>{esc(r['config'])}</code>" for r in p["runs"]) + "</li>" for seed, p in pairs)
    image = f'<h2>Every seed</h2><img alt="every seed" src="{_inline(figure)}">' if summary else ""
    text = f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>sp-compare: baseline vs SP over {len(pairs)} seeds</title>
<style>body{{font-family:sans-serif;max-width:1200px;margin:2em auto;padding:0 1em}}table{{border-collapse:collapse}}
td,th{{border:1px solid #ccc;padding:.3em .6em;text-align:right}}td:first-child,th:first-child{{text-align:left}}
img{{max-width:100%}}</style></head>
<body><h1>sp-compare: baseline vs SP over {len(pairs)} seeds</h1>
<h2>Paired by seed</h2>{html_table(rows)}
<p>Differences are SP minus baseline, seed by seed; the interval is a 95% Student t interval over the seed pairs. A verdict
says better or worse only when the interval excludes 0.</p>
{image}
<h2>Per seed</h2>{html_table(seed_rows)}
<ul>{links}</ul>
</body></html>
"""
    (out / "compare.html").write_text(text)
    print()
    print_table(rows)
    print()
    print_table(seed_rows)
    print(f"wrote {out / 'compare.html'}, {out / 'compare.json'}" + (f", {figure}" if summary else ""))
