"""Bad input to ``sp-fit``: each kind answered by the console script, run as a user runs
it, as one line naming the file or flag and what was expected, exit status 2, nothing written or
overwritten. Meshes the fits can still use (open, non-manifold, several parts, some degenerate
faces) are accepted with a warning line each, checked here in-process.

The nerfstudio commands' cases are in tests/nerfstudio/test_bad_input_ns.py; the table of all kinds
is in the README's troubleshooting section.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from trimesh.exchange.ply import export_ply

from tests.helpers.fs_faults import listing, make_read_only, undo_read_only

BIN = Path(sys.executable).parent
ENV = dict(os.environ, OMP_NUM_THREADS="1", OMP_WAIT_POLICY="PASSIVE")
TINY = ["--encoding.levels", "4", "--encoding.log2-table-size", "12", "--encoding.base-resolution", "8",
        "--encoding.max-resolution", "64", "--hidden", "16", "--mesh-resolution", "24", "--refine", "1",
        "--metric-points", "2000", "--steps", "3", "--quiet"]
POINTS = ["--n-points", "3000", "--surface-batch", "128", "--space-batch", "128"]
SDF = ["--batch", "64", "--pool", "2000"]


def write_cloud(path: Path, points, normals) -> Path:
    """An ASCII PLY point cloud with normals."""
    points, normals = np.asarray(points, float).reshape(-1, 3), np.asarray(normals, float).reshape(-1, 3)
    header = ("ply\nformat ascii 1.0\n"
              f"element vertex {len(points)}\n" + "".join(f"property float {k}\n" for k in ("x", "y", "z", "nx", "ny", "nz"))
              + "end_header\n")
    path.write_text(header + "".join(" ".join(f"{v:g}" for v in (*p, *n)) + "\n" for p, n in zip(points, normals)))
    return path


def write_mesh(path: Path, mesh: trimesh.Trimesh) -> Path:
    path.write_bytes(export_ply(mesh))
    return path





@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Every bad input through ``sp-fit``: ``name -> (result, out, before, after)``. Each runs as its own
    process, forked from a server that imported sp-fit once (``tests/helpers/forkserver.py``; an sp-fit
    start-up is 5-7 s here); the first case also runs as the real console script, to show the two agree."""
    from tests.helpers.forkserver import ForkServer

    root = tmp_path_factory.mktemp("bad-fit")
    sphere = write_mesh(root / "sphere.ply", trimesh.creation.icosphere(2))
    ico = trimesh.creation.icosphere(1)
    normals = ico.vertex_normals.copy()
    normals[5] = 0.0
    flat = trimesh.Trimesh(vertices=[[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]], faces=[[0, 1, 2], [1, 2, 3]], process=False)
    inputs = {
        "empty": write_cloud(root / "empty.ply", [], []),
        "coincident": write_cloud(root / "coincident.ply", np.ones((50, 3)), np.tile([0.0, 0.0, 1.0], (50, 1))),
        "zero-normals": write_cloud(root / "zero-normals.ply", ico.vertices, normals),
        "degenerate": write_mesh(root / "degenerate.ply", flat),
    }
    # a folder that holds an earlier run's results: a failed --overwrite must leave them as they were
    earlier = root / "earlier"
    earlier.mkdir()
    for name in ("mesh.ply", "metrics.json", "loss.png"):
        (earlier / name).write_text(f"the earlier run's {name}\n")
    read_only = root / "read-only"
    read_only_ok = make_read_only(read_only)
    plan = {
        "empty": (["pointcloud", inputs["empty"], *POINTS], root / "o-empty", None),
        "coincident": (["pointcloud", inputs["coincident"], *POINTS], root / "o-coincident", None),
        "zero-normals": (["pointcloud", inputs["zero-normals"], *POINTS], root / "o-zero", None),
        "degenerate": (["sdf", inputs["degenerate"], *SDF], root / "o-degenerate", None),
        "nan": (["sdf", sphere, *SDF, "--lr", "1e30"], root / "o-nan", None),
        "cuda-index": (["pointcloud", sphere, *POINTS, "--device", "cuda:7"], root / "o-cuda", None),
        "full-disk": (["pointcloud", sphere, *POINTS, "--overwrite"], earlier, 1000),  # writes past 1000 bytes fail
    }
    if read_only_ok:
        plan["read-only"] = (["pointcloud", sphere, *POINTS], read_only, None)
    before = {name: listing(out) for name, (_, out, _) in plan.items()}
    argv = {name: [*map(str, args), "--out", str(out), *TINY] for name, (args, out, _) in plan.items()}
    real = subprocess.Popen([str(BIN / "sp-fit"), *argv["empty"]], env=ENV, cwd=root, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    server = ForkServer(["sp-fit", "sp_plugins.geometry", "sp_plugins.tasks.common", "matplotlib.pyplot"], ENV)
    try:
        results = server.run([{"name": name, "script": "sp-fit", "args": argv[name], "cwd": str(root), "fsize": fsize}
                              for name, (_, _, fsize) in plan.items()], parallel=2)
        out, err = real.communicate(timeout=300)
    finally:
        server.close()
        if real.poll() is None:
            real.kill()
        if read_only_ok:
            undo_read_only(read_only)
    results["empty-real"] = {"name": "real sp-fit", "rc": real.returncode, "stdout": out, "stderr": err}
    plan["empty-real"] = plan["empty"]
    before["empty-real"] = before["empty"]
    return {name: (results[name], out, before[name], listing(out)) for name, (_, out, _) in plan.items()}


def refused(runs, name: str, *says: str) -> str:
    """Exit status 2, one line on stderr (``sp-fit: error: ...``; only ``sp-fit: warning:`` lines besides it)
    holding ``says``, and --out as it was."""
    result, out, before, after = runs[name]
    report = f"[{name}] rc={result['rc']}\n{result['stderr'][-3000:]}"
    assert result["rc"] == 2 and "Traceback" not in result["stderr"], report
    lines = [line for line in result["stderr"].strip().splitlines() if not line.startswith("sp-fit: warning: ")]
    assert len(lines) == 1 and lines[0].startswith("sp-fit: error: "), report
    for word in says:
        assert word in lines[0], f"{word!r} missing\n{report}"
    assert after == before, f"[{name}] --out changed: {sorted(set(after) ^ set(before)) or 'files rewritten'}"
    return lines[0]


def test_empty_point_cloud(runs):
    line = refused(runs, "empty", "empty.ply", "the file is empty", "expected a mesh or an oriented point cloud")
    assert refused(runs, "empty-real") == line  # the real console script says the same


def test_coincident_points(runs):
    refused(runs, "coincident", "coincident.ply", "all 50 points coincide", "expected points spread over a surface")


def test_zero_normals(runs):
    refused(runs, "zero-normals", "zero-normals.ply", "1 of 42 normals are zero", "point 5", "expected a direction")


def test_mesh_whose_faces_are_all_degenerate(runs):
    refused(runs, "degenerate", "degenerate.ply", "every face is degenerate", "expected a mesh with a surface")


def test_loss_turning_nan_stops_naming_the_step(runs):
    refused(runs, "nan", "step 1: the loss became", "lower --lr", "1e+30")


def test_cuda_index_that_does_not_exist(runs):
    if torch.cuda.is_available() and torch.cuda.device_count() > 7:
        pytest.skip("this machine has a cuda:7")
    refused(runs, "cuda-index", "--device cuda:7")


def test_read_only_out(runs):
    if "read-only" not in runs:
        pytest.skip("cannot make a read-only folder here (root without chattr +i)")
    refused(runs, "read-only", "--out", "read-only", "cannot write", "choose a writable output folder")


def test_full_disk_leaves_earlier_results_unchanged(runs):
    line = refused(runs, "full-disk", "--out", "earlier", "cannot write", "disk is full", "nothing was written")
    _, out, _, _ = runs["full-disk"]
    assert (out / "mesh.ply").read_text() == "the earlier run's mesh.ply\n", line


# -- meshes the fits accept, with a warning ---------------------------------------------------------


def _warnings(capsys, mesh, task, path="in.ply") -> str:
    from sp_plugins.cli.fit import _warn_about_topology

    _warn_about_topology(Path(path), mesh, task)
    return capsys.readouterr().err


def test_closed_single_mesh_gets_no_warning(capsys):
    assert _warnings(capsys, trimesh.creation.icosphere(2), "pointcloud") == ""


@pytest.mark.parametrize("task, says", [("pointcloud", "expect the fit to close or thicken"), ("sdf", "sign of each distance")])
def test_open_mesh_is_accepted_with_a_warning(capsys, task, says):
    sphere = trimesh.creation.icosphere(2)
    half = trimesh.Trimesh(sphere.vertices, sphere.faces[sphere.triangles_center[:, 2] > 0])
    err = _warnings(capsys, half, task)
    assert err.count("\n") == 1 and err.startswith("sp-fit: warning: in.ply: not watertight (") and "boundary edges: it is open" in err
    assert says in err


def test_non_manifold_and_multi_part_meshes_are_accepted_with_warnings(capsys):
    a = trimesh.creation.icosphere(1)
    fin = trimesh.Trimesh(vertices=np.vstack([a.vertices, [[3.0, 3.0, 3.0]]]),  # a third face on one edge
                          faces=np.vstack([a.faces, [[a.faces[0][0], a.faces[0][1], len(a.vertices)]]]), process=False)
    err = _warnings(capsys, fin, "sdf")
    assert "edges shared by more than two faces: it is non-manifold" in err
    b = a.copy()
    b.apply_translation([3.0, 0.0, 0.0])
    err = _warnings(capsys, trimesh.util.concatenate([a, b]), "pointcloud")
    assert err.count("\n") == 1 and "2 separate parts: all are fitted; the clean_* metrics keep only the largest part" in err


def test_inconsistent_winding_is_named(capsys):
    sphere = trimesh.creation.icosphere(2)
    faces = np.array(sphere.faces)
    faces[:10] = faces[:10, ::-1]
    err = _warnings(capsys, trimesh.Trimesh(sphere.vertices, faces, process=False), "pointcloud")
    assert "not consistently oriented" in err and "normals sampled for the fit" in err


def test_some_degenerate_faces_are_dropped_with_a_warning(tmp_path, caplog):
    from sp_plugins.geometry import load_mesh

    sphere = trimesh.creation.icosphere(2)
    faces = np.vstack([sphere.faces, [[0, 0, 1], [2, 2, 2]]])
    path = write_mesh(tmp_path / "some-degenerate.ply", trimesh.Trimesh(sphere.vertices, faces, process=False))
    with caplog.at_level("WARNING"):
        mesh = load_mesh(path)
    assert len(mesh.faces) == len(sphere.faces) and (mesh.area_faces > 0).all()
    assert "dropped 2 degenerate faces (zero area) of 322" in caplog.text


def test_ascii_ply_normals_are_read(tmp_path):
    from sp_plugins.geometry import load_oriented_points

    ico = trimesh.creation.icosphere(1)
    data = load_oriented_points(write_cloud(tmp_path / "ascii.ply", ico.vertices, ico.vertex_normals))
    assert data.source == "file" and np.allclose(data.normals, ico.vertex_normals / np.linalg.norm(ico.vertex_normals, axis=1, keepdims=True), atol=1e-5)


# -- what the input-error hook recognizes in host code (ns-eval / ns-train run it; in-process here) ---


def _raised(fn):
    try:
        fn()
    except Exception as exc:  # noqa: BLE001
        return exc
    raise AssertionError("did not raise")


def test_hook_names_a_checkpoint_torch_cannot_read(tmp_path):
    from sp_plugins.adapter.errors import describe_failure

    path = tmp_path / "step-000000003.ckpt"
    torch.save({"w": torch.zeros(1000)}, path)
    path.write_bytes(path.read_bytes()[:700])
    message = describe_failure(_raised(lambda: torch.load(path, map_location="cpu")))
    assert message.startswith(f"{path}: cannot be read as a PyTorch checkpoint (") and "truncated or damaged" in message
    assert "\n" not in message


def test_hook_names_a_checkpoint_torch_could_not_write_and_removes_it(tmp_path):
    from sp_plugins.adapter.errors import describe_failure

    path = tmp_path / "step-000000004.ckpt"
    pid = os.fork()
    if pid == 0:  # a child with a file-size limit: the write fails as on a full disk
        import resource
        import signal

        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (1000, 1000))
        exc = _raised(lambda: torch.save({"w": torch.zeros(10000)}, path))
        message = describe_failure(exc)
        ok = message is not None and message.startswith(f"{path}: writing the checkpoint failed (") and not path.exists()
        os._exit(0 if ok else 1)
    _, status = os.waitpid(pid, 0)
    assert os.waitstatus_to_exitcode(status) == 0 and not path.exists()


def test_hook_names_a_file_it_could_not_write(tmp_path):
    import errno

    from sp_plugins.adapter.errors import describe_failure

    full = OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "eval.json"))
    assert describe_failure(full) == (f"{tmp_path / 'eval.json'}: cannot write (No space left on device); the disk is full "
                                      "(or a quota or file-size limit is reached): free space or write elsewhere")
    read_only = OSError(errno.EROFS, "Read-only file system", "/mnt/ro/eval.json")
    assert "the folder is read-only or not yours" in describe_failure(read_only)
    assert describe_failure(OSError(errno.ENOENT, "No such file or directory", "x")) is None  # not a write problem
    assert describe_failure(KeyError("x")) is None  # everything else keeps its traceback
