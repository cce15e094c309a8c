"""nerfstudio's web viewer in a subprocess, for tests: start a command that serves it (``ns-train``
under the default ``--vis viewer``, ``ns-viewer --load-config``), read the port viser bound from its
output, wait until that port serves the viser client page, stop it.

Shared by tests/nerfstudio/test_ns_viewer.py (``ns-viewer`` serves each method family's
finished run) and the headless-browser test (tests/nerfstudio/test_viewer_browser.py).

    with serving([command("ns-viewer"), "--load-config", config], tmp_path / "viewer.log") as viewer:
        assert "<title>Viser</title>" in viewer.page()      # viewer.url for a browser

    with forked_viewers(ns_server, {"sdf": [command("ns-viewer"), "--load-config", config]}, tmp_path) as viewers:
        ...                                                 # several at once, forked: no import each

The port comes from viser's own banner (``HTTP │ http://0.0.0.0:7007``), not from nerfstudio's
"Viewer running locally at" line: nerfstudio picks 7007 when it is free, else a random free port,
and viser moves to the next port when the bind fails; only viser's banner names the port it holds.
Parallel runs (pytest-xdist workers) therefore each get their own port.
"""

from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
import threading
import time
import urllib.error
import urllib.request
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, Iterator, Optional, Sequence

from tests.helpers.ns_commands import ENV

PORT_LINE = re.compile(r"HTTP\W+http://[^\s/:]+:(\d+)")
"""viser's banner row with the port it bound (the box characters between vary with the terminal)."""

CLIENT_MARKER = "<title>Viser</title>"
"""In the client page viser ships inside its package (``viser/client/build/index.html``)."""

QUIT_ON_COMPLETION = ("--viewer.quit-on-train-completion", "True")
"""The one flag a test adds to ``ns-train`` under the default viewer: without it the trainer keeps
serving after the last step, waiting for a user to close it."""


@dataclass
class Viewer:
    """A running viewer process: ``port`` is what viser bound, ``log`` its stdout and stderr."""

    proc: subprocess.Popen  # or a ForkedChild
    log: Path
    port: int

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def output(self) -> str:
        return self.log.read_text(errors="replace")

    def page(self, timeout: float = 60.0) -> str:
        """The client HTML served at :attr:`url` (retried until it answers or ``timeout``)."""
        return wait_for_page(self.port, timeout=timeout, proc=self.proc, log=self.log)

    def websocket_message(self, timeout: float = 30.0) -> bytes:
        """Open the viewer's websocket as the page does and return the first message the server
        sends (its persistent scene and GUI state, msgpack)."""
        from websockets.sync.client import connect

        with connect(f"ws://127.0.0.1:{self.port}", open_timeout=timeout, max_size=None) as ws:
            message = ws.recv(timeout=timeout)
        return message if isinstance(message, bytes) else message.encode()


def start(args: Sequence[str], log: Path, *, env: Optional[dict] = None, cwd: Optional[Path] = None) -> subprocess.Popen:
    """Start ``args`` with stdout and stderr into ``log`` (a file, so a chatty process never blocks on
    a full pipe)."""
    log = Path(log)
    log.parent.mkdir(parents=True, exist_ok=True)
    env = dict(ENV if env is None else env, PYTHONUNBUFFERED="1", COLUMNS="200")
    with open(log, "wb") as out:
        return subprocess.Popen([str(a) for a in args], stdout=out, stderr=subprocess.STDOUT, env=env, cwd=cwd)


def tail(log: Path, chars: int = 4000) -> str:
    try:
        return Path(log).read_text(errors="replace")[-chars:]
    except OSError:
        return "(no output)"


def wait_for_port(proc: subprocess.Popen, log: Path, timeout: float = 300.0) -> int:
    """The port from viser's banner in ``log``; fails with the output's tail if ``proc`` exits first."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        match = PORT_LINE.search(Path(log).read_text(errors="replace")) if Path(log).exists() else None
        if match:
            return int(match.group(1))
        if proc.poll() is not None:
            raise AssertionError(f"exited with {proc.returncode} before the viewer started:\n{tail(log)}")
        time.sleep(0.2)
    raise AssertionError(f"no viewer port in {timeout:.0f} s:\n{tail(log)}")


def wait_for_page(port: int, *, timeout: float = 60.0, proc: Optional[subprocess.Popen] = None,
                  log: Optional[Path] = None) -> str:
    """GET ``http://127.0.0.1:port/`` until it returns the viser client page; the page."""
    deadline = time.monotonic() + timeout
    last: object = None
    while time.monotonic() < deadline:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=10) as response:
                page = response.read().decode(errors="replace")
            if CLIENT_MARKER in page:
                return page
            last = f"a page without {CLIENT_MARKER!r}: {page[:200]!r}"
        except (urllib.error.URLError, ConnectionError, TimeoutError, OSError) as err:
            last = err
        if proc is not None and proc.poll() is not None:
            break
        time.sleep(0.3)
    raise AssertionError(f"port {port} did not serve the viser client ({last}):\n{tail(log) if log else ''}")


