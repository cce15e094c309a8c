"""The patch registry: every entry is guarded, and after each scope the host is exactly
as it was.

For every entry that imports here (nerfstudio 1.x, torchmetrics and Python's own; the sdfstudio
entries have the same checks in ``tests/sdfstudio/test_patches.py``):

- its guard passes on the host installed here, and fails, in one line naming the patch, what it
  expected and the host version it found, when any attribute it names in ``guarded`` is something
  else (the attribute is replaced for the check, as a changed host would have it);
- its scope changes what it says it changes inside the block, and after the block every patched
  attribute, ``sys.excepthook``, ``warnings.filters`` (the same list, the same entries),
  ``dataclasses.dataclass``, ``sys.meta_path`` and every module that was in ``sys.modules`` are
  the objects they were.
"""

from __future__ import annotations

import dataclasses
import gc
import importlib
import importlib.util
import sys
import warnings

import pytest
import torch

pytest.importorskip("nerfstudio")

from sp_plugins.patches import registry
from sp_plugins.patches.registry import PatchGuardError
from tests.helpers.sp_fields import installed_for_process

HOSTS = ("nerfstudio", "python", "torchmetrics", "torch") + (("nerfbaselines",) if importlib.util.find_spec("nerfbaselines") else ())
ENTRIES = [p for p in registry.entries() if p.host in HOSTS]


@pytest.fixture(autouse=True)
def _collect_models_of_earlier_files():
    """A model built by an earlier test file in this process (an xdist worker runs many) may be
    cyclic garbage that still holds its patches (``registry.hold``) until the next collection."""
    gc.collect()


def test_the_registry_holds_every_patch_module():
    from pathlib import Path

    folder = Path(registry.__file__).parent
    modules = {p.stem for p in folder.glob("*.py")} - {"__init__", "registry"}
    assert modules <= set(registry.ENTRIES), sorted(modules - set(registry.ENTRIES))
    assert {p.name for p in ENTRIES} >= {"nerfstudio_external_methods", "nerfstudio_sdf_field", "nerfstudio_marching_cubes",
                                          "nerfstudio_lpips", "host_warnings", "input_error_hook"}
    for patch in registry.entries():
        assert patch.version and patch.changes and patch.scope_text and patch.guarded, patch.name


def test_the_docs_patch_table_has_one_row_per_entry_naming_its_host_version():
    """docs/extending.md's patch table is what a reader audits: a patch without its row is invisible."""
    import re
    from pathlib import Path

    page = (Path(__file__).resolve().parents[2] / "docs" / "extending.md").read_text()
    rows = dict(re.findall(r"^\| `(\w+)` \| ([^|]+) \|", page, flags=re.M))
    assert set(rows) == set(registry.ENTRIES), (sorted(set(registry.ENTRIES) - set(rows)), sorted(set(rows) - set(registry.ENTRIES)))
    for patch in registry.entries():
        assert patch.version in rows[patch.name], (patch.name, patch.version, rows[patch.name])


def resolve(dotted: str):
    try:
        return importlib.import_module(dotted)
    except ImportError:
        parent, _, name = dotted.rpartition(".")
        return getattr(importlib.import_module(parent), name)


@pytest.mark.parametrize("patch", ENTRIES, ids=lambda p: p.name)
def test_every_entry_is_guarded(patch, monkeypatch):
    patch.guard()  # the host installed here is the one it was written for
    for where, attr in patch.guarded:
        with monkeypatch.context() as m:
            m.setattr(resolve(where), attr, object())
            with pytest.raises(PatchGuardError) as failure:
                patch.guard()
        message = str(failure.value)
        assert "\n" not in message and f"patch {patch.name}:" in message, message
        assert f"written for {patch.host} {patch.version}" in message and "found" in message, message
    patch.guard()  # and the host is back


def host_state(patch) -> dict:
    state = {
        "excepthook": sys.excepthook,
        "filters": (warnings.filters, list(warnings.filters)),
        "dataclass": dataclasses.dataclass,
        "meta_path": list(sys.meta_path),
        "modules": dict(sys.modules),
        "cuda": (torch.cuda.synchronize, torch.cuda.set_device, torch.Tensor.cuda),
    }
    for where, attr in patch.guarded:
        owner = resolve(where)
        state[f"{where}.{attr}"] = vars(owner).get(attr) if isinstance(owner, type) else getattr(owner, attr)
    return state


