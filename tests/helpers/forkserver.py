"""Run console scripts (``ns-train``, ``ns-eval``, ``sp-export-mesh``...) as separate processes that
share one import of nerfstudio: a test-only fork server.

Every ``ns-*`` command spends most of its start-up (20-30 s on a loaded 2-core machine) importing
nerfstudio and every installed method. This server imports the entry points once, then runs each
command in a child forked from it, exactly as the console script does: ``sys.argv`` set, the
entry point called, an uncaught exception handed to ``sys.excepthook`` (whatever the command
installed meanwhile) and a ``SystemExit`` turned into the exit status, as the interpreter does at
the top level. Each child has its own stdout and stderr (pipes), working folder and, optionally, a
file-size limit (``RLIMIT_FSIZE``: writes past it fail with EFBIG, the way they fail on a full
disk). A test that wants the real script too runs it with :mod:`subprocess` (the bad-input tests
in tests/nerfstudio and tests/cli each run one case that way).

Protocol (one JSON document per line): the test writes ``{"cases": [...], "parallel": N}``, the
server answers ``{"results": [...]}``, one ``{"name", "rc", "stdout", "stderr", "seconds"}`` per
case, in order. A case is ``{"name", "script", "args", "cwd"?, "env"?, "fsize"?, "timeout"?, "log"?}``
(``timeout``: seconds, after which the child and what it started are killed; ``log``: a file that takes
its stdout and stderr instead of the result, for a command a test talks to while it runs, a viewer).
Each child runs in its own process group, and what it leaves running there is stopped when it ends,
as the interpreter's exit stops daemon processes.
"""

from __future__ import annotations

import json
import os
import resource
import signal
import subprocess
import sys
import time
from importlib.metadata import entry_points
from pathlib import Path
from typing import Dict, List, Optional



def _entry(script: str):
    (ep,) = [ep for ep in entry_points(group="console_scripts") if ep.name == script]
    return ep.load()


def _exit_code(exc: SystemExit) -> int:
    if exc.code is None:
        return 0
    if isinstance(exc.code, int):
        return exc.code
    print(exc.code, file=sys.stderr)
    return 1


CHILD_PID = "fork server child pid"
"""The first line of a case's ``log`` file: the child's pid (its process group; the test may stop it)."""


def _end_group() -> None:
    """Stop what the command left in its process group (a data manager's worker processes), as the
    interpreter's exit does (multiprocessing's exit function: daemon workers stopped, queues and
    semaphores released); what still runs holds the output pipes open, so the batch would wait forever."""
    for name in ("multiprocess.util", "multiprocessing.util"):  # the atexit handler os._exit skips
        module = sys.modules.get(name)
        if module is not None:
            try:
                module._exit_function()
            except Exception:  # noqa: BLE001  (best effort, as at exit)
                pass
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    try:
        os.killpg(0, signal.SIGTERM)
    except OSError:
        pass


def _kill_group(pid: int) -> None:
    try:
        os.killpg(pid, signal.SIGKILL)
    except OSError:
        pass


