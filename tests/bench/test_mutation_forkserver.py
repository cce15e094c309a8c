"""The mutation study's fork server (``bench/mutation_forkserver.py``): a fork sees the source on disk
as it is at that run (a mutant), reports pytest's exit status, dies with its client, and a client
without a server runs the same pytest itself (never a false "killed")."""

import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

SERVER = Path(__file__).resolve().parents[2] / "bench" / "mutation_forkserver.py"


def client(project: Path, sock: Path, *args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-S", str(SERVER), "run", str(sock), "-q", "-p", "no:cacheprovider", *args],
                          cwd=project, capture_output=True, text=True, timeout=timeout)


@pytest.fixture()
def project(tmp_path):
    """A module, a test of it, and a running server that preloaded only ``json``."""
    (tmp_path / "subject.py").write_text("VALUE = 1\n")
    (tmp_path / "test_subject.py").write_text("import subject\n\ndef test_value():\n    assert subject.VALUE == 1\n")
    sock = tmp_path / "server.sock"
    env = dict(os.environ, PYTHONPATH=str(tmp_path), PYTHONDONTWRITEBYTECODE="1", PYTEST_DISABLE_PLUGIN_AUTOLOAD="1")
    server = subprocess.Popen([sys.executable, str(SERVER), "serve", str(sock), "json"], cwd=tmp_path, env=env,
                              stdout=subprocess.PIPE, text=True)
    assert server.stdout.readline().strip() == "ready"
    yield tmp_path, sock
    server.kill()
    server.wait()


def test_each_run_imports_the_module_as_it_is_on_disk_and_reports_pytests_status(project):
    path, sock = project
    first = client(path, sock, "test_subject.py")
    assert first.returncode == 0 and "1 passed" in first.stdout
    (path / "subject.py").write_text("VALUE = 2\n")  # the mutant: same size, maybe the same mtime
    second = client(path, sock, "test_subject.py")
    assert second.returncode == 1 and "1 failed" in second.stdout
    (path / "subject.py").write_text("VALUE = 1\n")
    assert client(path, sock, "test_subject.py").returncode == 0
    assert client(path, sock, "no_such_test.py").returncode == 4  # pytest's usage error, passed on as is


def test_a_killed_client_takes_its_fork_with_it_and_the_server_goes_on(project):
    path, sock = project
    pid_file = path / "fork.pid"
    (path / "test_slow.py").write_text(textwrap.dedent(f"""
        import os, time
        def test_slow():
            open({str(pid_file)!r}, "w").write(str(os.getpid()))
            time.sleep(120)
    """))
    run = subprocess.Popen([sys.executable, "-S", str(SERVER), "run", str(sock), "-q", "test_slow.py"], cwd=path,
                           stdout=subprocess.DEVNULL)
    deadline = time.monotonic() + 60
    while not pid_file.exists() or not pid_file.read_text():
        assert time.monotonic() < deadline and run.poll() is None, "the slow test never started"
        time.sleep(0.05)
    run.kill()  # as cosmic-ray does at its timeout
    run.wait()
    pid = int(pid_file.read_text())
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            break
        time.sleep(0.1)
    else:
        pytest.fail(f"the fork {pid} outlived its client")
    assert client(path, sock, "test_subject.py").returncode == 0


def test_without_a_server_the_client_runs_the_same_pytest_itself(tmp_path):
    (tmp_path / "test_fails.py").write_text("def test_no():\n    assert False\n")
    done = client(tmp_path, tmp_path / "absent.sock", "test_fails.py")
    assert done.returncode == 1 and "1 failed" in done.stdout


def test_a_preload_that_imports_the_code_under_test_is_refused(tmp_path):
    (tmp_path / "sp_plugins").mkdir()
    (tmp_path / "sp_plugins" / "__init__.py").write_text("")
    done = subprocess.run([sys.executable, str(SERVER), "serve", str(tmp_path / "s.sock"), "sp_plugins"], cwd=tmp_path,
                          env=dict(os.environ, PYTHONPATH=str(tmp_path)), capture_output=True, text=True, timeout=60)
    assert done.returncode == 1 and "the forks would test stale code" in done.stderr
