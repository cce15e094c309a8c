import numpy as np
import pytest
import trimesh

from sp_plugins.geometry import largest_component, mesh_metrics


@pytest.fixture(scope="module")
def sphere():
    return trimesh.creation.icosphere(5, radius=1.0)


def test_a_mesh_against_itself_is_at_the_sampling_floor(sphere):
    m = mesh_metrics(sphere, sphere, n_points=50_000)
    assert m["chamfer"] < 2.5e-3  # two independent samplings of 50k points
    assert m["fscore"] == 1.0
    assert m["normal_consistency"] > 0.999
    assert m["area_ratio"] == pytest.approx(1.0)
    again = mesh_metrics(sphere, sphere, n_points=50_000)
    assert again == m  # seeded


@pytest.mark.parametrize("offset", [0.05, 0.1])
def test_chamfer_grows_with_a_known_offset(sphere, offset):
    bigger = trimesh.creation.icosphere(5, radius=1.0 + offset)
    m = mesh_metrics(bigger, sphere, n_points=50_000, unit=1.0)
    # every point of one sphere is `offset` from the other (plus the sampling floor)
    assert m["chamfer"] == pytest.approx(offset, rel=0.05)
    assert m["accuracy"] == pytest.approx(offset, rel=0.05)
    assert m["completeness"] == pytest.approx(offset, rel=0.05)
    assert m["fscore"] == 0.0  # the offset exceeds the threshold (0.01)
    rel = mesh_metrics(bigger, sphere, n_points=50_000)  # default unit: the diagonal 2*sqrt(3)
    assert rel["chamfer"] == pytest.approx(m["chamfer"] / (2 * np.sqrt(3)), rel=0.02)


def test_floaters_raise_accuracy_only_and_cleanup_removes_them(sphere):
    floater = trimesh.creation.icosphere(3, radius=0.3)
    floater.apply_translation([2.5, 0.0, 0.0])
    noisy = trimesh.util.concatenate([sphere, floater])
    clean = mesh_metrics(sphere, sphere, n_points=50_000)
    dirty = mesh_metrics(noisy, sphere, n_points=50_000)
    assert dirty["accuracy"] > 5 * clean["accuracy"]
    assert dirty["completeness"] < 1.5 * clean["completeness"]
    assert dirty["precision"] < 1.0 and dirty["recall"] == 1.0
    kept = largest_component(noisy)
    assert len(kept.faces) == len(sphere.faces)
    assert mesh_metrics(kept, sphere, n_points=50_000)["accuracy"] < 1.5 * clean["accuracy"]


def test_normal_consistency_sees_a_rough_surface(sphere):
    rng = np.random.default_rng(0)
    rough = sphere.copy()
    rough.vertices = rough.vertices * (1 + 0.03 * rng.standard_normal((len(rough.vertices), 1)))
    assert mesh_metrics(rough, sphere, n_points=20_000)["normal_consistency"] < 0.95


def test_empty_prediction_and_bad_ground_truth(sphere):
    empty = trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64))
    m = mesh_metrics(empty, sphere, n_points=1000)
    assert m["chamfer"] == float("inf") and m["fscore"] == 0.0
    with pytest.raises(ValueError, match="no faces"):
        mesh_metrics(sphere, empty)
    with pytest.raises(ValueError, match="unit"):
        mesh_metrics(sphere, sphere, unit=0.0)
