"""The viewer's SP panel in a real browser on the issue's two runs, and a training step's time with
and without the viewer connected.

    python -m bench.viewer_panel                 # both parts; about 10 minutes on 2 CPU cores
    python -m bench.viewer_panel --part panel    # or --part timing

``panel``: ``ns-train sp-neus-hashgrid`` (sdfstudio-data) and ``sp-train nerfacto`` (blender-data) on a tiny
``sp-scene``-like scene, each under nerfstudio's default viewer, SP ending half-way on a linear schedule
(the presets' alpha0). Headless Chromium (the suite's browser helpers) pauses the run at step 20 and
reads the panel (alpha > 0), switches the render
control and measures how much the frame changes (plain -> field SP trains -> plain), resumes, waits past
the schedule's end and does it again (alpha 0: no change). Screenshots of both states go to
``bench/results/viewer_panel/``.

``timing``: ``ns-train sp-relu-field`` for 300 steps under the default viewer three ways: no browser,
a browser connected (the plain field rendered while it trains), a browser with the panel on "field SP
trains". The time per step is taken from the trainer's own progress lines between steps 100 and 300.

Writes ``bench/results/viewer_panel/results.json`` and ``results.md`` after each part.
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import sys
import time
from pathlib import Path
from typing import Dict, List

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.helpers.browser import CHROMIUM, CHROMIUM_ARGS  # noqa: E402
from tests.helpers.ns_commands import NERFACTO_FLAGS, SDF_FLAGS, command  # noqa: E402
from tests.helpers.viewer import QUIT_ON_COMPLETION, serving, tail  # noqa: E402
from tests.nerfstudio import test_viewer_browser as vb  # noqa: E402

OUT = ROOT / "bench" / "results" / "viewer_panel"
WORK = ROOT / "bench" / "out" / "viewer_panel"
STEPS = 120
EARLY = 20
"""The step the run is paused at first: past the untrained start (a flat field looks the same blurred)."""
CPU = ["--machine.device-type", "cpu", "--max-num-iterations", str(STEPS), "--pipeline.model.sp.end", "0.5",
       "--pipeline.model.sp.schedule", "linear",
       "--pipeline.datamanager.train-num-rays-per-batch", "256", "--steps-per-save", str(STEPS)]


def scene() -> Path:
    from sp_plugins.data import make_tiny_scene

    return make_tiny_scene(WORK / "spot", mesh="spot", layouts=("blender", "sdfstudio"), overwrite=True).root


def runs(root: Path) -> Dict[str, List[str]]:
    return {
        "ns-train sp-neus-hashgrid": [command("ns-train"), "sp-neus-hashgrid", *CPU, *SDF_FLAGS, "--pipeline.model.sdf-field.num-layers", "2",
                                      *QUIT_ON_COMPLETION, "sdfstudio-data", "--data", str(root / "sdfstudio")],
        "sp-train nerfacto": [command("sp-train"), "nerfacto", *CPU, *NERFACTO_FLAGS, *QUIT_ON_COMPLETION,
                              "blender-data", "--data", str(root / "blender")],
    }


def panel_part(browser, results: dict) -> None:
    root = scene()
    for name, args in runs(root).items():
        slug = re.sub(r"\W+", "_", name)
        reading: Dict[str, object] = {"command": " ".join(Path(a).name if i == 0 else str(a) for i, a in enumerate(args))}
        with serving(args, WORK / f"{slug}.log", cwd=root.parent, timeout=600) as run:
            url = vb.ready(run, "Viewer running locally at", timeout=600)
            page = vb.open_viewer(browser, url)
            why = vb.evidence(page, run, WORK / f"{slug}_failed.png")
            vb.wait_for(lambda: (s := vb.logged_steps(run)) and s[-1] >= EARLY and s, 600, f"step {EARLY}", why)
            vb.click(page, "Pause Training")
            vb.wait_for(lambda: vb.steady(run, 2.0), 120, "the trainer to hold still", why)
            vb.prepare_view(page)
            vb.wait_for(lambda: (r := vb.readout(page)) and r[1] > 0 and r, 120, "a rendered frame", why)
            reading["early"] = early = toggle(page, why, OUT / f"{slug}_early")
            assert early["panel"]["alpha"] > 0, early
            vb.click(page, "Resume Training")
            end = STEPS // 2
            vb.wait_for(lambda: (s := vb.logged_steps(run)) and s[-1] >= end + 10 and s, 600, f"step {end + 10}", why)
            vb.click(page, "Pause Training")
            vb.wait_for(lambda: vb.steady(run, 2.0), 120, "the trainer to hold still", why)
            vb.wait_for(lambda: float(vb.control(page, "alpha now").input_value()) == 0.0, 60, "alpha 0 in the panel", why)
            reading["after the schedule's end"] = toggle(page, why, OUT / f"{slug}_late")
            vb.click(page, "Resume Training")
            rc = run.proc.wait(timeout=900)
            assert rc == 0, tail(run.log)
            page.close()
        results.setdefault("panel", {})[name] = reading
        write(results)


def toggle(page, why, shots: Path) -> dict:
    """Panel readings, then the frame change plain -> field SP trains -> plain (mean abs grey levels)."""
    panel = vb.sp_panel(page)
    time.sleep(3)
    plain = vb.settled(page, every=2.0)
    vb.control(page, "draws").scroll_into_view_if_needed()
    page.screenshot(path=f"{shots}_plain.png")
    vb.choose_render(page, "field SP trains")
    time.sleep(3)
    shown = vb.settled(page, every=2.0)
    page.screenshot(path=f"{shots}_sp.png")
    change = float(abs(shown - plain).mean()) if shown.shape == plain.shape else float("inf")
    vb.choose_render(page, "plain field")
    time.sleep(3)
    again = vb.settled(page, every=2.0)
    back = float(abs(again - plain).mean()) if again.shape == plain.shape else float("inf")
    return {"panel": panel, "change_sp_vs_plain": round(change, 3), "change_plain_again": round(back, 3)}


TIMING_STEPS = 300
TIMING = ["--machine.device-type", "cpu", "--max-num-iterations", str(TIMING_STEPS), "--pipeline.model.resolution", "33",
          "--pipeline.model.num-samples", "32", "--pipeline.datamanager.train-num-rays-per-batch", "1024",
          "--pipeline.model.sp.end", "1.0", "--steps-per-save", str(TIMING_STEPS)]


def step_times(log_text: str) -> Dict[int, float]:
    """The trainer's progress lines: step -> its time per iteration (seconds)."""
    clean = vb.ANSI.sub("", log_text)
    out = {}
    for step, seconds, ms in re.findall(r"^\s*(\d+) \(\d+\.\d+%\)\s+(?:(\d+) s, )?([\d.]+) ms", clean, flags=re.M):
        out[int(step)] = int(seconds or 0) + float(ms) / 1000.0
    return out


