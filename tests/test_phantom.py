"""Tests of the synthetic ribcage: names, watertight meshes, exact truth, sampling, voxels, gaps."""

from __future__ import annotations

import json

import nibabel as nib
import numpy as np
import pytest
import trimesh
from scipy.optimize import minimize
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ribpull_core.errors import RibPullInputError
from ribpull_core.phantom import (
    RIB_NAMES,
    PhantomConfig,
    make_phantom,
    sample_surface,
    tube_level,
    voxelize,
    write_phantom,
)


@pytest.fixture(scope="module")
def phantom():
    return make_phantom()


@pytest.fixture(scope="module")
def labels_1mm(phantom):
    return voxelize(phantom, spacing_mm=1.0)


# ------------------------------------------------------------------------------- helpers


def n_components(mesh: trimesh.Trimesh) -> int:
    """Connected components of the vertex graph of mesh's faces."""
    f = mesh.faces
    rows = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
    cols = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
    n = len(mesh.vertices)
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    return connected_components(graph, directed=False)[0]


def inside_by_ray_parity(mesh: trimesh.Trimesh, points: np.ndarray, chunk: int = 64) -> np.ndarray:
    """(N,) bool: odd number of crossings of the ray from each point along +x with the closed mesh.

    Independent of the phantom's analytic model: only the triangles are used (exact 2D barycentric
    test in the y-z projection; rays through an edge have probability zero for these points)."""
    tri = mesh.triangles  # (F, 3, 3)
    ymin, ymax = tri[:, :, 1].min(1), tri[:, :, 1].max(1)
    zmin, zmax = tri[:, :, 2].min(1), tri[:, :, 2].max(1)
    xmax = tri[:, :, 0].max(1)
    out = np.zeros(len(points), dtype=bool)
    for s in range(0, len(points), chunk):
        p = points[s : s + chunk]
        cand = (
            (ymin <= p[:, 1:2]) & (p[:, 1:2] <= ymax) & (zmin <= p[:, 2:3]) & (p[:, 2:3] <= zmax)
            & (xmax > p[:, 0:1])
        )  # fmt: skip
        pi, fi = np.nonzero(cand)
        a, b, c = tri[fi, 0], tri[fi, 1], tri[fi, 2]
        q = p[pi]

        def cross2(u, v):
            return u[:, 1] * v[:, 2] - u[:, 2] * v[:, 1]

        den = cross2(b - a, c - a)
        l1 = cross2(b - q, c - q) / den
        l2 = cross2(c - q, a - q) / den
        l3 = 1.0 - l1 - l2
        hit = (l1 >= 0) & (l2 >= 0) & (l3 >= 0)
        x = l1 * a[:, 0] + l2 * b[:, 0] + l3 * c[:, 0]
        hit &= x > q[:, 0]
        counts = np.bincount(pi[hit], minlength=len(p))
        out[s : s + chunk] = counts % 2 == 1
    return out


def tube_surface_point(rib, fi: float, alpha: float) -> np.ndarray:
    """(3,) point of the rib's analytic tube surface at fractional sample index fi, angle alpha."""
    t = rib.tube
    m = len(t.points_mm)
    fi = float(np.clip(fi, 0, m - 1))
    i = min(int(fi), m - 2)
    f = fi - i
    c = t.points_mm[i] * (1 - f) + t.points_mm[i + 1] * f
    tg = t.tangents[i] * (1 - f) + t.tangents[i + 1] * f
    tg /= np.linalg.norm(tg)
    ev = t.e_v[i] * (1 - f) + t.e_v[i + 1] * f
    ev -= (ev @ tg) * tg
    ev /= np.linalg.norm(ev)
    et = np.cross(tg, ev)
    av = t.a_v_mm[i] * (1 - f) + t.a_v_mm[i + 1] * f
    at = t.a_t_mm[i] * (1 - f) + t.a_t_mm[i + 1] * f
    return c + av * np.cos(alpha) * ev + at * np.sin(alpha) * et


def local_params(rib, p: np.ndarray) -> tuple[float, float]:
    """(fi, alpha) of a point near the rib's tube surface."""
    t = rib.tube
    i = cKDTree(t.points_mm).query(p)[1]
    d = p - t.points_mm[i]
    return float(i), float(np.arctan2((d @ t.e_t[i]) / t.a_t_mm[i], (d @ t.e_v[i]) / t.a_v_mm[i]))


# --------------------------------------------------------------------------------- tests


