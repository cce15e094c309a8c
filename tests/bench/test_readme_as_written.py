"""``bench/readme_as_written.py`` keeps a block's record by its document and text: an edit above a block (its
line moves) must not drop the record from the table, as it did for the README's two examples once."""

from __future__ import annotations

from pathlib import Path

from bench import readme_as_written as raw
from tests.helpers import readme_runner as rr


def _item(line: int, source: str = "ns-train x\n") -> raw.Item:
    return raw.Item(rr.Block(Path("README.md"), line, "bash", source, "s"), {})


def test_a_block_s_key_is_its_document_and_text_not_its_line():
    assert _item(88).key == _item(131).key
    assert _item(88).key != _item(88, "ns-train y\n").key
    assert _item(88).key.startswith("README.md:")


def test_records_written_under_line_keys_are_found_by_text_the_newest_winning():
    key = _item(89).key
    digest = key.split(":")[-1]
    state = {f"README.md:88:{digest}": {"rc": 1, "date": "2026-12-06 09:00"},
             f"README.md:129:{digest}": {"rc": 0, "date": "2026-12-06 10:00"},
             f"sweeps.md:6:{digest}": {"rc": 0, "date": "2026-12-06 08:00"}}
    migrated = raw.by_text(state)
    assert migrated[key] == {"rc": 0, "date": "2026-12-06 10:00"}
    assert f"sweeps.md:{digest}" in migrated and len(migrated) == 2
    assert raw.by_text(migrated) == migrated  # already keyed by text: unchanged


def test_the_restated_record_names_the_block_s_current_line():
    record = {"where": "README.md:88", "commands": [{"command": "ns-train x", "seconds": 10.0}]}
    item = raw.Item(_item(131).block, {"ns-train": 60.0})
    restated = raw.restate(record, item)
    assert restated["where"] == "README.md:131" and restated["commands"][0]["stated_s"] == 60.0
    assert restated["unmatched_stated"] == []
