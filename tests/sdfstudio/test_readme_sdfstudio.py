"""The docs' sdfstudio guide (docs/guides/sdfstudio.md) is executable: its blocks run here, in sdfstudio's
environment, as a user types them, through the same runner as tests/test_readme.py (Sybil; the
budget flags, placeholders and skip markers declared in tests/helpers/readme_runner.py). The scene
they train on is made first by the README's own ``sp-scene spot my-scene`` line."""

from __future__ import annotations

import time

from tests.helpers import readme_runner as rr

SCENE_LINE = "sp-scene spot my-scene"


def test_readme_sdfstudio_blocks_run_as_a_user_types_them(tmp_path, record_property):
    readme = rr.REPO / "README.md"
    scene = [b for b in rr.blocks(readme) if b.source.startswith(SCENE_LINE)]
    assert scene, f"the README no longer starts a block with {SCENE_LINE!r}, which the sdfstudio blocks train on"
    start = time.monotonic()
    rr.run_block(rr.Block(readme, scene[0].line, "bash", SCENE_LINE + "\n", scene[0].section), tmp_path)
    runner = rr.Runner(tmp_path, mine=lambda block: block.path == rr.SDFSTUDIO_PAGE)
    outcomes = runner.run(rr.SDFSTUDIO_PAGE)
    text = f"{rr.summary(outcomes)}\nwall time {time.monotonic() - start:.0f} s"
    record_property("readme_runner_sdfstudio", text)
    print(text)
    ran = [o for o in outcomes if o.status in ("as written", "lowered")]
    assert ran and all(o.block.path == rr.SDFSTUDIO_PAGE for o in ran), text
    assert all(o.detail for o in outcomes if o.status == "skipped"), text


def test_every_flag_the_sdfstudio_section_names_exists(tmp_path):
    """The page's prose names flags too (a resume, the geo-* methods, meshing): each is a flag of
    sdfstudio's commands as sp-sdfstudio-train / ns-extract-mesh print them (the README once named
    ``--max-num-iterations``, which sdfstudio spells ``--trainer.max-num-iterations``)."""
    import re

    from tests.helpers.sdf_configs import run

    section = rr.SDFSTUDIO_PAGE.read_text()
    section = re.sub(r"<!-- readme-runner: skip .*?\n```.*?\n```", "", section, flags=re.S)  # pip lines
    # our own `python -m sp_plugins...` commands named in the prose have their own tests (the method table's --write)
    section = re.sub(r"`python -m sp_plugins[^`]*`", "", section)
    named = set(re.findall(r"(?<![\w-])--[a-z][\w.-]*[a-z](?!\.\*|[\w.-])", section))  # not --a.b.* wildcards
    helps = ""
    for args in (["sp-sdfstudio-train", "sp-neus-facto", "--help"], ["sp-sdfstudio-train", "sp-neus-facto", "sdfstudio-data", "--help"],
                 ["sp-sdfstudio-extract-mesh", "--help"], ["ns-extract-mesh", "--help"]):
        helps += run(args, cwd=tmp_path, extra_env={"COLUMNS": "200"}).stdout  # (forked: tests/helpers/sdf_configs.py)
    known = set(re.findall(r"--[a-z][\w.-]*[a-z]", helps))
    assert named and named <= known, f"flags the sdfstudio section names that sdfstudio's commands lack: {sorted(named - known)}"
