"""The docs' worked example (docs/extending.md, "A field with its own read point"): a toy field declares where it queries with one
method, ``sp_read_positions``, and the seam, unedited, moves its queries there. Runs the page's own
block, then the same field without the method: its queries then leave the box."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

PAGE = Path(__file__).resolve().parents[2] / "docs" / "extending.md"
HEADING = "### A field with its own read point (worked example)"
METHOD = '''
    def sp_read_positions(self, frustums: Frustums) -> torch.Tensor:
        return frustums.origins + frustums.directions * frustums.ends
'''
CALL = "self.queried = self.sp_read_positions(ray_samples.frustums)"
INLINE = "f = ray_samples.frustums\n        self.queried = f.origins + f.directions * f.ends"


def example() -> str:
    text = PAGE.read_text()
    assert HEADING in text, f"docs/extending.md has no {HEADING!r}"
    match = re.search(r"```python\n(.*?)```", text[text.index(HEADING):], flags=re.S)
    assert match, "no python block under the heading"
    return match.group(1)


def test_the_readme_field_with_its_own_read_point_is_reached_and_queried_inside_the_box():
    source = example()
    assert METHOD in source and CALL in source  # the one method this example is about
    exec(compile(source, str(PAGE), "exec"), {"__name__": "readme_example"})


def test_without_its_read_point_the_same_field_queries_outside_the_box():
    source = example().replace(METHOD, "\n").replace(CALL, INLINE)
    assert "sp_read_positions" not in source
    with pytest.raises(AssertionError):  # the example's last line: the far ends left the box
        exec(compile(source, str(PAGE), "exec"), {"__name__": "readme_example"})
