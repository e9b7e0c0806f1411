"""The noise bias of a fit to noisy points and its removal (ribpull_core.curvature_bias): the implicit
mean-curvature flow moves a sphere inward by 2 H t (and nothing for t = 0); the noise
estimate from quadric patch residuals recovers the std of the samples' noise; points with
isotropic noise sit sigma^2 H outside a sphere, and the flow the pipeline applies takes that off;
the refinement plan tells a too-noisy input from a too-sparse one."""

import numpy as np
import trimesh

from ribpull_core.config import RefineConfig, SectionQuadricConfig, TubePatchConfig
from ribpull_core.curvature_bias import (
    cotangent_laplacian,
    mean_curvature_flow,
    normal_noise_mm,
    remove_noise_bias,
    reverse_curvature_flow,
)
from ribpull_core.pointcloud import PointCloud, mask_boundary_cloud
from ribpull_core.refine import plan_refinement, refine_vertices

RADIUS_MM = 20.0
#: the sampled sphere: 10k points on it are ~0.7 mm apart, and a patch spans ~4 mm (as at the
#: bench's 60k points on the phantom), 4x the largest noise below (narrower patches fit the noise)
SAMPLED_RADIUS_MM = 40.0


def _sphere_points(n: int, noise_mm: float, seed: int) -> np.ndarray:
    """n samples of the SAMPLED_RADIUS_MM sphere, each moved by isotropic 3-D Gaussian noise of std noise_mm."""
    rng = np.random.default_rng(seed)
    d = rng.standard_normal((n, 3))
    d *= SAMPLED_RADIUS_MM / np.linalg.norm(d, axis=1, keepdims=True)
    return d + noise_mm * rng.standard_normal((n, 3))


def test_cotangent_laplacian_gives_a_sphere_its_curvature_and_area():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=RADIUS_MM)
    laplacian, mass = cotangent_laplacian(sphere.vertices, sphere.faces)
    area = mass.diagonal()
    assert abs(area.sum() - sphere.area) < 1e-6 * sphere.area
    assert abs(laplacian - laplacian.T).max() < 1e-12
    assert np.abs(laplacian @ np.ones(len(area))).max() < 1e-9  # constants have no Laplacian
    mean_curvature_normal = laplacian @ sphere.vertices / area[:, None]  # 2 H n, outward on a sphere
    along = np.einsum("ij,ij->i", mean_curvature_normal, sphere.vertices / RADIUS_MM)
    # the lumped (barycentric) mass is not a Voronoi area: single vertices scatter by ~15 %
    assert abs(along.mean() - 2.0 / RADIUS_MM) < 0.005 * 2.0 / RADIUS_MM, along.mean()
    assert np.allclose(along, 2.0 / RADIUS_MM, rtol=0.2), (along.min(), along.max())
    # positive semi-definite on a marching-cubes-like mesh with obtuse triangles too
    noisy = sphere.vertices + np.random.default_rng(0).normal(0, 0.3, sphere.vertices.shape)
    skewed, _ = cotangent_laplacian(noisy, sphere.faces)
    x = np.random.default_rng(1).standard_normal(len(noisy))
    assert x @ (skewed @ x) >= 0


def test_flow_moves_a_sphere_inward_by_twice_its_mean_curvature_times_t():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=RADIUS_MM)
    t = 2.0  # mm^2: 2 H t = 2 * t / R = 0.2 mm
    radii = np.linalg.norm(mean_curvature_flow(sphere.vertices, sphere.faces, t), axis=1)
    expected = RADIUS_MM * np.sqrt(1.0 - 4.0 * t / RADIUS_MM**2)  # exact shrink of a sphere: dR^2/dt = -4
    assert abs(radii.mean() - expected) < 0.02, radii.mean()
    assert radii.std() < 0.01
    assert np.array_equal(mean_curvature_flow(sphere.vertices, sphere.faces, 0.0), sphere.vertices)
    grown = np.linalg.norm(reverse_curvature_flow(sphere.vertices, sphere.faces, t), axis=1)
    assert abs(grown.mean() - (RADIUS_MM + 2.0 * t / RADIUS_MM)) < 0.02, grown.mean()  # outward by 2 H t
    assert grown.std() < 0.01