def test_ribs_names_labels_and_order(phantom):
    assert [r.name for r in phantom.ribs] == list(RIB_NAMES)
    for r in phantom.ribs:
        assert r.side == r.name[0] and r.number == int(r.name[1:])
        expected = 91 + r.number if r.side == "L" else 103 + r.number
        assert r.label_id == expected
    assert {r.label_id for r in phantom.ribs} == set(range(92, 116))
    assert phantom.label_names()[98] == "rib_left_7" and phantom.label_names()[115] == "rib_right_12"


def test_meshes_watertight_outward_one_component_each(phantom):
    for r in phantom.ribs:
        m = r.mesh
        assert m.is_watertight, r.name
        assert m.is_winding_consistent, r.name
        assert n_components(m) == 1, r.name
    volumes = np.array([r.mesh.volume for r in phantom.ribs[:3]])
    assert np.all(volumes > 3000)  # mm^3, outward normals give positive volume
    assert n_components(phantom.mesh) == 24
    assert len(phantom.mesh.faces) == sum(len(r.mesh.faces) for r in phantom.ribs)


def test_cage_size_and_frame(phantom):
    lo, hi = phantom.mesh.bounds
    ext = hi - lo
    assert 260 < ext[0] < 300 and 175 < ext[1] < 215 and 225 < ext[2] < 275
    assert np.all(np.abs((lo + hi)[1:] / 2) < 2.0)  # centred in y and z; x = 0 is mid-sagittal
    for r in phantom.ribs:
        sign = -1 if r.side == "L" else 1  # RAS+: +x = patient's right
        assert np.all(sign * r.centerline_mm[:, 0] > 0), r.name
    lengths = {r.name: r.length_mm for r in phantom.ribs}
    assert 110 < lengths["L1"] < 150 and 110 < lengths["R12"] < 170
    assert max(lengths["L6"], lengths["L7"], lengths["L8"]) > 280


def test_centerlines_start_at_spine_and_lie_inside(phantom):
    spine_y = min(r.centerline_mm[0, 1] for r in phantom.ribs)
    for r in phantom.ribs:
        cl = r.centerline_mm
        assert cl.shape == (500, 3) and np.all(np.isfinite(cl))
        step = np.linalg.norm(np.diff(cl, axis=0), axis=1)
        assert step.max() / step.min() < 1.001  # uniform in arc length
        assert 18 < abs(cl[0, 0]) < 28, r.name  # head next to the vertebra
        assert abs(cl[0, 1] - spine_y) < 3, r.name  # all heads on the same coronal line
        assert np.linalg.norm(cl[-1] - cl[0]) > 60  # the tip is far from the head
        # inside the solid: analytic level 0, and the nearest surface is one thickness semi-axis away
        assert tube_level(r, cl).max() < 1e-3
        d, _ = cKDTree(r.mesh.vertices).query(cl)
        assert d.min() > 2.4 and d.max() < 3.7, (r.name, d.min(), d.max())
        # ends are cap centres: the cap poles lie one cap semi-axis beyond them
        assert np.allclose(np.linalg.norm(r.mesh.vertices - cl[0], axis=1).min(), r.tube.cap_mm[0], atol=0.05)
    subset = [phantom.ribs[i] for i in (0, 6, 11, 19)]
    for r in subset:
        assert inside_by_ray_parity(r.mesh, r.centerline_mm[::25]).all(), r.name


def test_ribseg_layout(phantom):
    arr = phantom.ribseg_centerlines()
    assert arr.shape == (24, 500, 3)
    assert np.allclose(arr[6], phantom.centerlines()["L7"]) and np.allclose(
        arr[12], phantom.centerlines()["R1"]
    )


def test_samples_noise_labels_and_normals(phantom):
    clean = sample_surface(phantom, 20_000, noise_mm=0.0, seed=5)
    noisy = sample_surface(phantom, 20_000, noise_mm=0.5, seed=5)
    assert clean.source_format == "phantom" and len(noisy) == 20_000
    assert np.array_equal(clean.labels, noisy.labels)
    diff = noisy.points - clean.points
    assert np.allclose(diff.std(axis=0), 0.5, rtol=0.04) and np.abs(diff.mean(axis=0)).max() < 0.02
    # clean samples lie on the analytic surface of the rib their label names; normals point outwards
    assert np.allclose(np.linalg.norm(clean.normals, axis=1), 1.0)
    for r in phantom.ribs:
        sel = clean.labels == r.label_id
        p, n = clean.points[sel], clean.normals[sel]
        assert abs(sel.mean() - r.mesh.area / phantom.mesh.area) < 0.01  # uniform by area
        assert np.abs(tube_level(r, p) - 1).max() < 0.01, r.name
        assert np.all(tube_level(r, p + 0.3 * n) > 1.03) and np.all(tube_level(r, p - 0.3 * n) < 0.97)
    # the true normals agree with the normals of the mesh faces they were sampled from (faceted:
    # adjacent faces differ by <= 12 deg; the nearest face centroid finds the face or a neighbour)
    r0 = phantom.ribs[0]
    sel = clean.labels == r0.label_id
    face = cKDTree(r0.mesh.triangles_center).query(clean.points[sel])[1]
    cosang = np.sum(r0.mesh.face_normals[face] * clean.normals[sel], axis=1)
    assert cosang.min() > np.cos(np.deg2rad(12))


