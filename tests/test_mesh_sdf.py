"""Meshing, SDF volume, point queries and preview on analytic fields with known surfaces (mm)."""

from __future__ import annotations

import nibabel as nib
import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial import cKDTree
from torch import nn

from ribpull_core.config import MeshConfig, SdfConfig
from ribpull_core.errors import JobCanceled, RibPullInputError
from ribpull_core.frame import UnitFrame
from ribpull_core.mesh import count_components, export_mesh, extract_mesh, split_components
from ribpull_core.methods.base import FittedField
from ribpull_core.pointcloud import PointCloud
from ribpull_core.render import render_preview
from ribpull_core.sdf import query_field, sdf_grid_for, signed_distance_volume, voxel_centers_mm, write_nifti

FRAME = UnitFrame((100.0, -50.0, 20.0), 150.0)  # 1 unit = 150 mm
BOX = (np.full(3, -0.8), np.full(3, 0.8))


class Spheres(nn.Module):
    """Two logits [out, in] with logit_in = k * max_i (r_i - |x - c_i|): a union of balls (unit frame)."""

    def __init__(self, centres, radii, k: float = 20.0):
        super().__init__()
        self.c = nn.Parameter(torch.tensor(centres, dtype=torch.float32).reshape(-1, 3))
        self.r = torch.tensor(radii, dtype=torch.float32).reshape(-1)
        self.k = k

    def forward(self, x):
        d = self.r[None, :] - torch.cdist(x, self.c)
        li = self.k * d.max(dim=1).values
        return torch.stack([-li, li], -1)


class Torus(nn.Module):
    """Torus around z, major radius R, minor radius r (unit frame)."""

    def __init__(self, R: float = 0.45, r: float = 0.15, k: float = 20.0):
        super().__init__()
        self.R = nn.Parameter(torch.tensor(R))
        self.r, self.k = r, k

    def forward(self, x):
        q = torch.sqrt((torch.linalg.norm(x[:, :2], dim=1) - self.R) ** 2 + x[:, 2] ** 2)
        li = self.k * (self.r - q)
        return torch.stack([-li, li], -1)


def sphere_field(centre=(0.1, -0.2, 0.05), radius=0.5) -> FittedField:
    return FittedField(Spheres([centre], [radius]), kind="occupancy", level=0.0)


@pytest.fixture(scope="module")
def sphere_mesh() -> trimesh.Trimesh:
    return extract_mesh(sphere_field(), FRAME, BOX, MeshConfig(resolution=96, coarse_resolution=24))


def test_sphere_mesh_is_watertight_outward_and_on_the_surface(sphere_mesh):
    m = sphere_mesh
    c_mm = FRAME.to_mm(np.array([0.1, -0.2, 0.05]))
    r_mm = 0.5 * 150.0
    err = np.abs(np.linalg.norm(m.vertices - c_mm, axis=1) - r_mm)
    voxel = m.metadata["voxel_mm"]
    assert voxel == pytest.approx(1.7 * 150 / 96)  # box ±0.8 plus padding 0.05
    assert m.is_watertight
    assert err.max() < 0.02 * voxel  # vertices in mm, in the input's frame
    assert m.volume == pytest.approx(4 / 3 * np.pi * r_mm**3, rel=0.01)  # positive: outward faces
    outward = np.einsum("ij,ij->i", m.face_normals, m.triangles_center - c_mm)
    assert (outward > 0).all()
    assert count_components(m) == 1
    assert m.metadata["field_queries"] < m.metadata["dense_queries"]


