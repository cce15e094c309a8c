"""One-line-error checks: a command refused bad input with exit status 2 and one line
``<prog>: error: ...`` as the last line of its stderr, no traceback."""

from __future__ import annotations


def one_line_error(rc: int, stderr: str, prog: str, *says: str, stdout: str = "", name: str = "",
                   others: bool = False) -> str:
    """Exit status 2, no traceback, the last non-empty stderr line ``<prog>: error: ...`` holding every
    one of ``says``; unless ``others``, no other ``: error: `` line before it. Returns that line."""
    report = f"[{name}] rc={rc}\n--- stderr\n{stderr[-3000:]}" + (f"\n--- stdout\n{stdout[-1500:]}" if stdout else "")
    assert rc == 2, report
    assert "Traceback" not in stderr, report
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert lines, report
    last = lines[-1]
    assert last.startswith(f"{prog}: error: "), report
    if not others:
        assert [line for line in lines if ": error: " in line] == [last], report
    for word in says:
        assert word in last, f"{word!r} not in the error line\n{report}"
    return last


def refused(proc, prog: str, *says: str, **kwargs) -> str:
    """:func:`one_line_error` for a :class:`subprocess.CompletedProcess`."""
    return one_line_error(proc.returncode, proc.stderr, prog, *says, stdout=proc.stdout or "", **kwargs)