def _child(case: dict, out: int, err: int) -> None:
    if case.get("log"):  # output into a file the test reads while the command runs (a server), after a line with its pid
        out = err = os.open(case["log"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        os.write(out, f"{CHILD_PID} {os.getpid()}\n".encode())
    os.dup2(out, 1)
    os.dup2(err, 2)
    os.setpgid(0, 0)  # its own process group: what it starts ends with it
    code = 1
    try:
        if case.get("cwd"):
            os.chdir(case["cwd"])
        os.environ.update(case.get("env") or {})
        if case.get("fsize") is not None:
            signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails with EFBIG instead of killing
            resource.setrlimit(resource.RLIMIT_FSIZE, (int(case["fsize"]), int(case["fsize"])))
        fn = _entry(case["script"])
        sys.argv = [str(Path(sys.executable).parent / case["script"]), *case["args"]]
        try:
            result = fn()
            code = result if isinstance(result, int) else 0
        except SystemExit as exc:
            code = _exit_code(exc)
        except BaseException:  # noqa: BLE001  (what the interpreter does with an uncaught exception)
            try:
                sys.excepthook(*sys.exc_info())
                code = 1
            except SystemExit as exc:
                code = _exit_code(exc)
    finally:
        try:
            sys.stdout.flush()
            sys.stderr.flush()
            _end_group()
        finally:
            os._exit(code)


def _drain(fd: int, sink: list) -> None:
    with os.fdopen(fd, "rb") as pipe:
        sink.append(pipe.read())


def run_cases(cases: List[dict], parallel: int = 1) -> List[dict]:
    """Fork one child per case, ``parallel`` at a time; their results in order. A child's stdout and
    stderr are pipes (a file-size limit does not apply to them), read by threads here."""
    import threading

    pending = list(enumerate(cases))
    running: Dict[int, tuple] = {}
    results: List[dict] = [{} for _ in cases]
    while pending or running:
        while pending and len(running) < max(1, parallel):
            i, case = pending.pop(0)
            (out_r, out_w), (err_r, err_w) = os.pipe(), os.pipe()
            sys.stdout.flush()
            sys.stderr.flush()
            pid = os.fork()
            if pid == 0:
                os.close(out_r)
                os.close(err_r)
                _child(case, out_w, err_w)
            os.close(out_w)
            os.close(err_w)
            try:
                os.setpgid(pid, pid)  # also here: no race with the child's own call
            except OSError:
                pass
            timer = None
            if case.get("timeout"):  # a command that hangs is killed (exit status -9) with what it started, not the batch
                timer = threading.Timer(float(case["timeout"]), _kill_group, (pid,))
                timer.daemon = True
                timer.start()
            sinks: tuple = ([], [])
            readers = [threading.Thread(target=_drain, args=(fd, sink), daemon=True) for fd, sink in zip((out_r, err_r), sinks)]
            for reader in readers:
                reader.start()
            running[pid] = (i, case, sinks, readers, time.perf_counter(), timer)
        pid, status = os.wait()
        if pid not in running:
            continue
        i, case, sinks, readers, start, timer = running.pop(pid)
        if timer is not None:
            timer.cancel()
        for reader in readers:
            reader.join()
        results[i] = {
            "name": case.get("name", case["script"]),
            "rc": os.waitstatus_to_exitcode(status),
            "stdout": b"".join(sinks[0]).decode(errors="replace"),
            "stderr": b"".join(sinks[1]).decode(errors="replace"),
            "seconds": round(time.perf_counter() - start, 2),
        }
    return results


def serve(preload: List[str]) -> None:
    """``preload``: console scripts (their entry points are loaded) and modules (names with a dot) to
    import before the first case, so no child pays for them."""
    import importlib

    channel = os.fdopen(os.dup(1), "w")
    os.dup2(2, 1)  # whatever the imports print goes to stderr, not into the protocol
    for name in preload:
        if "." in name:
            importlib.import_module(name)
        else:
            _entry(name)

    channel.write(json.dumps({"ready": True}) + "\n")
    channel.flush()
    for line in sys.stdin:
        request = json.loads(line)
        channel.write(json.dumps({"results": run_cases(request["cases"], request.get("parallel", 1))}) + "\n")
        channel.flush()


class ForkServer:
    """The server as a child of the test process (:meth:`run` sends cases and waits for them)."""

    def __init__(self, preload: List[str], env: Dict[str, str]) -> None:
        self.proc = subprocess.Popen([sys.executable, __file__, *preload], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=subprocess.DEVNULL, text=True, env=env)
        ready = self.proc.stdout.readline()
        assert ready and json.loads(ready).get("ready"), "the fork server did not start"

    def run(self, cases: List[dict], parallel: int = 1) -> Dict[str, dict]:
        self.proc.stdin.write(json.dumps({"cases": cases, "parallel": parallel}) + "\n")
        self.proc.stdin.flush()
        answer = self.proc.stdout.readline()
        assert answer, "the fork server died"
        return {r["name"]: r for r in json.loads(answer)["results"]}

    def call(self, args: List[str], env: Optional[Dict[str, str]] = None, expect: int = 0):
        """One command line ``[<console script or its path>, *args]`` in a forked child, as
        :func:`subprocess.run` would run it; fails with its output's tail unless it exits ``expect``.
        Returns a :class:`subprocess.CompletedProcess`."""
        script, *rest = [str(a) for a in args]
        result = self.run([{"name": "call", "script": Path(script).name, "args": rest, "env": env or {}}])["call"]
        proc = subprocess.CompletedProcess(args, result["rc"], result["stdout"], result["stderr"])
        assert proc.returncode == expect, (
            f"{' '.join(map(str, args))} (forked) exited {proc.returncode}\n--- stdout\n{proc.stdout[-3000:]}\n"
            f"--- stderr\n{proc.stderr[-4000:]}")
        return proc

    def close(self) -> None:
        """Stop the server (it holds no state worth a clean shutdown of nerfstudio's imports)."""
        self.proc.stdin.close()
        self.proc.kill()
        self.proc.wait()


if __name__ == "__main__":
    serve(sys.argv[1:])
