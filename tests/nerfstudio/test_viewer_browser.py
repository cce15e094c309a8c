"""nerfstudio's web viewer in a real browser: headless Chromium, driven by Playwright from the
package index with the system's ``chromium`` (run.sh installs it; no browser download), against the viewer
of an ``ns-train sp-relu-field`` run while it trains and against ``ns-viewer --load-config`` on that run
once it finished. The commands are typed as a user would; the only flag beyond CPU budget and size is
``--viewer.quit-on-train-completion True``. Everything the test sees it reads from the page: the
connection, the stats readout (``Step: N``, ``Resolution: WxHpx``), the pause / resume buttons and the
rendered frame's pixels (a screenshot of the viewport).

``SP_VIEWER_SCREENSHOT=docs/viewer_sp.png`` also saves the training run's screenshot there (the README's)."""

from __future__ import annotations

import io
import os
import re
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from tests.helpers.ns_commands import ENV, command
from tests.helpers.viewer import QUIT_ON_COMPLETION, Viewer, serving, tail

try:
    from playwright.sync_api import TimeoutError as PlaywrightTimeout
except ImportError:  # the tests skip (or fail under CI=true) in their fixture, naming it
    PlaywrightTimeout = TimeoutError

from tests.helpers.browser import CHROMIUM, CHROMIUM_ARGS, browser_or_skip

STEPS = 200
CHANGED = 0.25
"""A frame change (mean absolute, grey levels) that is the SP view's: two renders of the plain field differ by 0.0."""
PAUSE_AFTER = 30  # trainer's logged step; the run is 200 steps, about 10 a second on an idle core
SP_END = 1.0  # SP on for every step but the last (sp_plugins.core.AlphaSchedule.resolve)
TINY = [
    "--machine.device-type", "cpu", "--max-num-iterations", str(STEPS), "--pipeline.model.resolution", "33",
    "--pipeline.model.num-samples", "32", "--pipeline.datamanager.train-num-rays-per-batch", "1024",
    "--pipeline.model.sp.end", str(SP_END),
]
ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")
READOUT = re.compile(r"Step: (\d+)\s*Resolution: (\d+)x(\d+)px")


_browser_or_skip = browser_or_skip


# -- the viewer processes (started by tests/helpers/viewer.py, as a user types them) ----------------
def ready(viewer: Viewer, line: str, timeout: float = 300) -> str:
    """The viewer's address once the command printed ``line``: ns-train's banner ("Viewer running locally
    at", printed when training starts) or ns-viewer's "disabled local writer" (after its viewer is built).
    A page used before that (measured 2026-12-05: "Max res" set and "Hide Train Cams" clicked between
    viser's table and the banner) was never rendered to, staying at "Step: 0", "Resolution: 0x0px", and
    the click raised in the host (``Viewer.camera_handles`` does not exist yet); a page that only
    connects early renders."""
    wait_for(lambda: line in viewer.output() or viewer.proc.poll() is not None, timeout, repr(line))
    assert viewer.proc.poll() is None, f"exited ({viewer.proc.returncode}) before {line!r}\n{tail(viewer.log)}"
    return viewer.url


def logged_steps(viewer: Viewer) -> list:
    """The steps of the trainer's own progress lines (``N (x.xx%)``, every 10 steps)."""
    return [int(m) for m in re.findall(r"^\s*(\d+) \(\d+\.\d+%\)", ANSI.sub("", viewer.output()), flags=re.M)]


def steady(viewer: Viewer, seconds: float) -> bool:
    """Whether the trainer logged no new step during ``seconds``."""
    before = logged_steps(viewer)
    time.sleep(seconds)
    return logged_steps(viewer) == before


def wait_for(check, timeout: float, what: str, why=lambda: "", every: float = 0.25):
    """Poll ``check()`` until it returns something truthy; fail naming ``what``, the last value and ``why()``."""
    deadline, value = time.monotonic() + timeout, None
    while time.monotonic() < deadline:
        value = check()
        if value:
            return value
        time.sleep(every)
    raise AssertionError(f"{what}: not within {timeout} s (last reading {value!r})\n{why()}")


