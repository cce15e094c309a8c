"""Console commands typed in a shell, run by the fork server: a folder of shims first on ``PATH``.

The README runner types the README's ``ns-*`` / ``sp-train`` commands in a bash session; each would
spend 8 s (idle) to 20 s (loaded) importing nerfstudio before doing a few steps of work. With
:func:`shims`, a command of :data:`SCRIPTS` is a tiny stdlib-only client that hands its arguments,
working folder, environment and its own stdout/stderr (the file descriptors themselves, passed over a
UNIX socket) to a server that imported the entry points once; the server forks a child that runs the
console script exactly as :mod:`tests.helpers.forkserver` does (``sys.argv``, the entry point, the
excepthook, the exit status), writing straight to the shim's stdout and stderr. The shim exits with
the child's status. Commands the shell runs in any subprocess (``sp-sweep``'s trials on Ray) reach
the server through the same ``PATH``; without the server (``SP_FORK_SOCKET`` unset or not answering)
a shim runs the real script. Test-only: what is tested is the command line as typed, started once
per command, not the interpreter's start-up.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Dict, Iterator

SCRIPTS = ("ns-train", "ns-eval", "ns-render", "ns-export", "sp-train", "sp-export-mesh", "sp-compare", "sp-fit", "sp-scene",
           "nerfbaselines")
"""Console scripts that import nerfstudio or torch at start-up (``nerfbaselines`` with our specs imports
nerfstudio when it loads the method): the ones worth a fork."""

SHIM = """#!{python} -S
import json, os, socket, sys
real = {real!r}
path = os.environ.get("SP_FORK_SOCKET")
try:
    s = socket.socket(socket.AF_UNIX)
    s.connect(path)
except (OSError, TypeError):
    os.execv(real, [real, *sys.argv[1:]])
sys.stdout.flush(); sys.stderr.flush()
body = json.dumps({{"script": {name!r}, "args": sys.argv[1:], "cwd": os.getcwd(), "env": dict(os.environ)}}).encode()
socket.send_fds(s, [len(body).to_bytes(8, "little")], [1, 2])
s.sendall(body)
answer = b""
while True:
    chunk = s.recv(4096)
    if not chunk:
        break
    answer += chunk
rc = json.loads(answer or b'{{"rc": 1}}')["rc"]
sys.exit(rc if rc >= 0 else 128 - rc)
"""


def _recv_exact(conn: socket.socket, n: int) -> bytes:
    data = b""
    while len(data) < n:
        chunk = conn.recv(n - len(data))
        if not chunk:
            raise ConnectionError("the shim went away")
        data += chunk
    return data


def _handle(conn: socket.socket) -> None:
    """In a forked handler: run one command in a grandchild on the shim's own stdout/stderr; answer its status."""
    from forkserver import _child  # a sibling module (this file runs as a script, as forkserver does)

    head, fds, _, _ = socket.recv_fds(conn, 8, 2)
    case = json.loads(_recv_exact(conn, int.from_bytes(head, "little")))
    pid = os.fork()
    if pid == 0:
        conn.close()
        _child(case, fds[0], fds[1])
    for fd in fds:
        os.close(fd)
    _, status = os.waitpid(pid, 0)
    conn.sendall(json.dumps({"rc": os.waitstatus_to_exitcode(status)}).encode())


def serve(path: str) -> None:
    here = str(Path(__file__).resolve().parent)
    import forkserver

    for name in SCRIPTS:
        forkserver._entry(name)
    if sys.path and sys.path[0] == here:  # the commands see a user's sys.path, not tests/helpers
        sys.path.pop(0)
    server = socket.socket(socket.AF_UNIX)
    server.bind(path)
    server.listen(16)
    print("ready", flush=True)
    while True:
        conn, _ = server.accept()
        if os.fork() == 0:
            server.close()
            code = 0
            try:
                _handle(conn)
            except BaseException:  # noqa: BLE001
                code = 1
            finally:
                os._exit(code)
        conn.close()
        try:
            while os.waitpid(-1, os.WNOHANG)[0]:
                pass
        except ChildProcessError:
            pass


@contextmanager
def shims(folder: Path, env: Dict[str, str]) -> Iterator[Dict[str, str]]:
    """Start the server (with ``env``) and write the shims into ``folder``; yields the variables a
    shell needs (``PATH`` with the shims first, ``SP_FORK_SOCKET``). The server stops on exit."""
    folder.mkdir(parents=True, exist_ok=True)
    sock = str(folder / "fork.sock")
    bin_dir = Path(sys.executable).parent
    for name in SCRIPTS:
        shim = folder / name
        shim.write_text(SHIM.format(python=sys.executable, real=str(bin_dir / name), name=name))
        shim.chmod(0o755)
    proc = subprocess.Popen([sys.executable, __file__, sock], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                            env=env, text=True, start_new_session=True)
    try:
        ready = proc.stdout.readline() if proc.stdout else ""
        assert ready.strip() == "ready", "the fork shim server did not start"
        yield {"PATH": f"{folder}{os.pathsep}{env.get('PATH', '')}", "SP_FORK_SOCKET": sock}
    finally:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except OSError:
            pass
        proc.wait()


if __name__ == "__main__":
    serve(sys.argv[1])
