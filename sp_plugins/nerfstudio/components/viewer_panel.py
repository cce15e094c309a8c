"""SP in nerfstudio's viewer: a panel on every model that trains with SP, and a render of the field
as the optimizer sees it.

nerfstudio's viewer turns every ``ViewerElement`` reachable from the pipeline's modules into a
control (``nerfstudio.viewer.utils.parse_object``), in a folder named by the attribute path. Our
models hold one :class:`SPPanel` (``model.stochastic_preconditioning``, a module without parameters
or buffers, so checkpoints are unchanged): alpha now, the schedule's progress and end, the settings
in force, and one control, **render**: the plain field (the default, what evaluation sees) or the
field SP trains, averaged over ``draws`` perturbations at the current alpha, so the user sees the
blur the optimizer fits and watches it sharpen as alpha anneals.

The control acts on the viewer's renders only: :func:`in_viewer_render` is true in nerfstudio's
render thread (``RenderStateMachine``) and nowhere else, so ``ns-eval``, ``ns-render``, evaluation
inside training and checkpoints are what they were, whatever the control says. The draws come from
a generator of their own (:meth:`~sp_plugins.core.StochasticPreconditioner.preview`), so the
training noise stream is untouched; the render holds nerfstudio's train lock, as every viewer
render does.
"""

from __future__ import annotations

import functools
import sys
import threading
from typing import Any, Callable, Dict, Optional

from torch import nn

from sp_plugins.core import StochasticPreconditioner
from sp_plugins.core.preconditioner import mean_of_calls

PLAIN = "plain field"
SP_VIEW = "field SP trains"
RENDER_MODES = [PLAIN, SP_VIEW]
DEFAULT_DRAWS = 4
UPDATE_EVERY = 10
"""Training steps between two refreshes of the panel's readouts (each is one message to the page)."""


def in_viewer_render() -> bool:
    """True in the thread of nerfstudio's viewer that renders frames (and only there)."""
    module = sys.modules.get("nerfstudio.viewer.render_state_machine")
    return module is not None and isinstance(threading.current_thread(), module.RenderStateMachine)


def alpha_text(sp: StochasticPreconditioner) -> str:
    """Alpha now, in scene units (4 significant digits)."""
    return f"{sp.alpha:.4g}"


def settings_text(sp: StochasticPreconditioner) -> str:
    """The settings in force, one line."""
    c = sp.config
    grid = f"alpha grid {c.alpha_grid_resolution}^3 ({c.alpha_grid_mode})" if c.alpha_grid else "global alpha"
    draws = f"{c.num_samples} draws per query" if c.num_samples > 1 else "1 draw per query"
    return f"{c.noise} noise, boundary {c.boundary}, {draws}, {grid}"


def schedule_text(sp: StochasticPreconditioner) -> str:
    """Where the schedule stands: the step, the step alpha reaches 0 at, and the way gone."""
    (step, total), schedule = sp.progress, sp.schedule  # Python mirrors: no device read
    if total < 0 or schedule is None:
        return f"{sp.config.schedule} from alpha0 {sp.config.alpha0:g}; the run's length is not known yet"
    end = schedule.end_step
    if end is None:
        return f"{sp.config.schedule}: alpha {sp.alpha:.3g} at step {step} (constant: on for the whole run)"
    gone = min(1.0, step / end) if end > 0 else 1.0
    state = "done: SP is off" if sp.alpha == 0 else f"{gone:.0%} of the way"
    return f"step {step} of {total}; alpha reaches 0 at step {end} ({state})"


@functools.lru_cache(maxsize=None)
def _readout_class() -> type:
    """A disabled text readout that reads its value again when the viewer installs it (made once, on
    first use: nerfstudio's viewer elements import viser, which a run without a panel never needs)."""
    from nerfstudio.viewer.viewer_elements import ViewerText

    class Readout(ViewerText):
        def __init__(self, name: str, read: Callable[[], str], hint: Optional[str] = None) -> None:
            super().__init__(name, read(), disabled=True, hint=hint)
            self._read = read

        def install(self, viser_server: Any) -> None:
            self.value = self._read()  # stored only: there is no GUI handle yet
            super().install(viser_server)

    return Readout


class SPPanel(nn.Module):
    """The viewer's SP panel of one model (no parameters or buffers: checkpoints are unchanged).

    Attribute names order the controls (the viewer sorts them by name); labels are what the user reads."""

    def __init__(self, sp: StochasticPreconditioner) -> None:
        super().__init__()
        from nerfstudio.viewer.viewer_elements import ViewerDropdown, ViewerSlider, ViewerText

        self._sp_ref = [sp]  # not a submodule: the model owns (and checkpoints) the preconditioner
        # the readouts take their values again when the viewer installs them: ns-viewer loads the
        # checkpoint (its step, its alpha) after the model, and so this panel, was built
        # alpha as text: viser's number input infers its precision from the first value (0 before the
        # run's length is known) and would show 0.003 as 0
        Readout = _readout_class()
        self.e1_alpha = Readout("alpha now", lambda: alpha_text(sp), hint="the noise's standard deviation per axis, in scene units")
        self.e2_schedule = Readout("schedule", lambda: schedule_text(sp))
        self.e3_settings = ViewerText("settings", settings_text(sp), disabled=True)
        self.e4_render = ViewerDropdown("render", PLAIN, RENDER_MODES,
                                        hint="the plain field (what evaluation sees) or the field SP trains: the mean of "
                                             "'draws' perturbed renders at the current alpha (viewer only)")
        self.e5_draws = ViewerSlider("draws", DEFAULT_DRAWS, 1, 16, step=1, hint="perturbed renders averaged per frame")

    @property
    def sp(self) -> StochasticPreconditioner:
        return self._sp_ref[0]

    def refresh(self) -> None:
        """Push alpha, the schedule's progress to the page (a no-op before a viewer shows them)."""
        self.e1_alpha.value = alpha_text(self.sp)
        self.e2_schedule.value = schedule_text(self.sp)

    def shows_sp(self) -> bool:
        return self.e4_render.value == SP_VIEW

    def render(self, render_once: Callable[[], Dict[str, Any]]) -> Dict[str, Any]:
        """``render_once()`` (a viewer frame), as the panel's control asks: plain, or the mean of
        ``draws`` renders with the fields perturbed at the current alpha (private noise, fixed seed:
        a still camera shows a still image)."""
        if not (self.shows_sp() and self.sp.scheduled and in_viewer_render()):
            return render_once()
        with self.sp.preview(seed=0):
            return mean_of_calls(render_once, max(1, int(self.e5_draws.value)))


def update_callback(panel: SPPanel) -> Callable[[int], None]:
    """After a training iteration: refresh the readouts every :data:`UPDATE_EVERY` steps, and at the
    step alpha reaches 0."""
    last = {"alpha": None}

    def update(step: int) -> None:
        alpha = panel.sp.alpha
        if step % UPDATE_EVERY == 0 or (alpha == 0.0 and last["alpha"] != 0.0):
            panel.refresh()
        last["alpha"] = alpha

    return update
