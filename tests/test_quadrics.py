"""Local quadric patches (ribpull_core.quadrics): projections land on the sampled surface, closer
than the nearest noisy sample, and bad patches fall back to the samples."""

import numpy as np
from scipy.spatial import cKDTree

from ribpull_core.quadrics import fit_local_quadrics, project_onto_blended_quadrics, project_onto_quadrics


def _sphere(n: int, radius: float, noise: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    d = rng.standard_normal((n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d * (radius + noise * rng.standard_normal((n, 1)))


def test_projection_denoises_a_noisy_sphere():
    radius, noise = 10.0, 0.1  # mm; 8000 samples: ~0.4 mm apart
    pts = _sphere(8000, radius, noise, seed=0)
    queries = _sphere(4000, radius, 0.3, seed=1)  # queries up to ~1 mm off the surface
    nearest = cKDTree(pts).query(queries)[1]
    target = project_onto_quadrics(queries, nearest, fit_local_quadrics(pts, k=20))
    err_patch = np.abs(np.linalg.norm(target, axis=1) - radius)
    err_sample = np.abs(np.linalg.norm(pts[nearest], axis=1) - radius)
    assert err_sample.mean() > 0.07  # the noise itself (0.1 mm std: mean |e| ~0.08)
    assert err_patch.mean() < 0.5 * err_sample.mean()
    # the target is under the query (along the normal), not a sample's tangential position
    tangential = np.linalg.norm(np.cross(target / np.linalg.norm(target, axis=1, keepdims=True),
                                         queries / np.linalg.norm(queries, axis=1, keepdims=True)), axis=1)
    assert np.median(tangential) < 0.01


def test_exact_on_a_noiseless_quadric_surface():
    rng = np.random.default_rng(2)
    uv = rng.uniform(-1, 1, (3000, 2))
    height = 0.3 * uv[:, 0] ** 2 - 0.2 * uv[:, 0] * uv[:, 1] + 0.1 * uv[:, 1] ** 2
    pts = np.column_stack([uv, height])
    q_uv = rng.uniform(-0.8, 0.8, (500, 2))
    q_h = 0.3 * q_uv[:, 0] ** 2 - 0.2 * q_uv[:, 0] * q_uv[:, 1] + 0.1 * q_uv[:, 1] ** 2
    queries = np.column_stack([q_uv, q_h + rng.uniform(-0.02, 0.02, 500)])
    nearest = cKDTree(pts).query(queries)[1]
    target = project_onto_quadrics(queries, nearest, fit_local_quadrics(pts, k=16))
    t_h = 0.3 * target[:, 0] ** 2 - 0.2 * target[:, 0] * target[:, 1] + 0.1 * target[:, 1] ** 2
    assert np.abs(target[:, 2] - t_h).max() < 1e-3


def test_far_projections_fall_back_to_the_samples():
    # two sheets 0.05 apart in every neighbourhood: the patch is the mid-plane, no sheet's surface
    rng = np.random.default_rng(3)
    xy = rng.uniform(0, 1, (4000, 2))
    pts = np.column_stack([xy, np.where(np.arange(4000) % 2 == 0, 0.0, 0.05)])
    patches = fit_local_quadrics(pts, k=40)
    queries = pts[:200] + [0.0, 0.0, 0.002]
    nearest = cKDTree(pts).query(queries)[1]
    plain = project_onto_quadrics(queries, nearest, patches)
    shift = np.linalg.norm(plain - pts[nearest], axis=1)
    far = shift > 0.015
    assert far.mean() > 0.2  # many patches describe neither sheet
    guarded = project_onto_quadrics(queries, nearest, patches, fallback=pts[nearest], max_shift=0.015)
    np.testing.assert_allclose(guarded[far], pts[nearest][far])
    np.testing.assert_allclose(guarded[~far], plain[~far])


def test_patches_across_both_sides_of_a_thin_plate_are_not_used():
    # a 0.01-thick plate (thinner than a patch) sampled on both faces, normals out of each face
    rng = np.random.default_rng(4)
    xy = rng.uniform(0, 1, (4000, 2))
    top = np.arange(4000) % 2 == 1
    pts = np.column_stack([xy, np.where(top, 0.01, 0.0)])
    normals = np.zeros_like(pts)
    normals[:, 2] = np.where(top, 1.0, -1.0)
    thin = fit_local_quadrics(pts, k=20, normals=normals)
    assert not thin.one_sided.any()
    queries = pts[:100] + [0.0, 0.0, 0.001]
    kept = project_onto_quadrics(queries, np.arange(100), thin, fallback=pts[:100])
    np.testing.assert_allclose(kept, pts[:100])
    # one face alone: every patch is one-sided and used
    face = fit_local_quadrics(pts[~top], k=20, normals=normals[~top])
    assert face.one_sided.all()


def test_facing_counts_the_neighbours_whose_normals_agree():
    rng = np.random.default_rng(5)
    pts = np.column_stack([rng.uniform(0, 1, (2000, 2)), np.zeros(2000)])
    normals = np.tile([0.0, 0.0, 1.0], (2000, 1))
    normals[7] *= -1  # one flipped normal: every patch holding point 7 has one neighbour facing away
    patches = fit_local_quadrics(pts, k=20, normals=normals)
    _, nn = cKDTree(pts).query(pts, k=20)
    holds = (nn == 7).any(axis=1) & (np.arange(2000) != 7)
    np.testing.assert_allclose(patches.facing[holds], 19 / 20)
    assert not patches.one_sided[holds].any() and patches.one_sided[~holds & (np.arange(2000) != 7)].all()
    assert patches.facing[7] == 1 / 20  # its own normal faces only itself


def test_blended_projection_matches_the_numpy_formula():
    pts = _sphere(20_000, 50.0, 0.3, 4)
    tree = cKDTree(pts)
    patches = fit_local_quadrics(pts, 16, tree=tree)
    rng = np.random.default_rng(6)
    queries = _sphere(3000, 50.0, 0.0, 7) * rng.uniform(0.97, 1.03, (3000, 1))  # near the surface, both sides
    for blend in (1, 5, 8, 12):  # below, at and past numpy's eight running sums
        dist, nn = tree.query(queries, k=blend)
        dist, nn = dist.reshape(len(queries), blend), nn.reshape(len(queries), blend)
        d = queries[:, None] - patches.centre[nn]
        e1, e2, normal = (patches.frame[:, i] for i in range(3))
        u, v = (d * e1[nn]).sum(-1), (d * e2[nn]).sum(-1)
        terms = np.stack([np.ones_like(u), u, v, u * u, u * v, v * v], axis=-1)
        step = np.einsum("cbi,cbi->cb", terms, patches.coef[nn]) - (d * normal[nn]).sum(-1)
        weight = np.exp(-(dist / np.maximum(patches.radius[nn], 1e-12)) ** 2)
        want = queries + (weight[..., None] * step[..., None] * normal[nn]).sum(1) / weight.sum(1)[:, None]
        got = project_onto_blended_quadrics(queries, patches, tree, blend=blend, chunk=1000)
        # the compiled sums follow numpy's order (equal to the bit on the machine it was measured on)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-11)
    moved = np.linalg.norm(got, axis=1)
    assert np.abs(moved - 50.0).max() < np.abs(np.linalg.norm(queries, axis=1) - 50.0).max()  # pulled onto the sphere
    assert project_onto_blended_quadrics(np.zeros((0, 3)), patches, tree).shape == (0, 3)