def evidence(page, run, path: Path):
    """For a failure message: the page's text, a screenshot and the process's output."""
    def why():
        page.screenshot(path=str(path))
        text = " | ".join(page.inner_text("body").split("\n")[:12])
        return f"page: {text}\nscreenshot: {path}\n{' '.join(map(str, run.proc.args))}\n{tail(run.log)}"
    return why


# -- the page -------------------------------------------------------------------------------------
def open_viewer(browser, url: str):
    page = browser.new_page(viewport={"width": 720, "height": 480})
    page.goto(url, wait_until="domcontentloaded", timeout=90_000)
    page.get_by_text("Connected", exact=True).wait_for(timeout=90_000)
    return page


def readout(page):
    """(step, width, height) from the viewer's stats panel, None before it is drawn."""
    found = READOUT.search(page.inner_text("body"))
    return tuple(int(g) for g in found.groups()) if found else None


def prepare_view(page):
    """What a user on a CPU does first: the smallest render size (so frames keep up with training),
    the training cameras hidden (their thumbnails are the data, not our model), and the camera pulled
    back out of the scene box (viser starts close to the origin)."""
    label = page.locator("label", has_text=re.compile(r"^Max res$"))
    # the slider's row: the label, the slider, and the number box beside it
    max_res = label.locator("xpath=ancestor::div[.//input[@type='text']][1]//input[@type='text']")
    max_res.fill("64")
    max_res.press("Enter")
    # a click before the host drew the cameras raises in its callback (the button stays): click again
    for attempt in range(3):
        page.get_by_role("button", name="Hide Train Cams").click()
        try:
            page.get_by_role("button", name="Show Train Cams").wait_for(timeout=10_000)
            break
        except PlaywrightTimeout:
            assert attempt < 2, "Hide Train Cams had no effect"
    box = viewport_box(page)
    page.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    for _ in range(8):
        page.mouse.wheel(0, 300)
        time.sleep(0.1)


def viewport_box(page) -> dict:
    """The part of the 3D canvas left of the control panel."""
    canvas = page.locator("canvas").first.bounding_box()
    panel_x = page.get_by_role("tab", name="Control").bounding_box()["x"] - 20
    return {"x": canvas["x"], "y": canvas["y"], "width": panel_x - canvas["x"], "height": canvas["height"]}


def frame_stats(page) -> dict:
    """Pixel statistics of the viewport (the axes gizmo's corner left out): the spread of grey levels
    and the share of coloured pixels (Spot is orange and violet; the viewer's own scene is white and grey)."""
    from PIL import Image

    png = page.screenshot(clip=viewport_box(page))
    rgb = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(np.float32)
    rgb[-90:, :90] = np.nan
    flat = rgb.reshape(-1, 3)
    flat = flat[~np.isnan(flat).any(1)]
    chroma = flat.max(1) - flat.min(1)
    return {"grey_std": round(float(flat.mean(1).std()), 1), "coloured": round(float((chroma > 60).mean()), 4),
            "mean_rgb": [round(float(c), 1) for c in flat.mean(0)]}


def shows_the_object(stats: dict) -> bool:
    return stats["grey_std"] > 15 and stats["coloured"] > 0.01


def sp_schedule(folder: Path):
    """The alpha schedule of the run, from the SP settings its ``config.yml`` saved (read as text: loading
    it would import nerfstudio into the test process)."""
    from sp_plugins.core import AlphaSchedule

    (config,) = folder.glob("outputs/**/config.yml")
    block = config.read_text().split("sp: !!python/object:sp_plugins.core.config.SPConfig", 1)[1]
    block = re.split(r"\n(?!      )", block.lstrip("\n"), maxsplit=1)[0]  # its lines, indented under sp:
    sp = dict(re.findall(r"^      (\w+): (.*)$", block, flags=re.M))
    assert sp["enabled"] == "true" and sp["relative_to_diagonal"] == "false", sp
    return AlphaSchedule.resolve(sp["schedule"], float(sp["alpha0"]), end=float(sp["end"]), total_steps=STEPS,
                                 final_ratio=float(sp["final_ratio"]))