def stop(proc: subprocess.Popen, timeout: float = 20.0) -> Optional[int]:
    """Terminate ``proc`` (kill it if it does not exit in ``timeout``); its exit status."""
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=timeout)
    return proc.returncode


class ForkedChild:
    """A command forked by the test fork server (``tests/helpers/forkserver.py``, a case with a ``log``):
    what :class:`Viewer` needs of a process, from the pid the child wrote first in its log."""

    def __init__(self, pid: int) -> None:
        self.pid, self.returncode = pid, None

    def poll(self) -> Optional[int]:
        if self.returncode is None:
            try:
                os.kill(self.pid, 0)
            except ProcessLookupError:
                self.returncode = -1  # ended (its status is the fork server's result)
        return self.returncode


@contextlib.contextmanager
def forked_viewers(server, commands: Dict[str, Sequence[str]], folder: Path, *,
                   timeout: float = 300.0) -> Iterator[Dict[str, Viewer]]:
    """``name -> [console script, *args]`` forked together from the test fork ``server`` (no import per
    command), each until its viewer page is served; yields ``name -> Viewer``; stops them all on exit.
    ``server.run`` blocks until its children end, so it runs in a thread here; its results (exit
    statuses) are ``forked_viewers.results`` afterwards."""
    from tests.helpers.forkserver import CHILD_PID

    logs = {name: Path(folder) / f"{name.replace(' ', '-')}.log" for name in commands}
    cases = [{"name": name, "script": Path(str(args[0])).name, "args": [str(a) for a in args[1:]], "log": str(logs[name]),
              "timeout": timeout + 60} for name, args in commands.items()]
    results: dict = {}
    thread = threading.Thread(target=lambda: results.update(server.run(cases, parallel=len(cases))), daemon=True)
    thread.start()
    children: Dict[str, ForkedChild] = {}
    try:
        deadline = time.monotonic() + timeout
        for name, log in logs.items():
            while name not in children:
                first = log.read_text(errors="replace").split("\n", 1)[0] if log.exists() else ""
                if first.startswith(CHILD_PID) and first.split()[-1].isdigit():
                    children[name] = ForkedChild(int(first.split()[-1]))
                elif time.monotonic() > deadline or not thread.is_alive():
                    raise AssertionError(f"{name}: the fork server did not start it")
                else:
                    time.sleep(0.1)
        viewers = {}
        for name, child in children.items():
            viewers[name] = Viewer(child, logs[name], wait_for_port(child, logs[name], timeout=max(1.0, deadline - time.monotonic())))
            viewers[name].page()
        yield viewers
    finally:  # every child that started, also one the test had not got to (a failure on the way)
        for log in logs.values():
            first = log.read_text(errors="replace").split("\n", 1)[0] if log.exists() else ""
            if first.startswith(CHILD_PID) and first.split()[-1].isdigit():
                with contextlib.suppress(OSError):
                    os.killpg(int(first.split()[-1]), signal.SIGTERM)
        thread.join(timeout=60)
        forked_viewers.results = results


@contextlib.contextmanager
def serving(args: Sequence[str], log: Path, *, env: Optional[dict] = None, cwd: Optional[Path] = None,
            timeout: float = 300.0) -> Iterator[Viewer]:
    """Run ``args`` until the viewer's page is served, yield the :class:`Viewer`, stop the process
    on exit (also when the test fails)."""
    proc = start(args, log, env=env, cwd=cwd)
    try:
        port = wait_for_port(proc, log, timeout=timeout)
        viewer = Viewer(proc, Path(log), port)
        viewer.page(timeout=60.0)
        yield viewer
    finally:
        stop(proc)
