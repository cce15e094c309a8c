import os

# Two processes with two torch threads each slow this 2-core machine down more than tenfold.
os.environ.setdefault("OMP_NUM_THREADS", "1")

import torch

torch.set_num_threads(int(os.environ.get("SP_TEST_THREADS", "1")))


def _import_nerfstudios_external_module_here() -> None:
    """nerfstudio 1.x's ``utils.external`` keeps the ImportError of a missing tiny-cuda-nn in a module
    global, and its traceback every frame that was importing it, locals included, for the life of the
    process. Imported first inside a test, it would keep that test's model alive, and with it the
    patches the model holds (``registry.hold``), for every later test of the worker. Imported here, it
    keeps this function's frame. (Not in sdfstudio's environment: its ``nerfstudio`` has no such module.)"""
    import importlib.util

    spec = importlib.util.find_spec("nerfstudio")  # (a top-level spec imports nothing)
    if spec is not None and spec.origin and (Path(spec.origin).parent / "utils" / "external.py").is_file():
        import nerfstudio.utils.external  # noqa: F401


# -- disk: a test's large checkpoints go when the test is done ------------------------------------
from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

_import_nerfstudios_external_module_here()

LARGE_BYTES = 4 * 2**20
"""Checkpoint-like files above this size are removed from a test's ``tmp_path`` after the test (the
257^3 ReLU-field presets write about 2.6 GB per checkpoint; one suite run used to leave ~6.4 GB)."""
LARGE_SUFFIXES = (".ckpt", ".pt", ".pth", ".npy", ".npz", ".safetensors")


def remove_large_files(root: Path, limit: int = LARGE_BYTES, suffixes=LARGE_SUFFIXES) -> list:
    """Delete files under ``root`` ending in one of ``suffixes`` and larger than ``limit`` bytes; the removed paths."""
    removed = []
    if not root.is_dir():
        return removed
    for path in root.rglob("*"):
        try:
            if path.suffix in suffixes and path.is_file() and not path.is_symlink() and path.stat().st_size > limit:
                path.unlink()
                removed.append(path)
        except OSError:  # a file that went meanwhile, or one we may not remove: leave it
            pass
    return removed


@pytest.fixture(autouse=True)
def _remove_large_checkpoints_after_the_test(request):
    """Runs after every test that has a ``tmp_path`` (all its assertions are done by then): its large
    checkpoints are removed, the small files stay for inspection. ``SP_TEST_KEEP_LARGE=1`` keeps them."""
    # the test asks for tmp_path anyway; asking here first only fixes the order (ours is torn down last)
    tmp_path = request.getfixturevalue("tmp_path") if "tmp_path" in request.fixturenames else None
    yield
    if tmp_path is not None and not os.environ.get("SP_TEST_KEEP_LARGE"):
        remove_large_files(Path(tmp_path))


# -- order: the slowest files first ---------------------------------------------------------------
SLOW_FIRST = (
    "test_readme.py",  # every README block, lowered (the longest file: minutes)
    "sweeps/test_sweep_fit.py", "test_wheel.py", "nerfstudio/test_with_sp.py",
    "nerfstudio/test_ns_commands.py", "nerfstudio/test_viewer_browser.py", "cli/test_demo.py", "bench/test_failure_regime.py",
    "nerfstudio/test_kill_resume.py",
    "nerfstudio/test_bad_input_ns.py", "nerfstudio/test_safe_config_ns.py", "nerfstudio/test_multiprocess.py",
    "nerfstudio/test_relu_field_thr3ed.py", "nerfstudio/test_real_capture.py", "bench/test_gpu_check.py",
    "cli/test_fuzz_inputs.py", "nerfstudio/test_sp_option_matrix.py", "nerfstudio/test_viewer_walk.py",
    "nerfbaselines/test_nerfbaselines.py", "nerfstudio/test_method_table.py",
    # (2026-12-05's --durations=0: files of 20 s or more on 2 idle cores that were not listed)
    "nerfstudio/test_ns_reduced_config.py", "nerfstudio/test_ns_cli_smoke.py", "cli/test_device_flags.py",
    "patches/test_nerfstudio_external_methods_patch.py", "encodings/test_hashgrid.py", "tasks/test_fit_resume.py",
    "patches/test_registry.py", "nerfstudio/test_guest.py",
)
"""Files of half a minute or more (``--durations`` of the CI run, 2026-12-04). ``./run.sh test`` hands whole files to
pytest-xdist workers in collection order (``--no-loadscope-reorder``: by default xdist starts with the
files of most tests); a slow file drawn last would run alone at the end."""


def pytest_collection_modifyitems(config, items):
    if not hasattr(config, "workerinput"):
        return  # one process (not an xdist worker): the order given stands (the mutation study's cheapest-first files)
    here = Path(__file__).resolve().parent

    def rank(item):
        try:
            name = Path(item.path).resolve().relative_to(here).as_posix()
        except ValueError:
            return len(SLOW_FIRST)
        return SLOW_FIRST.index(name) if name in SLOW_FIRST else len(SLOW_FIRST)

    items.sort(key=rank)  # stable: a file's tests keep their order