def test_coarse_to_fine_equals_dense_with_far_fewer_queries():
    field = FittedField(Torus(), kind="occupancy", level=0.0)
    fine = extract_mesh(field, FRAME, BOX, MeshConfig(resolution=96, coarse_resolution=12))
    dense = extract_mesh(field, FRAME, BOX, MeshConfig(resolution=96, coarse_resolution=96))
    assert fine.metadata["levels"] == 3 and dense.metadata["levels"] == 0
    assert dense.metadata["field_queries"] == dense.metadata["dense_queries"] == 97**3
    assert fine.metadata["field_queries"] < 0.2 * dense.metadata["dense_queries"]
    assert fine.vertices.shape == dense.vertices.shape and fine.faces.shape == dense.faces.shape
    gap = cKDTree(dense.vertices).query(fine.vertices)[0]  # same vertices up to float32 rounding
    assert gap.max() < 1e-3
    assert fine.is_watertight and count_components(fine) == 1
    assert fine.euler_number == 0  # genus one


def test_two_separate_spheres_give_two_components():
    field = FittedField(Spheres([(-0.4, 0, 0), (0.4, 0.1, 0)], [0.25, 0.2]), kind="occupancy")
    m = extract_mesh(field, FRAME, BOX, MeshConfig(resolution=64, coarse_resolution=16))
    parts = split_components(m)
    assert count_components(m) == 2 and len(parts) == 2
    assert all(p.is_watertight for p in parts)
    assert len(parts[0].faces) >= len(parts[1].faces)  # largest first
    radii = sorted(np.cbrt(p.volume * 3 / (4 * np.pi)) for p in parts)
    np.testing.assert_allclose(radii, [0.2 * 150, 0.25 * 150], rtol=0.01)


def test_empty_level_set_is_a_degenerate_input_error():
    field = sphere_field(radius=0.01)  # far smaller than a coarse cell: all outside on the grid
    field.level = 0.5
    with pytest.raises(RibPullInputError) as err:
        extract_mesh(field, FRAME, BOX, MeshConfig(resolution=32, coarse_resolution=16))
    assert err.value.code == "degenerate" and "outside everywhere" in err.value.message
    inside = FittedField(Spheres([(0, 0, 0)], [5.0]), kind="occupancy")
    with pytest.raises(RibPullInputError, match="inside everywhere"):
        extract_mesh(inside, FRAME, BOX, MeshConfig(resolution=32, coarse_resolution=16))


def test_cancel_and_progress():
    calls = []
    m = extract_mesh(sphere_field(), FRAME, BOX, MeshConfig(resolution=32, coarse_resolution=8), progress=calls.append)
    assert len(m.faces) and calls[-1] == 1.0 and calls == sorted(calls)
    with pytest.raises(JobCanceled):
        extract_mesh(sphere_field(), FRAME, BOX, MeshConfig(resolution=32, coarse_resolution=8), should_cancel=lambda: True)


def test_export_formats_roundtrip(tmp_path, sphere_mesh):
    paths = export_mesh(sphere_mesh, tmp_path)
    assert set(paths) == {"ply", "stl", "obj", "glb"}
    for fmt, p in paths.items():
        assert p.name == f"mesh.{fmt}" and p.stat().st_size > 0
        back = trimesh.load(p, force="mesh")
        np.testing.assert_allclose(back.bounds, sphere_mesh.bounds, atol=1e-3)  # still mm


def test_sdf_volume_matches_analytic_sphere(sphere_mesh):
    c_mm = FRAME.to_mm(np.array([0.1, -0.2, 0.05]))
    cloud = PointCloud(points=sphere_mesh.vertices)
    shape, affine = sdf_grid_for(cloud, FRAME, SdfConfig(voxel_mm=4.0, padding_mm=10.0))
    np.testing.assert_allclose(np.diag(affine)[:3], 4.0)
    np.testing.assert_allclose(affine[:3, 3], cloud.bbox_mm[0] - 10.0)
    vol = signed_distance_volume(sphere_mesh, sphere_field(), FRAME, shape, affine, n_samples=200_000)
    assert vol.shape == shape and vol.dtype == np.float32
    true = np.linalg.norm(voxel_centers_mm(shape, affine) - c_mm, axis=1) - 75.0
    err = np.abs(vol.ravel() - true)
    assert err.mean() < 0.03 * 4.0 and err.max() < 0.25 * 4.0  # mm, voxel 4 mm
    clear = np.abs(true) > 0.5
    assert (np.sign(vol.ravel()[clear]) == np.sign(true[clear])).all()


