"""The docs' nerfstudio method table (docs/guides/any-method.md) is the one ``sp_plugins.method_table`` makes from the registered
methods and ``sp_plugins/nerfstudio/table.py`` (sdfstudio's: tests/sdfstudio/test_any_method.py)."""

import os
import subprocess
import sys

from sp_plugins import method_table
from sp_plugins.nerfstudio import table
from tests.nerfstudio.test_with_sp import BUILTIN_TRAIN

BEGIN, END = method_table.markers("nerfstudio")


def _readme_copy(text: str) -> str:
    assert BEGIN in text and END in text, "docs/guides/any-method.md has lost the nerfstudio method table's markers"
    return text[text.index(BEGIN): text.index(END) + len(END)]


def test_the_readme_table_is_the_generated_one():
    assert _readme_copy(method_table.page("nerfstudio").read_text()) == method_table.table("nerfstudio"), (
        "the nerfstudio method table in docs/guides/any-method.md is out of date: run python -m sp_plugins.method_table --write"
    )


def test_rows_are_read_from_the_table_module(monkeypatch):
    import nerfstudio.configs.method_configs  # noqa: F401  (our methods registered before the table changes)

    monkeypatch.setitem(table.REFUSED_MODELS, "nerfstudio.models.tensorf.TensoRFModel", "a reason of the table's")
    monkeypatch.delitem(table.CONTRACTED_MODELS, "nerfstudio.models.semantic_nerfw.SemanticNerfWModel")
    rows = method_table.table("nerfstudio").splitlines()
    assert "| `tensorf` | refused: a reason of the table's |" in rows
    assert "| `dnerf`, `generfacto`, `semantic-nerfw`, `vanilla-nerf` | offered: alpha0 0.02 to 0 over the first 20%, " \
           "boundary `none` (the default preset) |" in rows


def test_the_methods_the_readme_says_the_suite_does_not_train_are_the_ones_it_does_not():
    outcomes = method_table.nerfstudio_outcomes()
    offered = {m for m, (order, _) in outcomes.items() if order == 0}
    untrained = offered - set(BUILTIN_TRAIN)
    assert untrained == {"depth-nerfacto", "semantic-nerfw", "generfacto"}
    after = method_table.page("nerfstudio").read_text().partition(END)[2][:800]
    assert all(f"`{m}`" in after for m in untrained), "the sentence under the table names other methods"


def _run(cwd):
    return subprocess.run([sys.executable, "-m", "sp_plugins.method_table", "--write"], cwd=cwd, capture_output=True,
                          text=True, timeout=300, env=dict(os.environ, OMP_NUM_THREADS="1"))


def test_write_restores_a_drifted_readme_table(tmp_path):
    """The page says --write regenerates the table: run as written, from the root of a copy whose table drifted."""
    text = method_table.page("nerfstudio").read_text()
    head, _, rest = text.partition(BEGIN)
    old, _, tail = rest.partition(END)
    rows = old.strip("\n").splitlines()
    drifted = rows[:2] + ["| `gone` | offered |"] + rows[3:-1]  # one row changed, one lost
    copy = method_table.page("nerfstudio", tmp_path)
    copy.parent.mkdir(parents=True)
    copy.write_text(head + "\n".join([BEGIN, *drifted, END]) + tail)
    proc = _run(tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert copy.read_text() == head + method_table.table("nerfstudio") + tail
    assert f"wrote {copy} (nerfstudio)" in proc.stdout