def changed(before: dict, after: dict) -> list:
    found = []
    for key, value in before.items():
        if key == "modules":
            found += [name for name, module in value.items() if after["modules"].get(name) is not module]
        elif key == "filters":
            if after["filters"][0] is not value[0] or after["filters"][1] != value[1]:
                found.append("filters")
        elif key in ("meta_path",):
            if after[key] != value:
                found.append(key)
        elif isinstance(value, tuple):
            if any(a is not b for a, b in zip(value, after[key])):
                found.append(key)
        elif after[key] is not value:
            found.append(key)
    return found


ACTIVE = {  # inside the scope: what must be different
    "nerfstudio_external_methods": lambda: getattr(
        resolve("nerfstudio.configs.external_methods").ExternalMethodDummyTrainerConfig.__post_init__, "__sp_original__", None) is not None,
    "nerfstudio_parallel_seed": lambda: resolve("nerfstudio.data.datamanagers.parallel_datamanager").DataProcessor.__name__ == "build",
    "nerfstudio_sdf_field": lambda: type(resolve("nerfstudio.fields.sdf_field").tcnn).__name__ == "_TorchTcnnShim",
    "nerfstudio_marching_cubes": lambda: resolve("nerfstudio.exporter.marching_cubes").generate_mesh_with_multires_marching_cubes.__name__
    == "scoped_marching_cubes",
    "nerfstudio_lpips": lambda: hasattr(resolve("torchmetrics.image.lpip").LearnedPerceptualImagePatchSimilarity, "real"),
    "nerfbaselines_lpips": lambda: hasattr(resolve("nerfbaselines.metrics")._lpips, "real"),
    "host_warnings": lambda: any(getattr(f[1], "pattern", "").startswith("Using a non-tuple sequence") for f in warnings.filters),
    "torch_deterministic": lambda: torch.are_deterministic_algorithms_enabled(),
    "input_error_hook": lambda: getattr(sys.excepthook, "sp_plugins_input_errors", False),
}
ARGS = {"nerfstudio_marching_cubes": {"force": True}, "nerfstudio_sdf_field": {"force": True}}


@pytest.mark.parametrize("patch", ENTRIES, ids=lambda p: p.name)
def test_after_each_scope_the_host_is_as_it_was(patch, monkeypatch):
    monkeypatch.delenv("SP_HOST_WARNINGS", raising=False)
    assert patch.name not in registry.held() and patch.name not in installed_for_process()
    before = host_state(patch)
    with registry.scope(patch.name, **ARGS.get(patch.name, {})):
        assert ACTIVE[patch.name](), f"{patch.name}: the scope changed nothing"
    gc.collect()
    after = host_state(patch)
    assert changed(before, after) == [], patch.name
    assert not ACTIVE[patch.name]()


@pytest.mark.parametrize("patch", ENTRIES, ids=lambda p: p.name)
def test_a_scope_inside_its_own_scope_only_counts(patch, monkeypatch):
    """Re-entrance: a model's build inside sp-gpu-check's LPIPS scope enters it again; the guard runs
    at the outermost entry only, and the host is restored only after the outer exit (also when a
    held scope outlives the block it started in)."""
    monkeypatch.delenv("SP_HOST_WARNINGS", raising=False)
    assert patch.name not in registry.in_force()
    before = host_state(patch)
    args = ARGS.get(patch.name, {})
    with registry.scope(patch.name, **args) as outer:
        inside = host_state(patch)
        with registry.scope(patch.name, **args) as inner:
            assert inner is outer and ACTIVE[patch.name]()
            with registry.scope(patch.name, **args):
                assert changed(inside, host_state(patch)) == []
        assert ACTIVE[patch.name]() and changed(inside, host_state(patch)) == [], f"{patch.name}: left by the inner exit"
        assert registry.in_force().count(patch.name) == 1
    gc.collect()
    assert changed(before, host_state(patch)) == [] and not ACTIVE[patch.name](), patch.name
    assert patch.name not in registry.in_force()

    class Owner:
        pass

    owner = Owner()
    with registry.scope(patch.name, **args):
        registry.hold(patch.name, owner, **args)  # (inside the block: held past it)
    assert ACTIVE[patch.name](), f"{patch.name}: the hold ended with the block"
    with pytest.raises(ValueError):
        with registry.scope(patch.name, **args):
            raise ValueError("inside")
    assert ACTIVE[patch.name]()
    del owner
    gc.collect()
    assert changed(before, host_state(patch)) == [] and not ACTIVE[patch.name](), patch.name
    assert patch.name not in registry.in_force() and patch.name not in registry.held()


