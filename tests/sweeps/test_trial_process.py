"""A trial's process: it runs at the niceness the sweep asks for (Ray's workers run at 15)."""

import os
import sys

import pytest

from sp_plugins.sweeps.trial import _run

PRINT_NICENESS = "import os; print(os.getpriority(os.PRIO_PROCESS, 0))"


@pytest.mark.skipif(not hasattr(os, "getpriority"), reason="no process priorities on this platform")
@pytest.mark.parametrize("offset", [None, 3])
def test_trial_runs_at_the_requested_niceness(tmp_path, offset):
    own = os.getpriority(os.PRIO_PROCESS, 0)
    wanted = None if offset is None else min(own + offset, 19)  # raising it needs no privilege
    code, _, _ = _run([sys.executable, "-c", PRINT_NICENESS], str(tmp_path), dict(os.environ), tmp_path, 60, "", wanted)
    assert code == 0
    assert int((tmp_path / "stdout.log").read_text()) == (own if wanted is None else wanted)