def test_sdf_grid_for_nifti_inputs_reuses_the_input_grid():
    aff = np.array([[0, -0.8, 0, 10], [0.7, 0, 0, -20], [0, 0, 2.5, 30], [0, 0, 0, 1]], dtype=float)
    cloud = PointCloud(points=np.random.default_rng(0).random((10, 3)), nifti_affine=aff, nifti_shape=(100, 90, 40))
    shape, out = sdf_grid_for(cloud, FRAME, SdfConfig())
    assert shape == (100, 90, 40) and np.array_equal(out, aff)
    shape, out = sdf_grid_for(cloud, FRAME, SdfConfig(max_voxels=100_000))  # every 2nd voxel
    assert shape == (50, 45, 20) and np.prod(shape) <= 100_000
    np.testing.assert_allclose(out[:3, :3], aff[:3, :3] * 2)
    np.testing.assert_allclose(out[:3, 3], aff[:3, 3])


def test_sdf_grid_caps_voxels():
    pts = np.array([[0, 0, 0], [300, 200, 100]], dtype=float)
    shape, aff = sdf_grid_for(PointCloud(points=pts), UnitFrame.fit(pts), SdfConfig(max_voxels=50_000, padding_mm=5))
    assert np.prod(shape) <= 50_000
    corner = aff[:3, :3] @ (np.array(shape) - 1) + aff[:3, 3]
    assert (corner >= pts[1] + 5 - 1e-9).all() and np.allclose(aff[:3, 3], -5)


def test_write_nifti_roundtrip(tmp_path):
    aff = np.array([[-1.5, 0, 0, 90], [0, 1.5, 0, -120], [0, 0, 2.0, -60], [0, 0, 0, 1]])
    vol = np.random.default_rng(1).normal(size=(6, 7, 8)).astype(np.float32)
    p = write_nifti(tmp_path / "sdf.nii.gz", vol, aff)
    img = nib.load(p)
    np.testing.assert_allclose(img.affine, aff)
    assert int(img.header["qform_code"]) == 1 and int(img.header["sform_code"]) == 1
    assert img.header.get_xyzt_units()[0] == "mm"
    np.testing.assert_array_equal(np.asanyarray(img.dataobj), vol)

    plain = write_nifti(tmp_path / "sdf.nii", vol, aff)  # no .gz: written as is
    np.testing.assert_array_equal(np.asanyarray(nib.load(plain).dataobj), vol)


def test_voxel_centres_follow_a_rotated_affine():
    rot = trimesh.transformations.rotation_matrix(0.4, [1.0, 2.0, 3.0])[:3, :3]
    aff = np.eye(4)
    aff[:3, :3] = rot @ np.diag([0.75, 0.8, 2.5])
    aff[:3, 3] = [-100.0, 20.0, 7.0]
    shape = (5, 6, 7)
    ijk = np.stack(np.unravel_index(np.arange(np.prod(shape)), shape), -1).astype(np.float64)
    want = ijk @ aff[:3, :3].T + aff[:3, 3]
    np.testing.assert_allclose(voxel_centers_mm(shape, aff), want, atol=1e-12)
    np.testing.assert_allclose(voxel_centers_mm(shape, aff, 17, 101), want[17:101], atol=1e-12)


def test_query_field_in_mm(sphere_mesh):
    c_mm = FRAME.to_mm(np.array([0.1, -0.2, 0.05]))
    pts = c_mm + np.array([[0, 0, 0], [70, 0, 0], [0, -80, 0], [0, 0, 200]], dtype=float)
    q = query_field(sphere_field(), FRAME, pts, mesh_mm=sphere_mesh)
    np.testing.assert_array_equal(q["inside"], [True, True, False, False])
    assert q["occupancy"][0] > 0.99 and q["occupancy"][3] < 0.01
    np.testing.assert_allclose(q["U"], 2 * q["occupancy"] - 1, atol=1e-5)
    np.testing.assert_allclose(q["sdf_mm"], [-75, -5, 5, 125], atol=0.05)
    assert set(query_field(sphere_field(), FRAME, pts)) == {"occupancy", "U", "inside"}


