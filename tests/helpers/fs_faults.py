"""File-system faults for the bad-input tests: a read-only folder (also for root), and what "nothing
written or overwritten" compares. (A full disk is simulated with ``RLIMIT_FSIZE``: see
``tests/helpers/forkserver.py``'s ``fsize``.)"""

from __future__ import annotations

import os
import shutil
import stat
import subprocess
from pathlib import Path
from typing import Dict


def listing(root: Path) -> Dict[str, int]:
    """Every path under ``root`` with its mtime (ns); empty when ``root`` does not exist."""
    if not root.exists():
        return {}
    return {str(p.relative_to(root)): p.stat().st_mtime_ns for p in sorted(root.rglob("*"))}


def make_read_only(folder: Path) -> bool:
    """Make ``folder`` (created if needed) read-only for this user: its mode for a normal user; root
    ignores modes, so the immutable attribute there (``chattr +i``, where the tool and the file
    system have it). False when neither works (the caller skips)."""
    folder.mkdir(parents=True, exist_ok=True)
    if os.geteuid() != 0:
        folder.chmod(stat.S_IRUSR | stat.S_IXUSR)
        return True
    if shutil.which("chattr") and subprocess.run(["chattr", "+i", str(folder)], capture_output=True).returncode == 0:
        probe = folder / "probe"
        try:
            probe.touch()
        except OSError:
            return True
        probe.unlink()
        subprocess.run(["chattr", "-i", str(folder)], capture_output=True)
    return False


def undo_read_only(folder: Path) -> None:
    if os.geteuid() == 0:
        subprocess.run(["chattr", "-i", str(folder)], capture_output=True)
    else:
        folder.chmod(stat.S_IRWXU)
