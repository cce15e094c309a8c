"""docs/sp_defaults.md (and the README's copy, when it has one) is the table the configs give."""

import pytest

from sp_plugins import defaults_table


def test_the_documented_defaults_are_the_registered_configs():
    assert defaults_table.DOC.read_text() == defaults_table.document(), (
        "docs/sp_defaults.md is out of date: run python -m sp_plugins.defaults_table --write"
    )


def test_the_readme_copy_matches_when_present():
    readme = defaults_table.DOC.parent.parent / "README.md"
    text = readme.read_text()
    if defaults_table.BEGIN not in text:
        pytest.skip("the README has no copy of the table (it links docs/sp_defaults.md)")
    copy = text[text.index(defaults_table.BEGIN): text.index(defaults_table.END) + len(defaults_table.END)]
    assert copy == defaults_table.table(), "README's SP-defaults table is out of date: paste python -m sp_plugins.defaults_table"


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