def timing_part(browser, results: dict) -> None:
    root = scene()
    table = {}
    for how in ("no browser", "browser, plain field", "browser, field SP trains"):
        args = [command("ns-train"), "sp-relu-field", *TIMING, *QUIT_ON_COMPLETION, "blender-data", "--data", str(root / "blender")]
        log = WORK / f"timing_{re.sub(r'[^a-z]+', '_', how)}.log"
        with serving(args, log, cwd=root.parent, timeout=600) as run:
            vb.ready(run, "Viewer running locally at", timeout=600)
            page = None
            if how != "no browser":
                page = vb.open_viewer(browser, run.url)
                vb.prepare_view(page)
                if how.endswith("SP trains"):
                    vb.choose_render(page, "field SP trains")
            rc = run.proc.wait(timeout=1800)
            assert rc == 0, tail(run.log)
            text = run.output()
            if page is not None:
                page.close()
        times = {s: t for s, t in step_times(text).items() if 100 <= s <= TIMING_STEPS}
        table[how] = {"steps_read": len(times), "median_s_per_step": round(sorted(times.values())[len(times) // 2], 4) if times else None}
        results["timing"] = table
        write(results)


def write(results: dict) -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "results.json").write_text(json.dumps(results, indent=1))
    lines = ["# The viewer's SP panel", "", "`python -m bench.viewer_panel`; 2 CPU cores, no GPU.", ""]
    for name, r in results.get("panel", {}).items():
        lines += [f"## {name}", "", f"`{r['command']}`", "", "| when | alpha now | schedule | frame change, field SP trains vs plain | plain again |",
                  "|---|---:|---|---:|---:|"]
        for when in ("early", "after the schedule's end"):
            if when in r:
                e = r[when]
                lines.append(f"| {when} | {e['panel']['alpha']:g} | {e['panel']['schedule']} | {e['change_sp_vs_plain']} | {e['change_plain_again']} |")
        lines.append("")
    if "timing" in results:
        lines += ["## A training step with and without the viewer connected (`ns-train sp-relu-field`, steps 100-300)", "",
                  "| viewer | median s per step | steps read |", "|---|---:|---:|"]
        lines += [f"| {how} | {t['median_s_per_step']} | {t['steps_read']} |" for how, t in results["timing"].items()]
    (OUT / "results.md").write_text("\n".join(lines) + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--part", choices=["panel", "timing"], action="append")
    args = parser.parse_args()
    parts = args.part or ["panel", "timing"]
    from playwright.sync_api import sync_playwright

    WORK.mkdir(parents=True, exist_ok=True)
    results = json.loads((OUT / "results.json").read_text()) if (OUT / "results.json").exists() else {}
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)
        if "panel" in parts:
            panel_part(browser, results)
        if "timing" in parts:
            timing_part(browser, results)
        browser.close()
    print((OUT / "results.md").read_text())
    shutil.rmtree(WORK / "spot", ignore_errors=True)


if __name__ == "__main__":
    main()
