"""Surface metrics against shapes with known distances, compression and mesh summaries."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from ribpull_core.errors import RibPullInputError
from ribpull_core.fields import NeuralPullMLP
from ribpull_core.metrics import (
    compression_metrics,
    estimate_normals,
    mesh_summary,
    surface_metrics,
)
from ribpull_core.neighbours import morton_order
from ribpull_core.pointcloud import PointCloud

N = 200_000


@pytest.fixture(scope="module")
def spheres():
    # subdivision 6: 82k faces, chord error < 0.01 mm at r = 50 mm
    return trimesh.creation.icosphere(6, 50.0), trimesh.creation.icosphere(6, 51.0)


def test_identical_shapes_give_near_zero_distance(spheres):
    a, _ = spheres
    m = surface_metrics(a, a, n_samples=N, tau_mm=1.0)
    spacing = np.sqrt(a.area / N)  # ~0.4 mm: the floor of sample-to-sample distances
    assert m["cd_l1_sampled_mm"] < 0.5 * spacing
    assert 0.5 * spacing < m["hausdorff_sampled_mm"] < 4 * spacing  # the widest hole among the samples
    # measured to the surface, the floor is gone: every sample lies on the other mesh
    assert m["cd_l1_mm"] < 1e-3 and m["cd_l2_mm2"] < 1e-6 and m["hausdorff_mm"] < 0.02
    assert m["fscore"] == 1.0 and m["precision"] == 1.0 and m["recall"] == 1.0
    assert m["normal_consistency"] > 0.99
    assert m["n_samples"] == N == m["n_reference"]
    assert "cd_l1_paper" not in m


def test_one_millimetre_offset(spheres):
    a, b = spheres
    m = surface_metrics(a, b, n_samples=N, tau_mm=1.5)
    # the two polyhedra are 1 mm apart to within their chord error (< 0.01 mm)
    assert m["cd_l1_mm"] == pytest.approx(1.0, abs=0.02)
    assert m["cd_l2_mm2"] == pytest.approx(1.0, abs=0.04)
    assert 0.98 <= m["hausdorff_mm"] < 1.02
    assert m["cd_l1_mm"] < m["cd_l1_sampled_mm"] and 1.0 <= m["hausdorff_sampled_mm"] < 1.3
    assert m["fscore"] == 1.0
    assert m["normal_consistency"] > 0.99
    tight = surface_metrics(a, b, n_samples=N, tau_mm=0.5)
    assert tight["fscore"] < 0.01 and tight["precision"] < 0.01 and tight["recall"] < 0.01


def test_paper_units():
    a, b = trimesh.creation.icosphere(5, 50.0), trimesh.creation.icosphere(5, 52.0)
    k = 1.0 / 150.0  # half extent 150 mm
    m = surface_metrics(a, b, n_samples=50_000, paper_units_per_mm=k, seed=3)
    assert m["cd_l1_paper"] == pytest.approx(m["cd_l1_mm"] * k * 100)
    assert m["cd_l2_paper"] == pytest.approx(m["cd_l2_mm2"] * k * k * 1e4)
    assert m["hausdorff_paper"] == pytest.approx(m["hausdorff_mm"] * k * 100)
    assert m["cd_l1_paper"] == pytest.approx(2.0 / 150 * 100, rel=0.05)


def test_point_references_with_and_without_normals(spheres):
    a, b = spheres
    pts, fidx = trimesh.sample.sample_surface(b, 50_000, seed=7)
    est = estimate_normals(pts)
    assert np.abs(np.einsum("ij,ij->i", est, pts / np.linalg.norm(pts, axis=1, keepdims=True))).min() > 0.95
    bare = surface_metrics(a, pts, n_samples=50_000)
    cloud = surface_metrics(a, PointCloud(points=pts, normals=b.face_normals[fidx]), n_samples=50_000)
    for m in (bare, cloud):
        assert m["n_reference"] == 50_000
        assert m["cd_l1_mm"] == pytest.approx(1.0, abs=0.1)
        assert m["normal_consistency"] > 0.99
    assert cloud["cd_l1_mm"] == bare["cd_l1_mm"]  # normals change normal consistency only


def test_empty_prediction_is_degenerate():
    with pytest.raises(RibPullInputError) as err:
        surface_metrics(trimesh.Trimesh(), trimesh.creation.icosphere(2, 1.0), n_samples=100)
    assert err.value.code == "degenerate"


def test_compression_metrics_count_the_saved_tensors():
    net = NeuralPullMLP()
    n = sum(t.numel() for t in net.state_dict().values())
    m = compression_metrics(10_000_000, net)
    assert m["n_parameters"] == n and 450_000 < n < 475_000  # the paper's ~1.8 MB network
    assert m["weights_bytes_fp32"] == 4 * n and m["weights_bytes_fp16"] == 2 * n
    assert m["ratio_fp32"] == pytest.approx(4 * n / 1e7) and m["ratio_fp16"] == pytest.approx(2 * n / 1e7)
    assert compression_metrics(0, net)["ratio_fp32"] is None


def test_mesh_summary():
    s = mesh_summary(trimesh.creation.icosphere(5, 10.0))
    assert s["watertight"] and s["components"] == 1 and s["n_faces"] == 20 * 4**5
    assert s["volume_mm3"] == pytest.approx(4 / 3 * np.pi * 1000, rel=0.005)
    assert s["area_mm2"] == pytest.approx(4 * np.pi * 100, rel=0.005)
    two = trimesh.util.concatenate([trimesh.creation.box(), trimesh.creation.box().apply_translation([3, 0, 0])])
    assert mesh_summary(two)["components"] == 2
    opened = trimesh.creation.box()
    opened.update_faces(np.arange(len(opened.faces)) > 0)
    assert mesh_summary(opened)["watertight"] is False and mesh_summary(opened)["volume_mm3"] is None


def test_mesh_summary_matches_trimesh():
    sphere = trimesh.creation.icosphere(4, 10.0)
    boxes = trimesh.util.concatenate([trimesh.creation.box(), trimesh.creation.box().apply_translation([3, 0, 0])])
    opened = trimesh.Trimesh(sphere.vertices, sphere.faces[5:], process=False)
    # two cubes sharing one edge: that edge has four faces, so it joins nothing and is not watertight
    a = trimesh.creation.box()
    b = trimesh.creation.box().apply_translation([1, 1, 0])
    pinched = trimesh.Trimesh(np.vstack([a.vertices, b.vertices]), np.vstack([a.faces, b.faces + 8]), process=True)
    for m in (sphere, boxes, opened, pinched):
        s = mesh_summary(m)
        assert s["n_vertices"] == len(m.vertices) and s["n_faces"] == len(m.faces)
        assert s["watertight"] == m.is_watertight
        assert s["components"] == len(trimesh.graph.connected_components(m.face_adjacency, nodes=np.arange(len(m.faces))))
        assert s["area_mm2"] == pytest.approx(m.area, rel=1e-12)
        assert (s["volume_mm3"] is None) if not m.is_watertight else s["volume_mm3"] == pytest.approx(m.volume, rel=1e-9)
    assert mesh_summary(pinched)["components"] == 2 and not mesh_summary(pinched)["watertight"]


def test_morton_order_follows_the_z_curve_and_keeps_ties_in_input_order():
    # 1024 cells per axis over the longest side: x is the lowest bit, then y, then z
    pts = np.array([[1.0, 1, 1], [0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, 0]])
    order = morton_order(pts)
    assert order.dtype == np.int64
    np.testing.assert_array_equal(order, [1, 5, 2, 3, 4, 0])  # the two origins keep their order
    rng = np.random.default_rng(3)
    cloud = rng.normal(size=(5000, 3))
    o = morton_order(cloud)
    np.testing.assert_array_equal(np.sort(o), np.arange(5000))  # a permutation
    assert len(morton_order(np.zeros((0, 3)))) == 0


def test_estimate_normals_of_a_plane_and_too_few_points():
    rng = np.random.default_rng(4)
    pts = np.c_[rng.random((500, 2)) * 10, np.zeros(500)]
    np.testing.assert_allclose(np.abs(estimate_normals(pts)[:, 2]), 1.0, atol=1e-9)
    with pytest.raises(RibPullInputError):
        estimate_normals(pts[:2])


def test_surface_metrics_in_halves_on_two_threads_give_the_same_numbers(spheres):
    """The pipeline's surface metrics: the reference made beforehand (metrics.reference_samples),
    then completeness_mm and prediction_samples on whichever of two threads gets to each first
    (pipeline._SurfaceMetricsWork): the same dict as one surface_metrics call, for a point
    reference and a mesh reference."""
    import threading
    from concurrent.futures import Future
    from types import SimpleNamespace

    from ribpull_core.frame import UnitFrame
    from ribpull_core.metrics import reference_samples
    from ribpull_core.pipeline import _Reporter, _SurfaceMetricsWork

    a, b = spheres
    pts = np.asarray(b.vertices)  # 41k points on the 51 mm sphere
    frame = UnitFrame.fit(np.asarray(a.vertices))
    config = SimpleNamespace(seed=4, metrics=SimpleNamespace(n_samples=20_000, fscore_tau_mm=0.5))
    for reference in (pts, b):
        ready: Future = Future()
        ready.set_result(reference_samples(reference, n_samples=20_000, seed=4))
        timings: dict = {}
        work = _SurfaceMetricsWork(a, ready, frame, config, timings, _Reporter(None, None))
        other = threading.Thread(target=work.run_untaken)
        other.start()
        got = work.result()
        other.join()
        want = surface_metrics(a, reference, n_samples=20_000, tau_mm=0.5, seed=4,
                               paper_units_per_mm=frame.paper_units_per_mm)
        assert got == want
        assert 0.9 < want["cd_l1_mm"] < 1.1 and timings["metrics"] >= 0.0  # the spheres are 1 mm apart