def test_missing_ribs():
    ph = make_phantom(PhantomConfig(missing_ribs=("L11", "R3")))
    names = [r.name for r in ph.ribs]
    assert len(ph.ribs) == 22 and "L11" not in names and "R3" not in names
    arr = ph.ribseg_centerlines()
    assert np.all(arr[10] == -1) and np.all(arr[14] == -1) and np.all(arr[[0, 11, 13]] != -1)
    assert n_components(ph.mesh) == 22
    pc = sample_surface(ph, 5000, 0.0, 0)
    assert not np.isin([102, 106], pc.labels).any()
    with pytest.raises(RibPullInputError) as err:
        make_phantom(PhantomConfig(missing_ribs=("L13",)))
    assert err.value.code == "bad_parameter"


def test_mirror_swaps_x_and_sides(phantom):
    mir = make_phantom(PhantomConfig(mirror=True))
    assert [r.name for r in mir.ribs] == list(RIB_NAMES)
    flip = np.array([-1.0, 1.0, 1.0])
    for r in mir.ribs:
        other = "R" if r.side == "L" else "L"
        src = phantom.ribs[RIB_NAMES.index(f"{other}{r.number}")]
        assert np.allclose(r.centerline_mm, src.centerline_mm * flip, atol=1e-9)
        assert (r.centerline_mm[:, 0] < 0).all() == (r.side == "L")
        assert r.label_id == (91 if r.side == "L" else 103) + r.number
    m, s = mir.ribs[3].mesh, phantom.ribs[15].mesh  # L4 of the mirror = R4 of the original flipped
    assert cKDTree(s.vertices * flip).query(m.vertices)[0].max() < 1e-9
    assert m.is_winding_consistent and m.volume > 0 and np.isclose(m.volume, s.volume)


def test_scale():
    ph = make_phantom(PhantomConfig(scale=0.5, missing_ribs=tuple(RIB_NAMES[1:])))
    ref = make_phantom(PhantomConfig(missing_ribs=tuple(RIB_NAMES[1:])))
    assert np.allclose(ph.ribs[0].centerline_mm, ref.ribs[0].centerline_mm * 0.5, atol=1e-9)
    assert np.isclose(ph.ribs[0].mesh.volume, ref.ribs[0].mesh.volume * 0.125, rtol=1e-4)


def test_determinism_and_seed_variation(phantom):
    keep = ("L2", "L9", "R5")  # the whole cage is generated; only these ribs are meshed
    cfg = PhantomConfig(seed=3, missing_ribs=tuple(n for n in RIB_NAMES if n not in keep))
    a, b = make_phantom(cfg), make_phantom(cfg)
    assert [r.name for r in a.ribs] == list(keep)
    assert np.array_equal(a.mesh.vertices, b.mesh.vertices) and np.array_equal(a.mesh.faces, b.mesh.faces)
    pa, pb = sample_surface(a, 3000, 0.3, 7), sample_surface(b, 3000, 0.3, 7)
    assert np.array_equal(pa.points, pb.points) and np.array_equal(pa.normals, pb.normals)
    assert not np.array_equal(sample_surface(a, 3000, 0.3, 8).points, pa.points)
    for r in a.ribs:  # seeds change the anatomy by a few percent
        ref = phantom.ribs[RIB_NAMES.index(r.name)]
        rel = abs(r.length_mm / ref.length_mm - 1)
        shift = np.abs(r.centerline_mm - ref.centerline_mm).max()
        assert 0.002 < rel < 0.12 and 1.0 < shift < 25.0, (r.name, rel, shift)


