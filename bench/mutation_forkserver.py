"""Fork server for the mutation study: each mutant's pytest runs in a fresh fork of a
process that has already imported the heavy third-party modules (torch, numpy, trimesh, pytest...),
so a mutant costs its tests, not the ~4-5 s of interpreter start and imports a fresh ``pytest``
pays (most mutants die in the first second of their tests).

The parent never imports ``sp_plugins`` or ``tests`` (it refuses to start if a preloaded module
did): every fork imports them afresh from disk, the mutated module included, exactly as a new
interpreter would. cosmic-ray still runs one test command per mutant (the client below); when it
kills that command at its timeout, the server sees the client's socket close and kills the fork's
process group. Written by hand: mutmut 3 forks per mutant but only in its own runner and layout
(why cosmic-ray: ``bench/mutation_study.py``), and no package offers a pytest fork server.

    python bench/mutation_forkserver.py serve SOCKET [MODULE ...]   # preload MODULEs (default PRELOAD), print "ready"
    python bench/mutation_forkserver.py run SOCKET PYTEST_ARGS...   # one pytest run in a fork; its exit status
    python bench/mutation_forkserver.py stop SOCKET
"""

from __future__ import annotations

import json
import os
import select
import signal
import socket
import sys
import tempfile
import traceback
from typing import List

PRELOAD = ["torch", "numpy", "scipy.spatial", "pytest", "_pytest.python", "_pytest.assertion.rewrite", "trimesh",
           "PIL.Image", "cv2", "jaxtyping", "tyro", "rich.console"]
"""Imported once by the server when present: the third-party modules every covering test file imports."""

NERFSTUDIO_PRELOAD = ["nerfstudio.utils.external", "nerfstudio.models.base_model", "nerfstudio.models.nerfacto",
                      "nerfstudio.models.vanilla_nerf", "nerfstudio.models.neus_facto", "nerfstudio.models.mipnerf",
                      "nerfstudio.pipelines.base_pipeline", "nerfstudio.engine.trainer",
                      "nerfstudio.data.dataparsers.blender_dataparser", "nerfstudio.fields.sdf_field"]
"""nerfstudio 1.x's modules our tests build models from (~4 s). Not its method configs or scripts: they
discover the installed methods, ours included. Not in sdfstudio's environment: there, importing
``nerfstudio`` with sp-plugins' opt-in hook installed loads our patches (the leak check refuses it)."""


def _recv_all(conn: socket.socket) -> bytes:
    chunks = []
    while chunk := conn.recv(1 << 16):
        chunks.append(chunk)
    return b"".join(chunks)


def _kill_group(pid: int) -> None:
    try:
        os.killpg(pid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass


def _child(request: dict, out_fd: int) -> None:
    """In the fork: the pytest run, its output to ``out_fd``, its exit status as the process's."""
    try:
        os.setpgid(0, 0)
        os.dup2(out_fd, 1)
        os.dup2(out_fd, 2)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        os.chdir(request["cwd"])
        sys.dont_write_bytecode = True  # a mutant may keep its file's size and mtime: never a stale .pyc
        sys.argv = ["pytest", *request["args"]]
        import pytest

        code = int(pytest.main(request["args"]))
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    except BaseException:  # noqa: BLE001 (the fork must never return into the server's loop)
        traceback.print_exc()
        sys.stderr.flush()
        os._exit(99)


def _handle(conn: socket.socket, server: socket.socket) -> bool:
    request = json.loads(conn.makefile("rb").readline())
    if request.get("stop"):
        return False
    with tempfile.TemporaryFile() as out:
        pid = os.fork()
        if pid == 0:
            server.close()
            conn.close()
            _child(request, out.fileno())
        try:
            os.setpgid(pid, pid)
        except (ProcessLookupError, PermissionError):
            pass
        while True:
            done, status = os.waitpid(pid, os.WNOHANG)
            if done:
                break
            ready, _, _ = select.select([conn], [], [], 0.05)
            if ready and not conn.recv(1):  # the client is gone (cosmic-ray's timeout killed it)
                _kill_group(pid)
                os.waitpid(pid, 0)
                return True
        _kill_group(pid)  # whatever the tests started and left running
        out.seek(0)
        output = out.read().decode("utf-8", "replace")
    code = os.waitstatus_to_exitcode(status)
    conn.sendall(json.dumps({"code": code if code >= 0 else 128 - code, "output": output}).encode())
    return True


def serve(path: str, preload: List[str]) -> None:
    for name in preload:
        try:
            __import__(name)
        except ImportError:
            pass  # not in this environment: only a speed-up is lost
    leaked = sorted(m for m in sys.modules if m.split(".")[0] in ("sp_plugins", "tests"))
    if leaked:
        raise SystemExit(f"mutation_forkserver: preloading imported {leaked[:3]}: the forks would test stale code")
    if os.path.exists(path):
        os.unlink(path)
    server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    server.bind(path)
    server.listen(1)
    print("ready", flush=True)
    server.settimeout(1.0)
    parent, running = os.getppid(), True
    while running and os.getppid() == parent:  # the study that started it stopped: so does the server
        try:
            conn, _ = server.accept()
        except socket.timeout:
            continue
        conn.settimeout(None)
        with conn:
            running = _handle(conn, server)
    server.close()
    os.unlink(path)


def request(path: str, payload: dict) -> bytes:
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as conn:
        conn.connect(path)
        conn.sendall(json.dumps(payload).encode() + b"\n")
        if payload.get("stop"):
            conn.shutdown(socket.SHUT_WR)
        return _recv_all(conn)


def main(argv: List[str]) -> int:
    if len(argv) < 2 or argv[0] not in ("serve", "run", "stop"):
        print(__doc__, file=sys.stderr)
        return 2
    command, path, rest = argv[0], argv[1], argv[2:]
    if command == "serve":
        serve(path, rest or PRELOAD)
        return 0
    if command == "stop":
        request(path, {"stop": True})
        return 0
    try:
        reply = json.loads(request(path, {"cwd": os.getcwd(), "args": rest}))
    except (OSError, ValueError):
        # no server (stopped, or died mid-run): the same run in a fresh interpreter, never a false "killed"
        os.execv(sys.executable, [sys.executable, "-m", "pytest", *rest])
    sys.stdout.write(reply["output"])
    return reply["code"]


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