def test_render_preview_png(tmp_path, sphere_mesh):
    from PIL import Image

    big = trimesh.creation.torus(80, 20, major_sections=400, minor_sections=250)  # 200k faces
    t = np.linspace(0, 2 * np.pi, 100)
    p = render_preview(tmp_path / "preview.png", big, [np.stack([80 * np.cos(t), 80 * np.sin(t), 0 * t], 1)], "t")
    im = np.asarray(Image.open(p).convert("RGB")).astype(int)
    assert im.shape == (600, 1200, 3)
    assert (im.sum(-1) < 600).mean() > 0.02  # mesh pixels, not just white
    red = (im[..., 0] > 150) & (im[..., 1] < 90) & (im[..., 2] < 90)
    assert red.sum() > 100  # the skeleton is drawn
    assert render_preview(tmp_path / "empty.png", None).stat().st_size > 0


def test_surface_cut_by_the_box_is_closed():
    field = sphere_field(centre=(0.0, 0.0, 0.0), radius=0.5)
    box = (np.full(3, -0.3), np.full(3, 0.3))  # the ball fills the corners of the padded box
    m = extract_mesh(field, FRAME, box, MeshConfig(resolution=32, coarse_resolution=8))
    assert m.is_watertight and m.volume > 0
    np.testing.assert_allclose(m.bounds, FRAME.to_mm(np.array([[-0.35] * 3, [0.35] * 3])), atol=0.7 * 150 / 32)


def test_small_components_dropped_on_request():
    field = FittedField(Spheres([(-0.4, 0, 0), (0.4, 0.1, 0)], [0.3, 0.1]), kind="occupancy")
    cfg = MeshConfig(resolution=48, coarse_resolution=12, keep_components_min_fraction=0.2)
    m = extract_mesh(field, FRAME, BOX, cfg)
    assert count_components(m) == 1 and m.metadata["field_queries"] > 0
    assert np.cbrt(m.volume * 3 / (4 * np.pi)) == pytest.approx(0.3 * 150, rel=0.02)


def test_real_network_surface_sits_on_its_level_set():
    from ribpull_core.fields import NeuralPullMLP

    torch.manual_seed(0)
    arch = {"name": "NeuralPullMLP", "kwargs": {"hidden": 64, "layers": 4, "skip": 2}}
    field = FittedField(NeuralPullMLP(**arch["kwargs"]), kind="occupancy", arch=arch)
    m = extract_mesh(field, FRAME, BOX, MeshConfig(resolution=48, coarse_resolution=12))
    assert m.is_watertight and m.volume > 0
    step = 0.5 * m.metadata["voxel_mm"]
    v_unit = FRAME.to_unit(m.vertices)
    level_set = np.abs(v_unit).max(axis=1) < 0.8  # leave out the cap closing the surface at the box
    v, n = m.vertices[level_set], m.vertex_normals[level_set]
    assert level_set.mean() > 0.3
    outside = field.evaluate(FRAME.to_unit(v + step * n))["inside_score"] < field.level
    inside = field.evaluate(FRAME.to_unit(v - step * n))["inside_score"] > field.level
    assert outside.mean() > 0.97 and inside.mean() > 0.97  # outward normals, surface at the level


def test_sdf_volume_can_be_canceled(sphere_mesh):
    shape, affine = sdf_grid_for(PointCloud(points=sphere_mesh.vertices), FRAME, SdfConfig(voxel_mm=10.0))
    with pytest.raises(JobCanceled):
        signed_distance_volume(sphere_mesh, sphere_field(), FRAME, shape, affine, n_samples=10_000,
                               should_cancel=lambda: True)