def viewport_pixels(page) -> np.ndarray:
    """The viewport's pixels (RGB, float), the axes gizmo's corner left out."""
    from PIL import Image

    rgb = np.asarray(Image.open(io.BytesIO(page.screenshot(clip=viewport_box(page)))).convert("RGB")).astype(np.float32)
    rgb[-90:, :90] = 0.0
    return rgb


def frame_change(page, reference: np.ndarray) -> float:
    """Mean absolute difference (grey levels) of the viewport now from ``reference``."""
    now = viewport_pixels(page)
    return float(np.abs(now - reference).mean()) if now.shape == reference.shape else float("inf")


def settled(page, timeout: float = 90, every: float = 1.0) -> np.ndarray:
    """The viewport once two screenshots ``every`` s apart agree (the viewer sends a low-resolution frame
    first, then the full one)."""
    deadline, last = time.monotonic() + timeout, viewport_pixels(page)
    while time.monotonic() < deadline:
        time.sleep(every)
        now = viewport_pixels(page)
        if now.shape == last.shape and float(np.abs(now - last).mean()) < 0.05:
            return now
        last = now
    raise AssertionError(f"the viewport did not settle within {timeout} s")


def control(page, label: str):
    """The input in the row of the viewer control labelled ``label`` (viser's text inputs do not carry
    the id their label names, so the row, not the label's ``for``, finds them)."""
    row = page.locator("label", has_text=re.compile(rf"^{re.escape(label)}$")).locator(
        "xpath=ancestor::div[contains(@class, 'mantine-Flex-root')][1]")
    return row.locator("input:not([type='hidden'])").first


def sp_panel(page) -> dict:
    """The SP panel's readouts, read from the page."""
    return {"alpha": float(control(page, "alpha now").input_value()), "schedule": control(page, "schedule").input_value(),
            "settings": control(page, "settings").input_value(), "render": control(page, "render").input_value()}


def choose_render(page, mode: str) -> None:
    control(page, "render").click()
    page.get_by_role("option", name=mode).click()
    wait_for(lambda: control(page, "render").input_value() == mode, 20, f"render set to {mode!r}")


def click(page, name: str):
    page.get_by_role("button", name=name).click()
    page.get_by_role("button", name={"Pause Training": "Resume Training", "Resume Training": "Pause Training"}[name]).wait_for()


# -- fixtures -------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def browser():
    sync_playwright = _browser_or_skip()
    with sync_playwright() as p:
        chromium = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)
        yield chromium
        chromium.close()


@pytest.fixture(scope="module")
def spot(tmp_path_factory) -> Path:
    """The bundled Spot mesh as a tiny Blender scene (8 views of 32x32; what ``sp-scene spot`` writes, smaller)."""
    from sp_plugins.data import make_tiny_scene

    return make_tiny_scene(tmp_path_factory.mktemp("viewer") / "spot", mesh="spot", layouts=("blender",)).root


@pytest.fixture(scope="module")
def training(browser, spot):
    """``ns-train sp-relu-field`` under nerfstudio's default front end, the web viewer, run in the folder
    above the scene (its outputs/ there, as a user's)."""
    args = [command("ns-train"), "sp-relu-field", *TINY, *QUIT_ON_COMPLETION, "--output-dir", "outputs",
            "blender-data", "--data", spot / "blender"]
    with serving(args, spot.parent / "ns-train.log", cwd=spot.parent) as run:
        yield run


@pytest.fixture(scope="module")
def finished(training, spot) -> Path:
    """The training run, finished: its ``config.yml``, relative to the folder it ran in."""
    rc = training.proc.wait(timeout=600)
    assert rc == 0 and "Training Finished" in training.output(), tail(training.log)
    (config,) = spot.parent.glob("outputs/**/config.yml")
    return config.relative_to(spot.parent)