def test_noise_estimate_from_the_patch_residual_recovers_the_noise():
    config = RefineConfig()
    for noise in (0.3, 0.5, 1.0):
        plan = plan_refinement(_sphere_points(10_000, noise, seed=1), config)
        sigma = normal_noise_mm(plan.patch_residual_mm, plan.neighbours)
        assert abs(sigma - noise) < 0.1 * noise, (noise, sigma, plan)
        # the raw residual alone is the noise's (k - 6) / k of it: 6 % - 13 % low
        assert plan.patch_residual_mm < 0.95 * sigma


def test_the_flow_takes_the_noise_offset_off_a_surface_fitted_through_noisy_points():
    noise = 1.0
    # the offset the noise puts on the sphere: sigma^2 H = sigma^2 / R outward (the samples' mean radius)
    offset = np.linalg.norm(_sphere_points(400_000, noise, seed=2), axis=1).mean() - SAMPLED_RADIUS_MM
    assert abs(offset - noise**2 / SAMPLED_RADIUS_MM) < 0.005, offset
    inflated = trimesh.creation.icosphere(subdivisions=4, radius=SAMPLED_RADIUS_MM + offset)  # a fit through them
    points = _sphere_points(10_000, noise, seed=4)
    plan = plan_refinement(points, RefineConfig())
    sigma = normal_noise_mm(plan.patch_residual_mm, plan.neighbours)
    out, summary = remove_noise_bias(inflated.vertices, inflated.faces, sigma)
    left = np.linalg.norm(out, axis=1).mean() - SAMPLED_RADIUS_MM
    assert abs(left) < 0.3 * offset, (left, offset, summary)
    assert summary["sigma_mm"] == round(sigma, 4) and summary["mean_shift_mm"] > 0.6 * offset
    # the refinement (what the pipeline calls) applies that flow where its plan finds the input too noisy
    # (and then the tube patches, tests/test_tube_patches.py, and the section quadrics,
    # tests/test_section_quadrics.py: both off here)
    flow_only = RefineConfig(tube=TubePatchConfig(along_mm=0.0), section=SectionQuadricConfig(along_mm=0.0))
    refined, refine_summary = refine_vertices(inflated.vertices, points, flow_only, plan, faces=inflated.faces)
    assert plan.too_noisy and refine_summary["noise_flow"] == summary, refine_summary
    assert np.allclose(refined, out)
    no_flow = RefineConfig(noise_flow_factor=0.0, section=SectionQuadricConfig(along_mm=0.0))
    for config, faces in ((no_flow, inflated.faces), (RefineConfig(), None)):
        unchanged, unflowed = refine_vertices(inflated.vertices, points, config, plan, faces=faces)
        assert np.array_equal(unchanged, inflated.vertices) and "noise_flow" not in unflowed


def test_the_plan_tells_a_too_noisy_input_from_a_too_sparse_one():
    config = RefineConfig()
    noisy = plan_refinement(_sphere_points(10_000, 1.0, seed=3), config)
    assert not noisy.applies and noisy.too_noisy, noisy
    sparse = plan_refinement(_sphere_points(300, 0.0, seed=3), config)
    assert not sparse.applies and not sparse.too_noisy, sparse
    clean = plan_refinement(_sphere_points(10_000, 0.1, seed=3), config)
    assert clean.applies and not clean.too_noisy, clean


def _sphere_label_map(radius_mm: float, voxel_mm: float) -> PointCloud:
    """A partial-volume label map of a sphere (a voxel is set when more than half of it is inside,
    from 7^3 sub-samples), as the NIfTI loader gives it: its voxel centres, mm."""
    n = int(np.ceil(2 * radius_mm / voxel_mm)) + 6
    affine = np.diag([voxel_mm, voxel_mm, voxel_mm, 1.0])
    affine[:3, 3] = -0.5 * (n - 1) * voxel_mm
    sub = (np.arange(7) - 3) / 7.0 * voxel_mm
    centres = np.stack(np.meshgrid(*[affine[0, 3] + voxel_mm * np.arange(n)] * 3, indexing="ij"), -1)
    inside = np.zeros((n, n, n))
    for dx in sub:
        for dy in sub:
            for dz in sub:
                inside += np.linalg.norm(centres + [dx, dy, dz], axis=-1) < radius_mm
    ijk = np.argwhere(inside > 0.5 * 7**3)
    return PointCloud(points=ijk * voxel_mm + affine[:3, 3], labels=np.ones(len(ijk)), nifti_affine=affine, nifti_shape=(n, n, n))


