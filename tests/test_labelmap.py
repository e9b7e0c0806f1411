"""Label maps as training data: known occupancy at voxel centres and the sub-voxel boundary."""

from __future__ import annotations

import numpy as np
import pytest

from ribpull_core.pointcloud import (
    PointCloud,
    band_distances,
    mask_band_samples,
    mask_boundary_cloud,
    mask_signed_distance,
    voxel_spacing_mm,
)

RADIUS_MM = 12.0


def sphere_mask_cloud(spacing=(1.5, 1.5, 1.5), radius=RADIUS_MM, supersample=5) -> PointCloud:
    """A label-map cloud of a ball: a voxel is selected when more than half of it is inside
    (partial-volume correct, by supersampling), voxel centres in mm through a diagonal affine."""
    spacing = np.asarray(spacing, dtype=float)
    n = np.ceil((radius + 4 * spacing.max()) / spacing).astype(int)
    axes = [np.arange(-k, k + 1) * h for k, h in zip(n, spacing)]
    sub = (np.arange(supersample) + 0.5) / supersample - 0.5
    frac = np.zeros([len(a) for a in axes])
    for dx in sub:
        for dy in sub:
            for dz in sub:
                x, y, z = np.meshgrid(axes[0] + dx * spacing[0], axes[1] + dy * spacing[1], axes[2] + dz * spacing[2],
                                      indexing="ij")
                frac += (x**2 + y**2 + z**2) <= radius**2
    frac /= supersample**3
    ijk = np.argwhere(frac > 0.5)
    affine = np.diag([*spacing, 1.0])
    affine[:3, 3] = [-k * h for k, h in zip(n, spacing)]
    pts = ijk * spacing + affine[:3, 3]
    return PointCloud(points=pts, labels=np.ones(len(pts), np.int32), source_format="nifti",
                      nifti_affine=affine, nifti_shape=tuple(len(a) for a in axes))


@pytest.mark.parametrize("spacing", [(1.5, 1.5, 1.5), (0.75, 0.75, 2.5)])
def test_band_samples_state_the_side_of_the_voxel_centres(spacing):
    cloud = mask_band_samples(sphere_mask_cloud(spacing), width_voxels=2.0)
    r = np.linalg.norm(cloud.occupancy_points, axis=1)
    inside = cloud.occupancy_inside
    assert inside.any() and (~inside).any()
    # a partial-volume map: centres labelled inside are (nearly always) inside the true ball
    assert (r[inside] <= RADIUS_MM + 0.3).mean() > 0.99
    assert (r[~inside] >= RADIUS_MM - 0.3).mean() > 0.99
    # the band: nothing farther than 2 voxels (longest edge) from the other class, distances > 0
    d = cloud.occupancy_distance_mm
    assert d.min() > 0 and d.max() <= 2 * max(spacing) + 1e-6
    assert np.allclose(voxel_spacing_mm(cloud), spacing)


def test_band_distances_are_the_thresholded_distance_transforms():
    from scipy import ndimage

    rng = np.random.default_rng(2)
    inside = ndimage.gaussian_filter(rng.random((40, 36, 18)), 2.0) > 0.5  # blobs, touching the border too
    inside[0], inside[:, -1] = True, False
    spacing = np.array([0.75, 0.9, 2.5])
    reach = 2 * 2.5 + 1e-6
    dist = np.where(inside, ndimage.distance_transform_edt(inside, sampling=spacing),
                    ndimage.distance_transform_edt(~inside, sampling=spacing))
    want = np.flatnonzero(dist <= reach)
    flat, got = band_distances(inside, spacing, reach)
    assert 0 < len(want) < inside.size
    np.testing.assert_array_equal(flat, want)
    np.testing.assert_allclose(got, dist.ravel()[want], rtol=0, atol=1e-12)


@pytest.mark.parametrize("spacing", [(1.5, 1.5, 1.5), (0.75, 0.75, 2.5)])
def test_subvoxel_boundary_is_closer_to_the_true_surface_than_the_staircase(spacing):
    cloud = sphere_mask_cloud(spacing)
    stairs = mask_boundary_cloud(cloud, max_points=10**9)
    smooth = mask_boundary_cloud(cloud, max_points=10**9, subvoxel_sigma_mm=1.0)
    err_stairs = np.abs(np.linalg.norm(stairs.points, axis=1) - RADIUS_MM).mean()
    err_smooth = np.abs(np.linalg.norm(smooth.points, axis=1) - RADIUS_MM).mean()
    assert len(smooth) == len(stairs)
    assert err_smooth < 0.7 * err_stairs, (err_smooth, err_stairs)


def test_band_samples_survive_the_boundary_cloud():
    cloud = mask_boundary_cloud(mask_band_samples(sphere_mask_cloud()), max_points=10**9)
    assert cloud.occupancy_points is not None and len(cloud.occupancy_points) == len(cloud.occupancy_inside)


@pytest.mark.parametrize("spacing", [(1.5, 1.5, 1.5), (0.75, 0.75, 2.5)])
def test_signed_distance_prior_reads_the_ball_off_the_map(spacing):
    from trimesh import transform_points

    voxels = sphere_mask_cloud(spacing)
    cloud = mask_signed_distance(voxels, mask_boundary_cloud(voxels, max_points=10**9, subvoxel_sigma_mm=1.0), cell_mm=3.0)
    sdf, affine = cloud.solid_distance_mm, cloud.solid_distance_affine
    stride = np.round(np.linalg.norm(affine[:3, :3], axis=0) / np.asarray(spacing)).astype(int)
    assert np.array_equal(stride, np.maximum(1, np.round(3.0 / np.asarray(spacing))).astype(int))
    nodes = transform_points(np.argwhere(np.ones(sdf.shape, bool)).astype(float), affine)  # mm
    r = np.linalg.norm(nodes, axis=1)
    truth = r - RADIUS_MM
    near = np.abs(truth) < 4.0  # where the map (and the smoothing) can know the distance
    err = np.abs(sdf.ravel()[near] - truth[near])
    assert err.mean() < 0.5 * max(spacing) and err.max() < 1.5 * max(spacing), (err.mean(), err.max())
    # the sign is the map's: negative deep inside, positive far outside; the grid reaches 20 mm out
    assert (sdf.ravel()[truth < -3.0] < 0).all() and (sdf.ravel()[truth > 3.0] > 0).all()
    assert r.max() > RADIUS_MM + 19.0