def test_the_viewer_of_a_training_sp_run(training, browser, spot, tmp_path):
    url = ready(training, "Viewer running locally at")
    t0 = time.monotonic()
    page = open_viewer(browser, url)
    why = evidence(page, training, tmp_path / "failed.png")
    readings = {"url": url}

    def at(key, value):
        readings[key] = (value, f"{time.monotonic() - t0:.1f} s")
        return value

    # pause first, from the page: the run cannot end while the view is set up, and the trainer stops.
    # Not before the field has a shape: a frame of a field a few steps old is nearly all background, and
    # SP's change to it can stay under the threshold below (on a loaded machine the page is ready earlier
    # in the run than on an idle one).
    wait_for(lambda: (logged_steps(training) or [0])[-1] >= PAUSE_AFTER, 120, f"step {PAUSE_AFTER} in the trainer's log", why)
    before = at("trainer's log before pausing", logged_steps(training)[-1:])
    click(page, "Pause Training")
    try:
        _while_paused(page, training, spot, tmp_path, why, at, before, readings)
    finally:  # a failure while paused must not leave the run paused for the tests after this one
        if not page.is_closed() and page.get_by_role("button", name="Resume Training").count():
            page.get_by_role("button", name="Resume Training").click()


def _while_paused(page, training, spot, tmp_path, why, at, before, readings):
    # the step in flight when the button was pressed finishes: the trainer's log then holds still
    wait_for(lambda: steady(training, 2.0), 60, "the trainer's log to hold still after pausing", why)
    paused = at("paused (page, trainer's log)", ((readout(page) or (0,))[0], logged_steps(training)[-1]))
    paused_at = time.monotonic()
    # a frame of our model, rendered while paused: the resolution readout is set by each render
    prepare_view(page)
    first = at("first frame", wait_for(lambda: (r := readout(page)) and r[1] > 0 and r, 90, "a rendered frame", why))
    at("first frame's pixels", frame_stats(page))
    # the SP panel: alpha above 0 while SP is on, and its render control changes the frame
    panel = at("SP panel", sp_panel(page))
    assert panel["alpha"] > 0 and panel["render"] == "plain field" and "boundary reflect" in panel["settings"], (panel, why())
    plain = settled(page)
    shots = Path(os.environ.get("SP_VIEWER_PANEL_SHOTS", tmp_path))  # the docs' pictures of both states, panel shown
    control(page, "draws").scroll_into_view_if_needed()
    page.screenshot(path=str(shots / "viewer_panel_plain.png"))
    choose_render(page, "field SP trains")
    # a still camera renders a still frame (the SP view draws its noise from a fixed seed): any change above the
    # screenshots' own noise (0.0 between two plain frames) is the SP view's
    seen = []

    def changed():
        seen.append(round(frame_change(page, plain), 3))
        return seen[-1] > CHANGED and seen[-1]

    try:
        blurred = wait_for(changed, 45, "the frame to change", why)
    except AssertionError:  # choose it again: the control's change asks the viewer for one render
        choose_render(page, "plain field")
        choose_render(page, "field SP trains")
        blurred = wait_for(changed, 45, f"the frame to change, the control chosen twice (changes seen: {seen[-8:]})", why)
    blurred_change = at("frame change, field SP trains vs plain (grey levels)", blurred)
    settled(page)
    page.screenshot(path=str(shots / "viewer_panel_sp.png"))
    choose_render(page, "plain field")
    back = at("frame change, plain again vs plain (grey levels)",
              wait_for(lambda: (d := frame_change(page, plain)) < 0.5 and d + 1e-9, 90, "the plain frame back", why))
    assert blurred_change > 2 * back, (blurred_change, back)
    time.sleep(max(0.0, paused_at + 5 - time.monotonic()))  # at least 5 s paused (10 steps take about 1 s)
    assert (first[0], logged_steps(training)[-1]) == paused, f"training went on while paused\n{why()}"
    # resume: the step shown advances, while SP is on (alpha > 0 at every step shown)
    click(page, "Resume Training")
    seen = [first[0]]
    for _ in range(3):
        seen.append(wait_for(lambda: (r := readout(page)) and r[0] > seen[-1] and r[0], 90, f"a step past {seen[-1]}", why))
    at("steps shown after resuming", seen)
    # and the object shows up in the frames rendered during training
    at("frame", wait_for(lambda: (s := frame_stats(page)) and shows_the_object(s) and s, 90,
                         "a frame that shows the object (grey spread > 15, coloured pixels > 1%)", why))
    seen.append(at("step of that frame", readout(page)[0]))
    schedule = sp_schedule(spot.parent)
    assert all(schedule(s) > 0 for s in seen), (seen, schedule, why())
    assert logged_steps(training)[-1] > paused[1] >= (before or [0])[0], why()
    shot = tmp_path / "viewer_sp.png"
    page.screenshot(path=str(shot))
    if os.environ.get("SP_VIEWER_SCREENSHOT"):  # the README's picture: later in the run (SP still on), small
        from PIL import Image

        late = at("README picture at step", wait_for(lambda: (r := readout(page)) and r[0] >= 0.7 * STEPS and r[0], 120,
                                                     "a step 70% into the run", why))
        assert schedule(late) > 0, (late, schedule)
        page.screenshot(path=str(shot))
        picture = Image.open(shot).convert("RGB").convert("P", palette=Image.Palette.ADAPTIVE, colors=256)
        picture.save(os.environ["SP_VIEWER_SCREENSHOT"], optimize=True)
    page.close()
    print("viewer readings:", readings)


