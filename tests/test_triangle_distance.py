"""Point-to-surface distances through nearby samples' triangles, against brute force over all faces."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from ribpull_core.triangle_distance import closest_points, distance_to_surface, nearest_candidate_distance


def _brute_force(points: np.ndarray, mesh: trimesh.Trimesh) -> np.ndarray:
    """Distance to every face by trimesh's own closest-point routine, the minimum per point."""
    tri = mesh.triangles
    out = np.empty(len(points))
    for i, p in enumerate(points):
        q = trimesh.triangles.closest_point(tri, np.repeat(p[None], len(tri), axis=0))
        out[i] = np.linalg.norm(q - p, axis=1).min()
    return out


def _vf(tri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return tri.reshape(-1, 3), np.arange(3 * len(tri)).reshape(-1, 3)


def test_candidate_distance_matches_brute_force_in_every_region():
    mesh = trimesh.creation.icosphere(1, 10.0).apply_scale([1.0, 0.6, 1.4])  # 80 faces, uneven triangles
    rng = np.random.default_rng(0)
    # points near and far, inside and outside: every vertex, edge and face region gets hit
    points = np.concatenate([rng.normal(size=(300, 3)) * 12.0, mesh.vertices + rng.normal(size=(42, 3)) * 0.5])
    all_faces = np.tile(np.arange(len(mesh.faces)), (len(points), 1))
    got = nearest_candidate_distance(points, np.ascontiguousarray(mesh.triangles), all_faces)
    np.testing.assert_allclose(got, _brute_force(points, mesh), rtol=1e-9, atol=1e-9)


def test_closest_points_match_trimesh_in_every_region_and_on_degenerate_triangles():
    rng = np.random.default_rng(4)
    tri = rng.normal(size=(20_000, 3, 3)) * 5.0
    tri[:500, 1] = tri[:500, 0]                                  # a zero-length edge
    tri[500:1000, 2] = 0.5 * (tri[500:1000, 0] + tri[500:1000, 1])  # zero area: a segment
    tri[1000:1500, 1:] = tri[1000:1500, :1]                      # a point
    points = rng.normal(size=(20_000, 3)) * 8.0
    got = closest_points(points, tri)
    # the closest point itself may differ where a triangle is a segment or a point (ties), its
    # distance may not; elsewhere both are the one closest point
    want = trimesh.triangles.closest_point(tri[1500:], points[1500:])
    np.testing.assert_allclose(got[1500:], want, atol=1e-9)
    brute = np.array([np.linalg.norm(trimesh.triangles.closest_point(
        np.repeat(t[None], 1, 0), p[None]) - p) for t, p in zip(tri[:1500], points[:1500])])
    np.testing.assert_allclose(np.linalg.norm(got[:1500] - points[:1500], axis=1), brute, atol=1e-9)
    # on its triangle: the barycentric weights of the answer are in [0, 1]
    a, b, c = tri[1500:, 0], tri[1500:, 1], tri[1500:, 2]
    bary = trimesh.triangles.points_to_barycentric(np.stack([a, b, c], 1), got[1500:])
    assert bary.min() > -1e-6 and bary.max() < 1 + 1e-6


def test_degenerate_triangles_and_skipped_candidates():
    tri = np.array([[[0.0, 0, 0], [1, 0, 0], [2, 0, 0]],     # zero area: a segment from 0 to 2
                    [[5.0, 5, 5], [5, 5, 5], [5, 5, 5]]])    # a point
    points = np.array([[1.0, 1.0, 0.0], [3.0, 0.0, 0.0], [5.0, 5.0, 6.0]])
    got = nearest_candidate_distance(points, tri, np.array([[0, -1], [0, -1], [-1, 1]]))
    np.testing.assert_allclose(got, [1.0, 1.0, 1.0], atol=1e-12)
    # a zero-length edge (two corners at one place, as marching cubes and vertex moves leave): each
    # of the three edges in turn, with points in that edge's region, which raised ZeroDivisionError
    # inside the parallel loop and left those distances as whatever the memory held
    segment = np.array([[0.0, 0, 0], [0, 0, 0], [0, 2, 0]])
    probes = np.array([[1.0, 1.0, 0.0], [0.0, 1.0, -3.0], [0.0, 3.0, 0.0], [-1.0, -1.0, 0.0]])
    for roll in range(3):
        tri = np.ascontiguousarray(np.roll(segment, roll, axis=0)[None].repeat(4096, axis=0))
        got = nearest_candidate_distance(probes.repeat(1024, axis=0), tri, np.arange(4096)[:, None])
        np.testing.assert_allclose(got, np.repeat([1.0, 3.0, 1.0, np.sqrt(2.0)], 1024), atol=1e-12)


def test_distance_to_surface_is_exact_near_the_surface_and_bounded_far_from_it():
    mesh = trimesh.creation.icosphere(3, 20.0).apply_scale([1.0, 0.5, 1.0])  # 1280 faces, uneven
    samples, _ = trimesh.sample.sample_surface(mesh, 20_000, seed=1)
    rng = np.random.default_rng(2)
    near, _ = trimesh.sample.sample_surface(mesh, 400, seed=3)
    points = np.concatenate([near + rng.normal(size=near.shape) * 0.5,  # k centroids prove these
                             rng.normal(size=(100, 3)) * 60.0])         # these need the fallbacks
    got = distance_to_surface(points, mesh.triangles, k=16, block=128)
    true = _brute_force(points, mesh)
    np.testing.assert_allclose(got[:400], true[:400], rtol=1e-9, atol=1e-9)
    # far points: never short, and too long by at most the largest centroid-to-corner radius
    tri = mesh.triangles
    max_radius = np.linalg.norm(tri - tri.mean(axis=1, keepdims=True), axis=2).max()
    assert np.all(got >= true - 1e-9) and np.all(got <= true + max_radius)
    assert np.abs(got - true).max() < 0.5 * max_radius  # in practice much closer than the bound
    tiny = distance_to_surface(points, tri[:10])  # fewer triangles than k: all of them, exact
    np.testing.assert_allclose(tiny, _brute_force(points, trimesh.Trimesh(*_vf(tri[:10]))), atol=1e-9)
    to_samples, _ = cKDTree(samples).query(points)
    assert np.all(got <= to_samples + 1e-9)
    assert (to_samples - got)[:400].max() > 0.05  # the sampling error that measuring to triangles removes


def test_no_triangles_is_an_error():
    with pytest.raises(ValueError):
        distance_to_surface(np.zeros((1, 3)), np.zeros((0, 3, 3)))