def test_clean_up_drops_cavities_and_unsupported_specks_but_keeps_supported_parts():
    from ribpull_core.mesh import remove_unsupported_components

    main = trimesh.creation.icosphere(subdivisions=4, radius=20.0)
    cavity = trimesh.creation.icosphere(subdivisions=2, radius=5.0)
    cavity.invert()  # an inward-facing shell inside the solid
    speck = trimesh.creation.icosphere(subdivisions=2, radius=2.0).apply_translation([80.0, 0, 0])
    second = trimesh.creation.icosphere(subdivisions=3, radius=8.0).apply_translation([0, 60.0, 0])
    mesh = trimesh.util.concatenate([main, cavity, speck, second])
    points = np.concatenate([main.sample(3000, seed=0), second.sample(800, seed=1)])
    cleaned, info = remove_unsupported_components(mesh, points, support_mm=2.0)
    assert info == {"components_before": 4, "removed_cavities": 1, "removed_unsupported": 1}
    assert len(cleaned.split(only_watertight=False)) == 2
    assert np.isclose(cleaned.area, main.area + second.area)


class RippledSphere(nn.Module):
    """A ball whose radius ripples by ±amp (unit frame): its surface leaves the coarse grid's guess."""

    def __init__(self, radius: float = 0.5, amp: float = 0.04, freq: int = 9, k: float = 20.0):
        super().__init__()
        self.w = nn.Parameter(torch.zeros(1))
        self.radius, self.amp, self.freq, self.k = radius, amp, freq, k

    def forward(self, x):
        r = torch.linalg.norm(x, dim=1)
        ripple = self.amp * torch.sin(self.freq * torch.atan2(x[:, 1], x[:, 0])) * torch.cos(self.freq * x[:, 2] / 0.5)
        li = self.k * (self.radius + ripple - r)
        return torch.stack([-li, li], -1)


def test_coarse_to_fine_follows_a_surface_the_coarse_grid_misplaces():
    field = FittedField(RippledSphere(), kind="occupancy", level=0.0)
    fine = extract_mesh(field, FRAME, BOX, MeshConfig(resolution=96, coarse_resolution=12))
    dense = extract_mesh(field, FRAME, BOX, MeshConfig(resolution=96, coarse_resolution=96))
    assert fine.metadata["field_queries"] < 0.25 * dense.metadata["field_queries"]
    # every cell marching cubes cuts was evaluated by the network: the same mesh as the dense grid
    assert fine.vertices.shape == dense.vertices.shape and fine.faces.shape == dense.faces.shape
    assert cKDTree(dense.vertices).query(fine.vertices)[0].max() < 1e-3
    assert fine.is_watertight and count_components(fine) == 1


def test_obj_writer_matches_trimesh_byte_for_byte(tmp_path, sphere_mesh):
    from ribpull_core.mesh import obj_bytes

    rng = np.random.default_rng(3)
    odd = trimesh.Trimesh(rng.normal(0, 300, (500, 3)) * np.array([1, 1e-3, 1e-7]), rng.integers(0, 500, (900, 3)),
                          process=False)  # negative, tiny and large values, unreferenced vertices
    for m in (sphere_mesh, odd):
        assert obj_bytes(m.vertices, m.faces) == m.export(file_type="obj").encode()
    paths = export_mesh(sphere_mesh, tmp_path, ("obj",))
    back = trimesh.load(paths["obj"], process=False)
    np.testing.assert_allclose(back.vertices, sphere_mesh.vertices, atol=1e-8)
    np.testing.assert_array_equal(back.faces, sphere_mesh.faces)