def test_voxelize_matches_mesh_containment(phantom, labels_1mm):
    vol, aff = labels_1mm
    assert vol.dtype == np.uint8 and aff[0, 0] == 1.0
    assert set(np.unique(vol)) == {0} | set(range(92, 116))
    # voxel counts match the mesh volumes (1 mm^3 voxels)
    counts = np.bincount(vol.ravel(), minlength=116)
    for r in phantom.ribs:
        assert abs(counts[r.label_id] - r.mesh.volume) / r.mesh.volume < 0.02, r.name
    # random voxels of a 2-voxel band on both sides of the surface, checked against the triangles
    rng = np.random.default_rng(0)
    set_ijk = np.argwhere(vol > 0)
    near = np.zeros_like(vol, dtype=bool)
    for ax in range(3):
        for sh in (-2, -1, 1, 2):
            near |= np.roll(vol > 0, sh, axis=ax)
    off_ijk = np.argwhere(near & (vol == 0))
    ijk = np.concatenate([set_ijk[rng.choice(len(set_ijk), 1500, replace=False)],
                          off_ijk[rng.choice(len(off_ijk), 1500, replace=False)]])  # fmt: skip
    xyz = ijk @ aff[:3, :3].T + aff[:3, 3]
    # the rib each point belongs to (or is next to): nearest centerline point over all ribs
    all_cl = np.concatenate([r.tube.points_mm for r in phantom.ribs])
    owner = np.repeat(np.arange(len(phantom.ribs)), [len(r.tube.points_mm) for r in phantom.ribs])
    rib_of = owner[cKDTree(all_cl).query(xyz)[1]]
    agree = 0
    for k, r in enumerate(phantom.ribs):
        sel = rib_of == k
        inside_mesh = inside_by_ray_parity(r.mesh, xyz[sel])
        agree += np.sum(inside_mesh == (vol[tuple(ijk[sel].T)] == r.label_id))
    assert agree / len(xyz) >= 0.99, agree / len(xyz)


def test_minimum_gap_between_ribs(phantom):
    """Minimum distance between any two ribs' surfaces (exact on the analytic surfaces)."""
    # coarse passes: pairs whose centerlines come within 8 mm + both semi-axes; then their closest
    # vertex pairs within 8 mm (vertices are < 1 mm apart, so a pair with none closer than 8 mm has a
    # gap > 7 mm); then a local minimisation on the analytic surfaces from the closest pair
    cl_trees = [cKDTree(r.tube.points_mm) for r in phantom.ribs]
    vertex_gaps = []
    for i, a in enumerate(phantom.ribs):
        tree = None
        for j in range(i + 1, len(phantom.ribs)):
            b = phantom.ribs[j]
            reach = 8.0 + a.tube.a_v_mm.max() + b.tube.a_v_mm.max()
            if not np.isfinite(cl_trees[i].query(b.tube.points_mm, distance_upper_bound=reach)[0]).any():
                continue
            tree = tree or cKDTree(a.mesh.vertices)
            d, idx = tree.query(b.mesh.vertices, distance_upper_bound=8.0)
            k = int(np.argmin(d))
            if np.isfinite(d[k]):
                vertex_gaps.append((d[k], i, j, tree.data[idx[k]], b.mesh.vertices[k]))
    vertex_gaps.sort(key=lambda g: g[0])
    assert vertex_gaps and vertex_gaps[0][0] >= 6.0
    for dv, i, j, pa, pb in vertex_gaps[:6]:
        a, b = phantom.ribs[i], phantom.ribs[j]
        x0 = np.array([*local_params(a, pa), *local_params(b, pb)])

        def dist(x, a=a, b=b):
            return np.linalg.norm(tube_surface_point(a, x[0], x[1]) - tube_surface_point(b, x[2], x[3]))

        res = minimize(
            dist, x0, method="Nelder-Mead", options={"xatol": 1e-4, "fatol": 1e-5, "maxiter": 2000}
        )
        assert res.fun <= dv + 0.05
        assert res.fun >= 6.0, (a.name, b.name, res.fun)


def test_write_phantom(tmp_path):
    present = ("L1", "L7", "R12")
    cfg = PhantomConfig(n_points=4000, missing_ribs=tuple(n for n in RIB_NAMES if n not in present))
    paths = write_phantom(tmp_path, cfg, nifti=True, spacing_mm=2.0)
    assert set(paths) == {"points", "truth_mesh", "centerlines", "mask"}
    assert all(p.exists() and p.stat().st_size > 0 for p in paths.values())
    cl = json.loads(paths["centerlines"].read_text())
    assert cl["units"] == "mm" and sorted(cl["ribs"]) == sorted(present)
    assert cl["ribs"]["L7"]["label_id"] == 98 and np.asarray(cl["ribs"]["L7"]["points"]).shape == (500, 3)
    pts = trimesh.load(paths["points"])
    assert len(pts.vertices) == 4000
    truth = trimesh.load(paths["truth_mesh"], process=False)
    assert truth.is_watertight and len(truth.faces) == 3 * 39_744
    img = nib.load(paths["mask"])
    data = np.asarray(img.dataobj)
    assert np.allclose(img.affine[:3, :3], np.eye(3) * 2.0)
    assert set(np.unique(data)) == {0, 92, 98, 115}
    with pytest.raises(RibPullInputError):
        write_phantom(tmp_path / "bad", PhantomConfig(scale=0.0))
