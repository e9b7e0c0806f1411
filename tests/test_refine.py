"""Vertex refinement onto the input points (ribpull_core.refine): a perturbed mesh of a noisy
sphere comes back onto the true sphere with its faces untouched; a sparse input is left alone; a
vertex with no surface under it is not projected, and faired between its neighbours when the faces
are given; the run presets switch it on (default, smoke) and off (paper)."""

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from ribpull_core.config import RefineConfig
from ribpull_core.methods import build_fit_config
from ribpull_core.refine import (
    fair_vertices,
    patch_size,
    plan_refinement,
    refine_vertices,
    refinement_patches,
)

RADIUS_MM = 20.0


def _sphere_points(n: int, noise_mm: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    d = rng.standard_normal((n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d * (RADIUS_MM + noise_mm * rng.standard_normal((n, 1)))


def _perturbed_sphere_mesh(offset_mm: float, seed: int) -> trimesh.Trimesh:
    """An icosphere whose vertices sit up to offset_mm off the true radius (a field's smoothing error)."""
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=RADIUS_MM)
    rng = np.random.default_rng(seed)
    v = mesh.vertices * (1.0 + rng.uniform(-offset_mm, offset_mm, (len(mesh.vertices), 1)) / RADIUS_MM)
    return trimesh.Trimesh(v, mesh.faces, process=False)


def _radial_error(v: np.ndarray) -> np.ndarray:
    return np.abs(np.linalg.norm(v, axis=1) - RADIUS_MM)


def test_refinement_brings_a_perturbed_mesh_onto_the_sampled_surface():
    pts = _sphere_points(8000, 0.3, seed=0)  # ~0.45 mm apart, 0.3 mm noise
    mesh = _perturbed_sphere_mesh(0.4, seed=1)
    out, summary = refine_vertices(mesh.vertices, pts, RefineConfig())
    assert summary["applied"] is True and summary["moved_fraction"] > 0.95, summary
    before, after = _radial_error(mesh.vertices).mean(), _radial_error(out).mean()
    assert before > 0.15 and after < 0.45 * before, (before, after)
    # the noise of the samples is averaged away: the refined surface beats the samples themselves
    assert after < 0.5 * _radial_error(pts).mean()
    assert out.shape == mesh.vertices.shape and np.isfinite(out).all()


def test_patches_made_beforehand_refine_the_same():
    pts = _sphere_points(8000, 0.3, seed=0)
    mesh = _perturbed_sphere_mesh(0.4, seed=1)
    config = RefineConfig()
    plan = plan_refinement(pts, config)
    tree, patches = refinement_patches(pts, plan)
    assert len(patches.centre) == len(pts)
    here, s_here = refine_vertices(mesh.vertices, pts, config, plan, faces=mesh.faces)
    before, s_before = refine_vertices(mesh.vertices, pts, config, plan, tree=tree, faces=mesh.faces, patches=patches)
    np.testing.assert_array_equal(before, here)
    assert s_before == s_here and s_here["moved_fraction"] > 0.9


def test_patch_size_follows_the_radius_within_its_bounds():
    pts = _sphere_points(8000, 0.0, seed=0)
    tree, probe = cKDTree(pts), np.arange(0, len(pts), 4)
    k, r = patch_size(pts, RefineConfig(radius_mm=2.0), tree, probe)
    assert RefineConfig().min_neighbours < k < RefineConfig().max_neighbours and r <= 2.0 + 1e-9
    k_small, r_small = patch_size(pts, RefineConfig(radius_mm=0.1), tree, probe)  # fewer than the minimum inside
    assert k_small == RefineConfig().min_neighbours and r_small > 0.1
    k_big, _ = patch_size(pts, RefineConfig(radius_mm=10.0), tree, probe)  # hundreds inside: capped
    assert k_big == RefineConfig().max_neighbours


def test_noisy_input_is_left_as_meshed_and_says_why():
    pts = _sphere_points(8000, 2.0, seed=0)  # 2 mm noise: ~0.3 mm of it would stay in a 32-point patch
    plan = plan_refinement(pts, RefineConfig())
    assert plan.applies is False and "too noisy" in plan.reason
    assert plan.patch_residual_mm / np.sqrt(plan.neighbours) > RefineConfig().max_patch_noise_mm
    mesh = _perturbed_sphere_mesh(0.4, seed=1)
    out, summary = refine_vertices(mesh.vertices, pts, RefineConfig(), plan)
    assert summary["applied"] is False and summary["reason"] == plan.reason
    np.testing.assert_array_equal(out, mesh.vertices)


def test_noise_that_a_patch_averages_out_is_refined():
    pts = _sphere_points(8000, 1.0, seed=0)  # 1 mm noise, but 32 samples per 4 mm patch
    plan = plan_refinement(pts, RefineConfig())
    assert plan.applies is True and plan.neighbours == RefineConfig().max_neighbours, plan.summary()
    assert plan.patch_residual_mm > 0.5  # what the residual alone would have called too noisy
    mesh = _perturbed_sphere_mesh(1.0, seed=1)  # a field that followed the noise: ~0.5 mm off
    out, _ = refine_vertices(mesh.vertices, pts, RefineConfig(), plan, faces=mesh.faces)
    after = _radial_error(out).mean()
    assert after < 0.6 * _radial_error(mesh.vertices).mean() and after < 0.4 * _radial_error(pts).mean()


def test_sparse_input_is_left_as_meshed_and_says_why():
    pts = _sphere_points(300, 0.3, seed=0)  # ~4 mm apart: 13 samples spread over ~8 mm
    mesh = _perturbed_sphere_mesh(0.4, seed=1)
    out, summary = refine_vertices(mesh.vertices, pts, RefineConfig())
    assert summary["applied"] is False and "too sparse" in summary["reason"]
    assert summary["patch_radius_mm"] > RefineConfig().max_radius_mm
    np.testing.assert_array_equal(out, mesh.vertices)


def test_a_vertex_with_no_surface_under_it_stays_put():
    pts = _sphere_points(8000, 0.0, seed=0)
    mesh = _perturbed_sphere_mesh(0.0, seed=1)
    v = mesh.vertices.copy()
    v[0] *= (RADIUS_MM + 5.0) / RADIUS_MM  # 5 mm out: a projection would move it ~11 sampling gaps
    out, summary = refine_vertices(v, pts, RefineConfig())
    np.testing.assert_array_equal(out[0], v[0])
    assert summary["moved_fraction"] < 1.0
    assert _radial_error(out[1:]).max() < 0.05


def test_a_bump_the_points_do_not_support_is_faired_into_the_surface():
    pts = _sphere_points(8000, 0.0, seed=0)
    mesh = _perturbed_sphere_mesh(0.0, seed=1)
    v = mesh.vertices.copy()
    ring = mesh.vertex_neighbors[0]
    v[[0, *ring]] *= (RADIUS_MM + 5.0) / RADIUS_MM  # a bump: a vertex and its ring 5 mm out
    out, summary = refine_vertices(v, pts, RefineConfig(), faces=mesh.faces)
    assert summary["faired_vertices"] == 1 + len(ring) and summary["moved_fraction"] < 1.0, summary
    assert _radial_error(out[[0, *ring]]).max() < 0.2  # back on the sphere, from 5 mm off
    assert _radial_error(out).max() < 0.2
    unfaired, _ = refine_vertices(v, pts, RefineConfig(fair_order=0), faces=mesh.faces)
    np.testing.assert_array_equal(unfaired[0], v[0])


@pytest.mark.parametrize("order", [1, 2])
def test_fairing_holds_the_other_vertices_and_leaves_a_wholly_free_component(order):
    a = trimesh.creation.icosphere(subdivisions=3, radius=10.0)
    b = trimesh.creation.icosphere(subdivisions=2, radius=3.0)
    b.apply_translation([30.0, 0, 0])
    both = trimesh.util.concatenate([a, b])
    v = both.vertices.copy()
    v[0] *= 1.3  # one vertex of the big sphere out of place
    free = np.zeros(len(v), dtype=bool)
    free[0] = True
    free[len(a.vertices):] = True  # every vertex of the small sphere: nothing holds it
    out, n = fair_vertices(v, both.faces, free, order=order)
    assert n == 1
    np.testing.assert_array_equal(out[1:], v[1:])
    assert abs(np.linalg.norm(out[0]) - 10.0) < 0.5 < abs(np.linalg.norm(v[0]) - 10.0)


@pytest.mark.parametrize("preset, on", [("default", True), ("smoke", True), ("paper", False)])
def test_run_presets_switch_refinement(preset, on):
    assert (build_fit_config(preset).refine is not None) is on