def test_fast_components_match_trimesh():
    from ribpull_core.mesh import face_component_labels, remove_unsupported_components

    a = trimesh.creation.icosphere(subdivisions=3, radius=10.0)
    b = trimesh.creation.icosphere(subdivisions=3, radius=6.0).apply_translation([30.0, 0, 0])
    c = trimesh.creation.icosphere(subdivisions=1, radius=3.0).apply_translation([0, 40.0, 0])
    m = trimesh.util.concatenate([c, a, b])
    opened = trimesh.Trimesh(m.vertices, m.faces[3:], process=False)  # holes: boundary edges
    for mesh in (m, opened):
        labels, n = face_component_labels(mesh.faces)
        ref = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=len(mesh.faces))
        np.testing.assert_array_equal(labels, ref)
        assert n == count_components(mesh) == ref.max() + 1
    assert count_components(m) == 3
    # the clean-up keeps the faces of the kept components, grouped by component, with their vertices
    pts = np.concatenate([a.sample(2000, seed=0), b.sample(2000, seed=1)])
    cleaned, info = remove_unsupported_components(m, pts, support_mm=1.0)
    assert info == {"components_before": 3, "removed_cavities": 0, "removed_unsupported": 1}
    assert len(cleaned.faces) == len(a.faces) + len(b.faces) and len(cleaned.vertices) == len(a.vertices) + len(b.vertices)
    assert np.isclose(cleaned.area, a.area + b.area) and cleaned.is_watertight


def test_sdf_on_grid_pass_equals_point_queries(sphere_mesh, monkeypatch):
    import ribpull_core.sdf as sdf_mod

    cloud = PointCloud(points=sphere_mesh.vertices)
    shape, affine = sdf_grid_for(cloud, FRAME, SdfConfig(voxel_mm=4.0, padding_mm=10.0))
    grid = signed_distance_volume(sphere_mesh, sphere_field(), FRAME, shape, affine, n_samples=100_000)
    calls = []
    monkeypatch.setattr(sdf_mod, "_voxels_on_nodes", lambda *a: calls.append(1))  # force point queries
    points = signed_distance_volume(sphere_mesh, sphere_field(), FRAME, shape, affine, n_samples=100_000)
    assert calls and np.abs(grid - points).max() < 1e-4


def test_grid_upper_bounds_equal_the_numpy_gather_of_the_cells_nodes(sphere_mesh):
    """sdf_kernels.grid_upper_bounds: per point the nearest of the closest points stored at its
    cell's 8 nodes, as a numpy gather computes it, for points inside and outside the grid."""
    from ribpull_core.sdf import SurfaceDistance
    from ribpull_core.sdf_kernels import grid_upper_bounds

    dist = SurfaceDistance(sphere_mesh, n_samples=50_000, grid_mm=3.0)
    lo, hi = dist.origin, dist.origin + (dist.nodes - 1) * dist.grid_mm
    p = np.random.default_rng(0).uniform(lo - 20.0, hi + 20.0, (20_000, 3))
    f = (p - dist.origin) / dist.grid_mm
    cell = np.clip(np.floor(f).astype(np.int64), 0, dist.nodes - 2)
    corners = np.array(list(np.ndindex(2, 2, 2)))
    stored = dist.cp_grid[tuple((cell[:, None, :] + corners[None]).transpose(2, 0, 1))].astype(np.float64)  # (N, 8, 3)
    expected = np.sqrt(((stored - p[:, None, :]) ** 2).sum(-1).min(1))
    got, ingrid = grid_upper_bounds(dist.cp_grid, dist.origin, float(dist.grid_mm), dist.nodes.astype(np.int64), p)
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(ingrid, np.all((f >= 0) & (f <= dist.nodes - 1), axis=1))
    assert 0 < ingrid.sum() < len(p)  # both kinds were checked


