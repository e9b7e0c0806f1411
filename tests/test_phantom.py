"""Tests of the synthetic ribcage: names, watertight meshes, exact truth, sampling, voxels, gaps;
sternum and costal cartilages, separable / isolated ribs, partial-volume anisotropic label maps."""

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
    Tube,
    isolated_ribs,
    make_phantom,
    rib_gaps_mm,
    sample_surface,
    separable_ribs,
    tube_level,
    tube_mesh,
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


# ------------------------------------------------------------------ sternum and cartilages


@pytest.fixture(scope="module")
def sternum_phantom():
    return make_phantom(PhantomConfig(sternum=True))


def test_sternum_keeps_ribs_and_adds_structures(phantom, sternum_phantom):
    sp = sternum_phantom
    assert [r.name for r in sp.ribs] == list(RIB_NAMES)
    for a, b in zip(phantom.ribs, sp.ribs):  # the ribs are exactly the same
        assert np.array_equal(a.centerline_mm, b.centerline_mm) and np.array_equal(
            a.mesh.vertices, b.mesh.vertices
        )
    assert sp.centerlines().keys() == phantom.centerlines().keys()  # centerlines: ribs only
    names = [s.name for s in sp.structures]
    assert names[0] == "sternum" and sorted(names[1:]) == sorted(
        f"costal_cartilage_{s}{n}" for s in "LR" for n in range(1, 11)
    )
    assert {s.label_id for s in sp.structures} == {116, 117} and sp.structures[0].label_id == 116
    assert sp.label_names()[116] == "sternum" and sp.label_names()[117] == "costal_cartilages"
    assert 116 not in phantom.label_names() and phantom.structures == []
    # truth mesh: ribs then structures, one closed component each, labelled per face
    assert n_components(sp.mesh) == 24 + 21
    counts = np.bincount(sp.face_labels(), minlength=118)
    assert counts[116] == len(sp.structures[0].mesh.faces)
    assert counts[117] == sum(len(s.mesh.faces) for s in sp.structures[1:])
    assert len(sp.face_labels()) == len(sp.mesh.faces)
    for s in sp.structures:
        assert s.mesh.is_watertight and s.mesh.is_winding_consistent and s.mesh.volume > 300, s.name
        assert n_components(s.mesh) == 1, s.name
        assert inside_by_ray_parity(s.mesh, s.tube.points_mm[:: max(1, len(s.tube.points_mm) // 8)]).all(), (
            s.name
        )
    # sternum: on the midline, anterior, 150-180 mm long, 25-40 mm wide, 10-12 mm thick
    st = sp.structures[0]
    lo, hi = st.mesh.bounds
    assert abs(lo[0] + hi[0]) < 0.1 and 25 < hi[0] - lo[0] < 40
    length = np.linalg.norm(st.tube.points_mm[-1] - st.tube.points_mm[0]) + st.tube.cap_mm.sum()
    assert 150 < length < 180
    thickness = np.ptp(st.mesh.vertices @ st.tube.e_t[len(st.tube.e_t) // 2])
    assert 10 <= thickness <= 12
    tips_y = [r.centerline_mm[-1, 1] for r in sp.ribs if r.number <= 7]
    assert st.tube.points_mm[:, 1].min() > np.min(tips_y)  # in front of the ribs' tips
    # every cartilage lies medial of its rib's tip (towards the sternum) and outside every other solid
    for s in sp.structures[1:]:
        rib = sp.ribs[RIB_NAMES.index(s.rib)]
        assert np.abs(s.tube.points_mm[-1, 0]) < np.abs(rib.centerline_mm[-1, 0]), s.name
        for other in sp.solids:
            if other is not s:
                assert tube_level(other, s.mesh.vertices[::7]).min() > 1.0, (
                    s.name,
                    getattr(other, "name", ""),
                )


def test_sternum_samples_labels_and_normals(sternum_phantom):
    sp = sternum_phantom
    pc = sample_surface(sp, 30_000, noise_mm=0.0, seed=3)
    assert pc.label_names[116] == "sternum" and pc.label_names[117] == "costal_cartilages"
    for label in (116, 117):
        sel = pc.labels == label
        area = sum(s.mesh.area for s in sp.structures if s.label_id == label)
        assert abs(sel.mean() - area / sp.mesh.area) < 0.01
        p, n = pc.points[sel], pc.normals[sel]
        solids = [s for s in sp.structures if s.label_id == label]
        levels = np.stack([tube_level(s, p) for s in solids])  # (solids, N)
        owner = levels.argmin(axis=0)
        assert np.abs(levels.min(axis=0) - 1).max() < 0.01  # on the analytic surface
        for k, solid in enumerate(solids):  # normals = the level's outward gradient (finite differences)
            q, nq = p[owner == k], n[owner == k]
            h = 1e-3
            grad = np.stack(
                [(tube_level(solid, q + h * e) - tube_level(solid, q - h * e)) / (2 * h) for e in np.eye(3)],
                axis=1,
            )
            grad /= np.linalg.norm(grad, axis=1, keepdims=True)
            assert np.sum(grad * nq, axis=1).min() > 0.995, solid.name
            assert np.all(tube_level(solid, q + 0.3 * nq) > 1.0) and np.all(
                tube_level(solid, q - 0.3 * nq) < 1.0
            )
    # rib samples unaffected in kind: still on their rib's surface
    r = sp.ribs[6]
    sel = pc.labels == r.label_id
    assert sel.sum() > 100 and np.abs(tube_level(r, pc.points[sel]) - 1).max() < 0.01


def test_cartilage_gaps_and_separable_ribs(phantom, sternum_phantom):
    sp = sternum_phantom
    designed = sp.cartilage_gaps_mm
    assert sorted(designed) == sorted(f"{s}{n}" for s in "LR" for n in range(1, 11))
    for s in sp.structures[1:]:
        rib = sp.ribs[RIB_NAMES.index(s.rib)]
        # independent of rib_gaps_mm: the poles of rib tip and cartilage start are mesh vertices
        d = cKDTree(rib.mesh.vertices).query(s.mesh.vertices)[0].min()
        assert 1.0 <= d <= 3.5 and abs(d - s.gap_mm) < 0.02, (s.name, d, s.gap_mm)
    gaps = rib_gaps_mm(sp)
    for name, gap in gaps.items():
        if name in designed:  # the nearest other structure is the rib's own cartilage, at the designed gap
            assert abs(gap - designed[name]) < 0.05, (name, gap, designed[name])
        else:  # floating ribs 11-12: nothing within 5 mm
            assert gap == np.inf and name[1:] in ("11", "12")
    separable = separable_ribs(sp, min_gap_mm=1.5)
    expected = [n for n in RIB_NAMES if designed.get(n, np.inf) >= 1.5]
    assert separable == expected
    assert 0 < len(RIB_NAMES) - len(separable) == 4  # a strict, non-empty subset: 4 ribs are too close
    assert separable_ribs(sp, min_gap_mm=3.1) == [n for n in RIB_NAMES if n[1:] in ("11", "12")]
    assert min(gaps.values()) >= 1.0  # at 0.8 mm every rib is separable
    assert separable_ribs(phantom) == list(RIB_NAMES)  # ribs alone are >= 6 mm apart


def _merged_with_cartilage(sp, rib_name: str) -> trimesh.Trimesh:
    """Truth mesh in which rib_name and its cartilage are one tube (the gap filled, one component)."""
    rib = sp.ribs[RIB_NAMES.index(rib_name)]
    cart = next(s for s in sp.structures if s.rib == rib_name)
    a, b = rib.tube, cart.tube

    def cat(k):
        return np.concatenate([getattr(a, k), getattr(b, k)])

    tube = Tube(cat("points_mm"), cat("tangents"), cat("e_v"), cat("e_t"), cat("a_v_mm"), cat("a_t_mm"),
                np.array([a.cap_mm[0], b.cap_mm[1]]), a.step_mm)  # fmt: skip
    merged = tube_mesh(tube, n_rings=600)
    assert merged.is_watertight and n_components(merged) == 1
    others = [s.mesh for s in sp.solids if s is not rib and s is not cart]
    return trimesh.util.concatenate(others + [merged])


def test_isolated_ribs(sternum_phantom):
    sp = sternum_phantom
    iso = isolated_ribs(sp.mesh, sp)
    assert iso == {n: True for n in RIB_NAMES}  # the truth keeps every rib apart, separable or not
    merged = _merged_with_cartilage(sp, "L7")
    iso = isolated_ribs(merged, sp)
    assert iso["L7"] is False and all(v for k, v in iso.items() if k != "L7")
    # a missing rib is not isolated (no component covers it); names restricts the answer
    keep = [s.mesh for s in sp.solids if getattr(s, "name", "") != "R3"]
    assert isolated_ribs(trimesh.util.concatenate(keep), sp, names=["R3", "R4"]) == {"R3": False, "R4": True}
    with pytest.raises(RibPullInputError):
        isolated_ribs(sp.mesh, sp, names=["X1"])


def test_sternum_with_missing_and_mirrored_ribs():
    ph = make_phantom(PhantomConfig(sternum=True, mirror=True, missing_ribs=("L3", "R12")))
    names = [s.name for s in ph.structures]
    assert "costal_cartilage_L3" not in names and len(names) == 20 and names[0] == "sternum"
    assert n_components(ph.mesh) == 22 + 20
    ref = make_phantom(PhantomConfig(mirror=True, missing_ribs=("L3", "R12")))
    assert all(np.array_equal(a.centerline_mm, b.centerline_mm) for a, b in zip(ph.ribs, ref.ribs))
    gaps = rib_gaps_mm(ph)
    assert all(abs(gaps[k] - g) < 0.05 for k, g in ph.cartilage_gaps_mm.items())


# ----------------------------------------------------------- partial-volume, anisotropic voxels


def _check_partial_volume(sp, spacing):
    vol, aff = voxelize(sp, spacing_mm=spacing, partial_volume=True)
    sp3 = np.broadcast_to(np.asarray(spacing, float), (3,))
    assert np.allclose(np.diag(aff)[:3], sp3) and np.allclose(aff[:3, :3], np.diag(sp3))
    assert set(np.unique(vol)) == {0, 116, 117} | set(range(92, 116))
    voxel_mm3 = float(np.prod(sp3))
    counts = np.bincount(vol.ravel(), minlength=118) * voxel_mm3
    for r in sp.ribs:
        assert abs(counts[r.label_id] / r.mesh.volume - 1) < 0.03, (r.name, counts[r.label_id], r.mesh.volume)
    assert abs(counts[116] / sp.structures[0].mesh.volume - 1) < 0.02
    assert abs(counts[117] / sum(s.mesh.volume for s in sp.structures[1:]) - 1) < 0.03
    # "more than half of the voxel inside": brute-force fractions (9 x 9 x 9 sub-points) of random voxels
    # next to the surfaces of a few solids, independent of the implementation's sub-sampling
    rng = np.random.default_rng(1)
    grid = (np.stack(np.meshgrid(*[np.arange(9)] * 3, indexing="ij"), -1).reshape(-1, 3) + 0.5) / 9 - 0.5
    checked = 0
    for solid in (sp.ribs[0], sp.ribs[18], sp.structures[0], sp.structures[7]):
        v = solid.mesh.vertices[rng.choice(len(solid.mesh.vertices), 150, replace=False)]
        v = v + rng.uniform(-1, 1, v.shape) * sp3
        ijk = np.unique(np.rint((v - aff[:3, 3]) / sp3).astype(int), axis=0)
        centres = aff[:3, 3] + ijk * sp3
        sub = (centres[:, None, :] + grid[None] * sp3).reshape(-1, 3)
        frac = (tube_level(solid, sub) <= 1.0).reshape(len(ijk), -1).mean(axis=1)
        clear = np.abs(frac - 0.5) > 0.08  # leave out near-ties (the sub-sampling estimate differs there)
        labelled = vol[tuple(ijk.T)] == solid.label_id
        assert np.array_equal(labelled[clear], frac[clear] > 0.5), solid.name
        checked += clear.sum()
    assert checked > 300
    # where the majority rule and the centre test disagree (curved surfaces), the majority is right
    centre_vol, _ = voxelize(sp, spacing_mm=spacing)
    assert centre_vol.shape == vol.shape
    solid_of = {s.label_id: s for s in sp.solids if s.label_id != 117}  # one solid per label
    diff = np.argwhere((vol != centre_vol) & (vol != 117) & (centre_vol != 117))
    diff = diff[rng.choice(len(diff), min(400, len(diff)), replace=False)]
    agree = n = 0
    for ijk in diff:
        label = int(vol[tuple(ijk)] or centre_vol[tuple(ijk)])
        sub = aff[:3, 3] + ijk * sp3 + grid * sp3
        frac = (tube_level(solid_of[label], sub) <= 1.0).mean()
        if abs(frac - 0.5) > 0.03:
            n += 1
            agree += (vol[tuple(ijk)] == label) == (frac > 0.5)
    assert n > 50 and agree / n > 0.9, (n, agree)
    return vol


def test_partial_volume_isotropic(sternum_phantom):
    _check_partial_volume(sternum_phantom, 1.5)


def test_partial_volume_anisotropic(sternum_phantom):
    _check_partial_volume(sternum_phantom, (0.75, 0.75, 2.5))


def test_voxelize_tuple_spacing_and_errors(phantom):
    a, aff_a = voxelize(phantom, spacing_mm=2.0)
    b, aff_b = voxelize(phantom, spacing_mm=(2.0, 2.0, 2.0))
    assert np.array_equal(a, b) and np.array_equal(aff_a, aff_b)
    c, aff_c = voxelize(phantom, spacing_mm=(1.5, 2.0, 3.0))
    assert np.allclose(np.diag(aff_c)[:3], (1.5, 2.0, 3.0))
    ext = np.array(c.shape) * (1.5, 2.0, 3.0)
    assert np.allclose(ext, np.array(a.shape) * 2.0, atol=3.1)  # same box, other voxels
    for bad in (0.0, (1.0, -1.0, 1.0), (1.0, 2.0)):
        with pytest.raises(RibPullInputError):
            voxelize(phantom, spacing_mm=bad)


def test_write_phantom_sternum_anisotropic_and_cli(tmp_path):
    present = ("L1", "L7", "R10")
    missing = tuple(n for n in RIB_NAMES if n not in present)
    cfg = PhantomConfig(n_points=3000, missing_ribs=missing, sternum=True)
    paths = write_phantom(tmp_path / "a", cfg, nifti=True, spacing_mm=(1.5, 1.5, 3.0), partial_volume=True)
    img = nib.load(paths["mask"])
    assert np.allclose(img.header.get_zooms(), (1.5, 1.5, 3.0))
    assert set(np.unique(np.asarray(img.dataobj))) == {0, 92, 98, 113, 116, 117}
    truth = trimesh.load(paths["truth_mesh"], process=False)
    assert truth.is_watertight and n_components(truth) == 3 + 1 + 3
    pts = trimesh.load(paths["points"])
    assert len(pts.vertices) == 3000
    cl = json.loads(paths["centerlines"].read_text())
    assert sorted(cl["ribs"]) == sorted(present)  # centerlines stay ribs only

    from ribpull_core.cli import main

    out = tmp_path / "cli"
    rc = main(["phantom", str(out), "--points", "500", "--sternum", "--nifti", "--partial-volume",
               "--spacing", "2,2,3", "--missing", *missing])  # fmt: skip
    assert rc == 0
    img = nib.load(out / "mask.nii.gz")
    assert np.allclose(img.header.get_zooms(), (2.0, 2.0, 3.0))
    assert {116, 117} <= set(np.unique(np.asarray(img.dataobj)))
    for bad in ("2,2", "0", "a,b,c"):
        with pytest.raises(SystemExit) as err:
            main(["phantom", str(out), "--spacing", bad])
        assert err.value.code == 2


@pytest.mark.parametrize("spacing", [3.0, (2.0, 2.0, 4.0)])
def test_partial_volume_majority_rule_on_coarse_voxels(spacing):
    """Coarse voxels on one rib: the label is set iff a brute-force 7 x 7 x 7 estimate of the inside
    fraction is > 1/2, including voxels where that differs from the centre test."""
    ph = make_phantom(PhantomConfig(missing_ribs=tuple(n for n in RIB_NAMES if n != "L7")))
    rib = ph.ribs[0]
    vol, aff = voxelize(ph, spacing_mm=spacing, partial_volume=True)
    centre_vol, _ = voxelize(ph, spacing_mm=spacing)
    sp3 = np.diag(aff)[:3]
    ijk = np.argwhere(np.ones(vol.shape, dtype=bool))
    centres = aff[:3, 3] + ijk * sp3
    near = cKDTree(rib.tube.points_mm).query(centres, distance_upper_bound=9.0)[0] < np.inf
    ijk, centres = ijk[near], centres[near]
    grid = (np.stack(np.meshgrid(*[np.arange(7)] * 3, indexing="ij"), -1).reshape(-1, 3) + 0.5) / 7 - 0.5
    sub = (centres[:, None, :] + grid[None] * sp3).reshape(-1, 3)
    frac = (tube_level(rib, sub) <= 1.0).reshape(len(ijk), -1).mean(axis=1)
    clear = np.abs(frac - 0.5) > 0.05
    labelled = vol[tuple(ijk.T)] == rib.label_id
    centre_in = centre_vol[tuple(ijk.T)] == rib.label_id
    assert np.array_equal(labelled[clear], frac[clear] > 0.5)
    assert np.sum(clear & (centre_in != (frac > 0.5))) >= 3  # the centre test gets these wrong
    assert np.all(frac[labelled] > 0.4) and np.all(frac[~labelled] < 0.6)  # near-ties only either way


def test_a_roughened_label_map_flips_patches_of_its_boundary_only():
    from scipy import ndimage

    from ribpull_core.phantom import roughen_label_map

    vol = np.zeros((40, 40, 40), np.uint8)
    vol[8:20, 8:30, 10:30] = 5
    vol[22:32, 8:30, 10:30] = 7
    rough = roughen_label_map(vol, flip_fraction=0.1, seed=3)
    assert np.array_equal(rough, roughen_label_map(vol, flip_fraction=0.1, seed=3))  # seeded
    assert not np.array_equal(rough, roughen_label_map(vol, flip_fraction=0.1, seed=4))
    six = ndimage.generate_binary_structure(3, 1)
    inside = vol > 0
    inner = inside & ~ndimage.binary_erosion(inside, six)
    outer = ~inside & ndimage.binary_dilation(inside, six)
    changed = rough != vol
    # only boundary voxels change, about the fraction asked on either side
    assert not (changed & ~(inner | outer)).any()
    dents, bumps = changed & inner, changed & outer
    assert (rough[dents] == 0).all() and set(np.unique(rough[bumps])) <= {5, 7}
    assert 0.05 < dents.sum() / inner.sum() < 0.15 and 0.05 < bumps.sum() / outer.sum() < 0.15
    # in patches: most flipped voxels have a flipped 26-neighbour
    neighbours = ndimage.convolve(changed.astype(int), np.ones((3, 3, 3), int), mode="constant") - 1
    assert (neighbours[changed] > 0).mean() > 0.7