def test_a_label_maps_smoothed_boundary_sits_inside_by_the_smoothing_and_the_refinement_takes_it_off():
    radius, voxel, sigma = 8.0, 1.5, 0.9  # a rib's curvature, the bench's voxels and the default blur
    cloud = mask_boundary_cloud(_sphere_label_map(radius, voxel), subvoxel_sigma_mm=sigma)
    t = cloud.boundary_smoothing_mm2
    assert abs(t - (sigma**2 + voxel**2 / 12) / 2) < 1e-9 and 0.4 < t < 0.6, t
    inward = radius - np.linalg.norm(cloud.points, axis=1).mean()
    # 2 H t, H = 1 / R (measured: 0.154 mm against 0.125; the discrete blur is not quite a Gaussian)
    assert 0.7 * 2 * t / radius < inward < 1.4 * 2 * t / radius, (inward, 2 * t / radius)
    # a mesh through those points, refined onto them, is moved back out onto the sphere
    through = trimesh.creation.icosphere(subdivisions=5, radius=radius - inward)
    config = RefineConfig(min_neighbours=20)
    out, summary = refine_vertices(through.vertices, cloud.points, config, faces=through.faces, smoothing_time_mm2=t)
    assert summary["applied"] and summary["smoothing_bias"]["flow_time_mm2"] == round(t, 4), summary
    assert abs(np.linalg.norm(out, axis=1).mean() - radius) < 0.4 * inward, np.linalg.norm(out, axis=1).mean()
    unmoved, _ = refine_vertices(through.vertices, cloud.points, RefineConfig(min_neighbours=20, smoothing_bias_factor=0.0),
                                 faces=through.faces, smoothing_time_mm2=t)
    assert np.linalg.norm(unmoved, axis=1).mean() < radius - 0.6 * inward


def test_a_label_maps_terrace_points_are_down_weighted_and_its_risers_kept():
    """refine.terrace_weights on a partial-volume sphere map's boundary points: near the poles (the
    normal along z) the z faces are terraces and get the weight, the x / y faces between them are
    risers and keep 1; at the equator along x, the x faces are the terraces."""
    from ribpull_core.config import RefineConfig
    from ribpull_core.refine import point_weights_of, terrace_weights

    cloud = mask_boundary_cloud(_sphere_label_map(12.0, 1.0), subvoxel_sigma_mm=0.9)
    assert cloud.face_axis is not None and len(cloud.face_axis) == len(cloud)
    w = terrace_weights(cloud.points, cloud.face_axis, cloud.nifti_affine, 0.25)
    unit = cloud.points / np.linalg.norm(cloud.points, axis=1, keepdims=True)
    pole, equator_x = np.abs(unit[:, 2]) > 0.97, np.abs(unit[:, 0]) > 0.97
    assert pole.sum() > 10 and equator_x.sum() > 10
    assert np.all(w[pole & (cloud.face_axis == 2)] == 0.25) and np.all(w[pole & (cloud.face_axis != 2)] == 1.0)
    assert np.all(w[equator_x & (cloud.face_axis == 0)] == 0.25)
    assert 0.25 < w.mean() < 1.0
    assert np.array_equal(point_weights_of(cloud, RefineConfig(terrace_weight=0.25)), w)
    assert point_weights_of(cloud, RefineConfig(terrace_weight=1.0)) is None  # disabled
    assert point_weights_of(PointCloud(points=cloud.points), RefineConfig()) is None  # not a label map


def test_point_weights_shape_a_quadric_patch():
    """fit_local_quadrics: unit weights fit what no weights fit; a zero-weighted stray sample
    leaves the patch where the others put it."""
    from ribpull_core.quadrics import fit_local_quadrics, project_onto_quadrics

    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(-1, 1, (400, 2)), np.zeros(400)]
    pts[0] = [0.0, 0.0, 0.1]  # one sample off the plane z = 0, inside its neighbours' patches
    plain = fit_local_quadrics(pts, k=30)
    ones = fit_local_quadrics(pts, k=30, point_weights=np.ones(len(pts)))
    np.testing.assert_array_equal(plain.coef, ones.coef)
    w = np.ones(len(pts))
    w[0] = 0.0
    weighted = fit_local_quadrics(pts, k=30, point_weights=w)
    near = np.argsort(np.linalg.norm(pts[1:, :2], axis=1))[:5] + 1  # patches around the stray sample
    above = np.zeros((len(near), 3))

    def heights(patches):
        return np.abs(project_onto_quadrics(above, near, patches)[:, 2])

    assert heights(weighted).max() < 1e-9 and heights(plain).min() > 1e-3