def test_propagated_closest_points_equal_the_numpy_gather_bit_for_bit():
    """sdf_kernels.propagate_closest_points: every node takes the point stored at its EDT source
    node, and its squared distance in float32, exactly as the numpy gather and broadcast computed."""
    from scipy import ndimage

    from ribpull_core.sdf_kernels import propagate_closest_points

    rng = np.random.default_rng(3)
    shape = (17, 11, 13)
    near = rng.random(shape) < 0.05
    cp_near = np.zeros((3,) + shape, dtype=np.float32)
    cp_near[:, near] = rng.normal(size=(3, int(near.sum()))).astype(np.float32) * 10.0
    source = ndimage.distance_transform_edt(~near, return_distances=False, return_indices=True)
    ax = [(rng.normal() + np.arange(n) * 1.3).astype(np.float32) for n in shape]
    cp, best = propagate_closest_points(cp_near, source, *ax)
    want = cp_near.reshape(3, -1)[:, np.ravel_multi_index(tuple(source), shape)].reshape((3,) + shape)
    want_best = (ax[0][:, None, None] - want[0]) ** 2
    want_best += (ax[1][None, :, None] - want[1]) ** 2
    want_best += (ax[2][None, None, :] - want[2]) ** 2
    np.testing.assert_array_equal(cp, want)
    np.testing.assert_array_equal(best, want_best)
    assert cp.dtype == best.dtype == np.float32


def _numpy_cell_corner_distances(cp: np.ndarray, ax: list[np.ndarray]) -> np.ndarray:
    """The numpy passes cell_corner_distances replaced (SurfaceDistance.node_distances before
    2026-12-08): each axis padded with its node n - 2, then 8 shifted whole-grid expressions."""
    shape = cp.shape[1:]
    ext = cp
    for a in range(3):
        ext = np.concatenate([ext, np.take(ext, [max(shape[a] - 2, 0)], axis=a + 1)], axis=a + 1)
    best = np.full(shape, np.inf)
    for dx, dy, dz in np.ndindex(2, 2, 2):
        c = ext[:, dx : dx + shape[0], dy : dy + shape[1], dz : dz + shape[2]]
        q = (ax[0][:, None, None] - c[0]) ** 2
        q += (ax[1][None, :, None] - c[1]) ** 2
        q += (ax[2][None, None, :] - c[2]) ** 2
        np.minimum(best, q, out=best)
    return np.sqrt(best)


@pytest.mark.parametrize("shape", [(17, 11, 13), (9, 1, 6), (2, 2, 2)])
def test_cell_corner_distances_equal_the_numpy_passes_bit_for_bit(shape):
    """sdf_kernels.cell_corner_distances: at each node the nearest of the closest points stored at
    its cell's 8 nodes (the last cell for the upper faces; an axis one node thick has no cell
    beyond its node), in the same float64 arithmetic as the numpy passes it replaced."""
    from ribpull_core.sdf_kernels import cell_corner_distances

    rng = np.random.default_rng(5)
    cp = (rng.normal(size=(3,) + shape) * 10.0).astype(np.float32)
    ax = [rng.normal() + np.arange(n) * 1.3 for n in shape]
    got = cell_corner_distances(cp, *ax)
    assert got.dtype == np.float64 and got.shape == shape
    np.testing.assert_array_equal(got, _numpy_cell_corner_distances(cp, ax))


def test_fast_surface_sampling_is_area_uniform():
    from ribpull_core.mesh import sample_surface_fast

    # two squares, the second 4x the area: 1/5 vs 4/5 of the samples, uniform on each
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 5], [2, 0, 5], [2, 2, 5], [0, 2, 5]], float)
    f = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    pts, fi = sample_surface_fast(trimesh.Trimesh(v, f, process=False), 200_000, seed=1)
    big = pts[:, 2] > 1
    assert abs(big.mean() - 0.8) < 0.005 and np.array_equal(big, fi >= 2)
    hist, _, _ = np.histogram2d(pts[big, 0], pts[big, 1], bins=4, range=[[0, 2], [0, 2]])
    assert hist.min() > 0.9 * hist.mean() and hist.max() < 1.1 * hist.mean()
    assert np.all((pts[:, :2] >= 0) & (pts[:, :2] <= 2))


