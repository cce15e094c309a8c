"""docs/sp_defaults.md (and the README's copy, when it has one) is the table the configs give."""

import pytest

from sp_plugins import defaults_table


def test_the_documented_defaults_are_the_registered_configs():
    assert defaults_table.DOC.read_text() == defaults_table.document(), (
        "docs/sp_defaults.md is out of date: run python -m sp_plugins.defaults_table --write"
    )


def test_the_settings_page_shows_the_generated_table_and_no_copy_can_drift():
    """docs/choosing-settings.md includes docs/sp_defaults.md itself (no pasted copy; the site expands the
    comment, docs/conf.py); a copy between the markers in the README or a page would have to be today's table."""
    docs = defaults_table.DOC.parent
    assert "<!-- site-include: sp_defaults.md offset=1 -->" in (docs / "choosing-settings.md").read_text()
    for path in [docs.parent / "README.md", *sorted(docs.rglob("*.md"))]:
        text = path.read_text()
        if defaults_table.BEGIN in text:
            copy = text[text.index(defaults_table.BEGIN): text.index(defaults_table.END) + len(defaults_table.END)]
            assert copy == defaults_table.table(), f"{path.name}'s SP-defaults table is out of date: run python -m sp_plugins.defaults_table --write"


def test_rows_are_read_from_the_configs(monkeypatch):
    import dataclasses

    from sp_plugins.core import SPConfig
    from sp_plugins.tasks import pointcloud

    assert "| step |" in dict(defaults_table.rows())["sp-fit pointcloud"]  # not the core's exponential

    @dataclasses.dataclass
    class Changed(pointcloud.PointCloudSDFConfig):
        sp: SPConfig = dataclasses.field(default_factory=lambda: SPConfig(alpha0=0.5, schedule="linear", end=0.5))

    monkeypatch.setattr(pointcloud, "PointCloudSDFConfig", Changed)
    assert "| 0.5 | linear | 0.5 (1,000 of 2,000 steps) |" in dict(defaults_table.rows())["sp-fit pointcloud"]


def _run(cwd, module="defaults_table"):
    import os
    import subprocess
    import sys

    return subprocess.run([sys.executable, "-m", f"sp_plugins.{module}", "--write"], cwd=cwd, capture_output=True,
                          text=True, timeout=300, env=dict(os.environ, OMP_NUM_THREADS="1"))


def test_write_restores_a_drifted_readme_table(tmp_path):
    """The README says --write regenerates its table: run as written, from the root of a copy whose table drifted."""
    readme = defaults_table.DOC.parent.parent / "README.md"
    text = readme.read_text()
    head, _, rest = text.partition(defaults_table.BEGIN)
    old_table, _, tail = rest.partition(defaults_table.END)
    rows = old_table.strip("\n").splitlines()
    drifted = rows[:2] + ["| `sp-gone` | on | 9 | linear | 1 | uniform | clamp |"] + rows[3:-1]  # one changed, one lost
    (tmp_path / "README.md").write_text(head + "\n".join([defaults_table.BEGIN, *drifted, defaults_table.END]) + tail)
    proc = _run(tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert (tmp_path / "README.md").read_text() == head + defaults_table.table() + tail
    assert (tmp_path / "docs" / "sp_defaults.md").read_text() == defaults_table.document()
    assert f"wrote {tmp_path / 'README.md'}, {tmp_path / 'docs' / 'sp_defaults.md'}" in proc.stdout


@pytest.mark.parametrize("module", ["defaults_table", "method_table"])
def test_write_outside_a_checkout_is_one_line_and_writes_nothing(module, tmp_path):
    proc = _run(tmp_path, module)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    (line,) = proc.stderr.strip().splitlines()
    assert line.startswith(f"python -m sp_plugins.{module}: error: ") and "root of" in line
    assert list(tmp_path.iterdir()) == []