def test_ns_viewer_serves_the_finished_run(finished, browser, spot, tmp_path):
    # from the folder it trained in, as the user typed ns-train (its config names outputs/... from there)
    args = [command("ns-viewer"), "--load-config", finished]
    with serving(args, tmp_path / "ns-viewer.log", cwd=spot.parent) as viewer:
        url = ready(viewer, "disabled local writer")
        page = open_viewer(browser, url)
        why = evidence(page, viewer, tmp_path / "failed.png")
        prepare_view(page)
        first = wait_for(lambda: (r := readout(page)) and r[1] > 0 and r, 90, "a rendered frame", why)
        stats = wait_for(lambda: (s := frame_stats(page)) and shows_the_object(s) and s, 60,
                         "a frame that shows the object (grey spread > 15, coloured pixels > 1%)", why)
        # the SP panel of the finished run: alpha 0 after the schedule's end, and the render
        # control changes nothing (the field SP trains is the plain field then)
        panel = sp_panel(page)
        assert panel["alpha"] == 0.0 and "SP is off" in panel["schedule"], (panel, why())
        plain = settled(page)
        choose_render(page, "field SP trains")
        time.sleep(3)
        assert frame_change(page, settled(page)) < 0.5 and frame_change(page, plain) < 0.5, why()
        page.close()
        print("ns-viewer readings:", {"url": url, "first frame": first, "frame": stats})
        assert viewer.proc.poll() is None, tail(viewer.log)


def test_a_baseline_run_shows_no_sp_panel(browser, spot, tmp_path):
    """The same page on a run with SP off (``relu-field-flat``, our baseline of ``sp-relu-field``): the
    control panel is there, the SP panel is not."""
    out = tmp_path / "outputs"
    train = [command("ns-train"), "relu-field-flat", *TINY[:2], "--max-num-iterations", "5", *TINY[4:8], "--vis", "tensorboard",
             "--output-dir", out, "blender-data", "--data", spot / "blender"]
    proc = subprocess.run([str(a) for a in train], env=ENV, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    (config,) = out.glob("**/config.yml")
    with serving([command("ns-viewer"), "--load-config", config], tmp_path / "ns-viewer.log") as viewer:
        page = open_viewer(browser, ready(viewer, "disabled local writer"))
        page.get_by_role("button", name="Reset Up Direction").wait_for(timeout=60_000)  # the control panel is drawn
        text = page.inner_text("body")
        page.close()
    assert "Reset Up Direction" in text and "stochastic_preconditioning" not in text and "alpha now" not in text, text[-800:]