def test_rasterize_triangles_covers_pixel_centres_and_keeps_the_nearest():
    from ribpull_core.render import rasterize_triangles

    # a 4 x 4 px square (two triangles, one of each winding) at depth 0 over pixels x 2..5, y 1..4,
    # and a red triangle half over it: nearer (depth 1) on its left, farther (depth -1) elsewhere
    square = np.array([[[2, 1, 0], [6, 1, 0], [6, 5, 0]], [[2, 1, 0], [2, 5, 0], [6, 5, 0]]], float)
    near = np.array([[[0, 0, 1], [4, 0, 1], [0, 8, 1]]], float)
    far = np.array([[[5, 0, -1], [9, 0, -1], [9, 8, -1]]], float)
    colours = np.array([[0, 1, 0], [0, 1, 0], [1, 0, 0], [1, 0, 0]], float)
    im = rasterize_triangles(np.concatenate([square, near, far]), colours, 8, 10, np.ones(3))
    green = (im == [0, 1, 0]).all(-1)
    red = (im == [1, 0, 0]).all(-1)
    white = (im == 1).all(-1)
    assert (green | red | white).all()
    covered_square = np.zeros((8, 10), bool)
    covered_square[1:5, 2:6] = True
    # the near triangle wins where it covers the square's pixel centres: x + 0.5 <= 4 - (y + 0.5) / 2
    ys, xs = np.mgrid[0:8, 0:10] + 0.5
    in_near = xs <= 4 - ys / 2
    assert np.array_equal(red & covered_square, covered_square & in_near)
    assert np.array_equal(green, covered_square & ~in_near)  # the far triangle is hidden behind it
    assert red[0, 8] and white[7, 0]


def test_render_preview_views_follow_ras(tmp_path):
    """Anterior view: the camera in front (+y), the patient's right (+x) on the viewer's left.
    Lateral: the camera on the right (+x), anterior (+y) on the viewer's right. A 20 mm sphere and
    a 4 mm box are told apart by their widths in the image."""
    from PIL import Image

    def drawn_columns(png, view):  # columns of the view's half of the image that hold the mesh
        im = np.asarray(Image.open(png).convert("L")).astype(int)[60:, 600 * view:600 * (view + 1)]
        return np.flatnonzero((im < 245).any(axis=0))

    sphere = trimesh.creation.icosphere(3, 10)
    box_left = trimesh.creation.box((4, 4, 4)).apply_translation([-60, 0, 0])
    # anterior: the sphere on the patient's right (+x) shows on the left, the box on the right
    cols = drawn_columns(render_preview(tmp_path / "a.png", sphere.copy().apply_translation([60, 0, 0]) + box_left), 0)
    assert np.ptp(cols[cols < 300]) > 3 * np.ptp(cols[cols >= 300]) > 0
    # lateral: the sphere in front (+y) shows on the right, the box (y = 0) on the left
    cols = drawn_columns(render_preview(tmp_path / "l.png", sphere.copy().apply_translation([0, 60, 0]) + box_left), 1)
    assert np.ptp(cols[cols >= 300]) > 3 * np.ptp(cols[cols < 300]) > 0


def test_points_on_triangles_match_the_numpy_formula():
    """The compiled sampler gives the numbers of the vectorised formula it replaced, folds included."""
    from ribpull_core.mesh import points_on_triangles

    rng = np.random.default_rng(3)
    tri = rng.normal(size=(50, 3, 3)) * 10
    fi = np.sort(rng.integers(0, 50, 5000))
    r = rng.random((5000, 2))
    folded = r.copy()
    flip = folded.sum(1) > 1.0
    folded[flip] = 1.0 - folded[flip]
    t = tri[fi]
    expected = t[:, 0] + folded[:, :1] * (t[:, 1] - t[:, 0]) + folded[:, 1:] * (t[:, 2] - t[:, 0])
    assert flip.any() and (~flip).any()
    np.testing.assert_array_equal(points_on_triangles(tri, fi, r), expected)