def test_a_nested_scope_enters_again_where_the_host_dropped_the_patch(monkeypatch):
    """sys.excepthook replaced while our hook is held (pytest's monkeypatch, another library): a
    scope inside that hold wraps the hook in force for its block, as an outermost one would."""
    from sp_plugins.adapter.errors import InputError

    class Owner:
        pass

    owner, seen = Owner(), []
    registry.hold("input_error_hook", owner)
    with monkeypatch.context() as m:
        m.setattr(sys, "excepthook", lambda *exc: seen.append(exc[0]))
        replaced = sys.excepthook
        with registry.scope("input_error_hook"):
            with pytest.raises(SystemExit):
                sys.excepthook(InputError, InputError("bad"), None)
        assert sys.excepthook is replaced and "input_error_hook" in registry.in_force()
    del owner
    gc.collect()
    assert "input_error_hook" not in registry.in_force()


def test_held_scopes_end_with_their_last_owner(monkeypatch):
    monkeypatch.delenv("SP_HOST_WARNINGS", raising=False)
    patch = registry.get("host_warnings")
    before = host_state(patch)

    class Owner:
        pass

    first, second = Owner(), Owner()
    assert registry.hold("host_warnings", first) and not registry.hold("host_warnings", second)
    del first
    gc.collect()
    assert ACTIVE["host_warnings"]()  # the second still holds it
    del second
    gc.collect()
    assert changed(before, host_state(patch)) == [] and not ACTIVE["host_warnings"]()


def test_only_our_commands_keep_a_patch_for_the_process():
    with pytest.raises(RuntimeError, match="only by our commands"):
        registry.install_for_process("host_warnings")  # pytest is not one of our commands
    with pytest.raises(RuntimeError, match="sp-train"):
        registry.install_for_process("nerfstudio_external_methods", command="sp-fit")
    assert "host_warnings" not in installed_for_process()


def test_what_a_command_keeps_for_its_process_ends_as_at_exit(monkeypatch):
    """``end_for_process`` (for tests that run a command's main in their own process) leaves the
    process as it was: the patched state restored, nothing counted as in force."""
    patch = registry.get("host_warnings")
    before = host_state(patch)
    monkeypatch.delenv("SP_HOST_WARNINGS", raising=False)
    was_in_force = "host_warnings" in registry.in_force()
    registry.install_for_process("host_warnings", command="sp-fit")
    assert "host_warnings" in installed_for_process() and ACTIVE["host_warnings"]()
    registry.end_for_process()
    assert "host_warnings" not in installed_for_process()
    assert ("host_warnings" in registry.in_force()) is was_in_force
    if not was_in_force:
        assert changed(before, host_state(patch)) == []


@pytest.mark.parametrize("outer", ["install_for_process", "scope"])
def test_a_guard_that_enters_its_own_patch_counts_it_once_per_entry(outer, monkeypatch):
    """sdfstudio's opt-in import hook: ``sdfstudio_import_hook``'s guard looks sdfstudio up, the lookup
    fires the hook, and the hook installs every sdfstudio patch for the process, that one included,
    before the outer entry has finished. The patch must be entered once and left once, and the process's
    end must not find it gone (it raised ``KeyError`` in the atexit handler of every sp-sdfstudio-*
    run and bench, and the nested entry's stack was dropped without being left)."""
    import contextlib
    import types

    events = []

    def check(patch):
        if not events:  # the hook fires once, on the first lookup
            events.append("guard")
            registry.install_for_process("reentrant_test_patch", command="sp-fit")

    @contextlib.contextmanager
    def enter():
        events.append("enter")
        try:
            yield "value"
        finally:
            events.append("exit")

    module = types.ModuleType("reentrant_test_patch_module")
    module.PATCH = registry.Patch(name="reentrant_test_patch", host="python", version="-", changes="-", scope_text="-",
                                  check=check, enter=enter, owned_commands=("sp-fit",))
    monkeypatch.setitem(sys.modules, module.__name__, module)
    monkeypatch.setitem(registry.ENTRIES, "reentrant_test_patch", module.__name__)
    try:
        if outer == "scope":
            with registry.scope("reentrant_test_patch") as value:
                assert value == "value" and events == ["guard", "enter"]
            assert "reentrant_test_patch" in registry.in_force()  # the process install still holds it
        else:
            assert registry.install_for_process("reentrant_test_patch", command="sp-fit") == "value"
        assert events == ["guard", "enter"]
    finally:
        registry.end_for_process()
    assert events == ["guard", "enter", "exit"]
    assert "reentrant_test_patch" not in registry.in_force()
