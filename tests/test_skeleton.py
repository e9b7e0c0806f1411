"""Skeleton stage: contraction (paper eq. 3-4), curves, labels, export, metrics.

Synthetic tubes are built here (watertight swept ellipses with half-ellipsoid caps); the ribcage
tests use ribpull_core.phantom.
"""

from __future__ import annotations

import itertools
import json

import numpy as np
import pygltflib
import pytest
import trimesh
from scipy.spatial import cKDTree

from ribpull_core.errors import RibPullInputError
from ribpull_core.skeleton import (
    Skeleton,
    SkeletonConfig,
    export_skeleton,
    laplacian_contraction,
    skeleton_from_mesh,
    skeleton_metrics,
    skeletonize,
)
from ribpull_core.skeleton.curves import (
    arc_length,
    ball_sample,
    resample_polyline,
    rotation_minimizing_frames,
    tree_paths,
)
from ribpull_core.skeleton.labels import (
    geometric_labels,
    label_name,
    normalise_rib_name,
    number_by_height,
    totalseg_rib_name,
)

# ------------------------------------------------------------------------------------ helpers


def tube(axis_mm: np.ndarray, a_mm: float = 4.0, b_mm: float = 4.0, n_around: int = 40, n_cap: int = 8):
    """Watertight tube around a polyline: elliptical sections (semi-axes a, b) in rotation-minimising
    frames and half-ellipsoid caps of length b centred on the axis ends."""
    t, n, bn = rotation_minimizing_frames(axis_mm)
    ang = np.linspace(0, 2 * np.pi, n_around, endpoint=False)

    def section(i: int, lat: float, out: float) -> np.ndarray:
        """Ring of the section at node i, shrunk by cos(lat) and pushed out along the tangent."""
        ell = a_mm * np.cos(ang)[:, None] * n[i] + b_mm * np.sin(ang)[:, None] * bn[i]
        return axis_mm[i] + np.cos(lat) * ell + out * b_mm * np.sin(lat) * t[i]

    lats = np.linspace(0, np.pi / 2, n_cap + 1)[1:-1]
    rings = [section(0, p, -1.0) for p in lats[::-1]]
    rings += [section(i, 0.0, 0.0) for i in range(len(axis_mm))]
    rings += [section(len(axis_mm) - 1, p, 1.0) for p in lats]
    verts = np.vstack(rings + [axis_mm[:1] - b_mm * t[0], axis_mm[-1:] + b_mm * t[-1]])
    r = len(rings)
    ids = np.arange(r * n_around).reshape(r, n_around)
    j, jn = np.arange(n_around), (np.arange(n_around) + 1) % n_around
    faces = [np.stack([ids[:-1, j], ids[1:, j], ids[:-1, jn]], -1).reshape(-1, 3),
             np.stack([ids[:-1, jn], ids[1:, j], ids[1:, jn]], -1).reshape(-1, 3),
             np.column_stack([np.full(n_around, r * n_around), ids[0, j], ids[0, jn]]),
             np.column_stack([np.full(n_around, r * n_around + 1), ids[-1, jn], ids[-1, j]])]
    mesh = trimesh.Trimesh(verts, np.vstack(faces), process=True)
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def straight(length=100.0, start=(0.0, 0.0, 0.0), direction=(1.0, 0.2, 0.1), n=200):
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    return np.asarray(start) + np.linspace(0, length, n)[:, None] * d


def torus_arc(radius=60.0, angle=np.pi, n=300):
    u = np.linspace(0, angle, n)
    return np.c_[radius * np.cos(u), radius * np.sin(u), 10 * np.sin(u / 2)]


def sample(mesh, n, seed=0):
    pts, face = trimesh.sample.sample_surface(mesh, n, seed=np.random.default_rng(seed))
    return pts, mesh.face_normals[face]


def axis_distance(curve_mm, axis_mm):
    d, _ = cKDTree(resample_polyline(axis_mm, 0.05)).query(curve_mm)
    return d


@pytest.fixture(scope="module")
def straight_case():
    axis = straight()
    mesh = tube(axis, 4.0, 4.0)
    assert mesh.is_watertight
    pts, nrm = sample(mesh, 3000)
    return axis, mesh, pts, nrm


@pytest.fixture(scope="module")
def phantom_mod():
    return pytest.importorskip("ribpull_core.phantom")


# ------------------------------------------------------------------------------- contraction


def test_contraction_moves_points_onto_the_axis(straight_case):
    axis, _, pts, _ = straight_case
    contracted, info = laplacian_contraction(pts, SkeletonConfig())
    before, after = axis_distance(pts, axis), axis_distance(contracted, axis)
    assert before.mean() == pytest.approx(4.0, abs=0.3)
    assert after.mean() < 1.0  # paper eq. 3-4 pulls the surface to the medial curve
    (c,) = info["components"]
    assert 1 <= c["iterations"] <= 20
    ratios = [h["ring_ratio"] for h in c["history"] if not h.get("rejected")]
    assert all(b <= a for a, b in itertools.pairwise(ratios)) and ratios[-1] < 0.8
    assert contracted.shape == pts.shape and np.isfinite(contracted).all()


def test_contraction_keeps_separate_tubes_separate():
    ax1, ax2 = straight(start=(0, 0, 0), direction=(1, 0, 0)), straight(start=(0, 15, 0), direction=(1, 0, 0))
    p1, _ = sample(tube(ax1, 4, 3), 2000, 1)
    p2, _ = sample(tube(ax2, 4, 3), 2000, 2)
    pts = np.vstack([p1, p2])
    contracted, info = laplacian_contraction(pts, SkeletonConfig())
    assert len(info["components"]) == 2
    # every contracted point stays closer to its own tube's axis than to the other one
    own = np.r_[axis_distance(contracted[:2000], ax1), axis_distance(contracted[2000:], ax2)]
    other = np.r_[axis_distance(contracted[:2000], ax2), axis_distance(contracted[2000:], ax1)]
    assert (own < other).all() and own.max() < 4.0


# ------------------------------------------------------------------------------- skeletonize


def test_straight_tube_gives_one_path_on_the_axis(straight_case):
    axis, _, pts, nrm = straight_case
    skel = skeletonize(pts, normals=nrm)
    assert len(skel.curves) == 1
    m = skeleton_metrics(skel, {"tube": axis})
    assert (m["n_paths"], m["n_branch_nodes"], m["n_cycles"]) == (1, 0, 0)
    assert m["mean_dist_mm"] < 0.1 * 4.0 and m["coverage"] > 0.98
    c = skel.curves[0]
    assert c.length_mm == pytest.approx(100.0, abs=2.0)
    assert c.mean_radius_mm == pytest.approx(4.0, abs=0.3)
    assert c.max_curvature_per_mm < 0.01
    steps = np.linalg.norm(np.diff(skel.curve_points(c), axis=0), axis=1)
    assert steps.max() <= 1.0 + 1e-6


def test_curved_elliptical_tube_gives_one_path_on_the_axis():
    axis = torus_arc()
    mesh = tube(axis, 5.5, 3.5)
    pts, nrm = sample(mesh, 4000, 3)
    progress = []
    skel = skeletonize(pts, normals=nrm, progress=lambda f, msg: progress.append(f))
    m = skeleton_metrics(skel, {"arc": axis})
    assert (m["n_paths"], m["n_branch_nodes"], m["n_cycles"]) == (1, 0, 0)
    assert m["mean_dist_mm"] < 0.1 * 3.5 and m["p95_dist_mm"] < 0.5 and m["coverage"] > 0.98
    assert skel.curves[0].length_mm == pytest.approx(arc_length(axis)[-1], rel=0.02)
    assert skel.curves[0].max_curvature_per_mm == pytest.approx(1 / 60.0, rel=0.3)
    assert progress[-1] == 1.0 and all(b >= a for a, b in itertools.pairwise(progress))


def test_two_tubes_give_two_paths():
    ax1 = straight(80, (0, 0, 0), (1, 0, 0.1))
    ax2 = torus_arc(40.0, np.pi / 2) + [0, 0, 30]
    p1, _ = sample(tube(ax1, 4, 3), 2500, 4)
    p2, _ = sample(tube(ax2, 4, 3), 2500, 5)
    skel = skeletonize(np.vstack([p1, p2]))
    m = skeleton_metrics(skel, {"a": ax1, "b": ax2})
    assert (m["n_paths"], m["n_components"], m["n_branch_nodes"], m["n_cycles"]) == (2, 2, 0, 0)
    assert m["mean_dist_mm"] < 0.3 and m["coverage"] > 0.98
    for c in skel.curves:  # each curve lies along one tube only
        d1, d2 = axis_distance(skel.curve_points(c), ax1), axis_distance(skel.curve_points(c), ax2)
        assert (d1 < 1.5).all() or (d2 < 1.5).all()


def test_fused_t_junction_keeps_a_real_branch():
    main, side = straight(120, (0, 0, 0), (1, 0, 0)), straight(60, (60, 0, 0), (0, 1, 0))

    def inside(p, axis, r=4.0):  # points of one tube's surface that lie inside the other tube
        length = np.linalg.norm(axis[-1] - axis[0])
        d = (axis[-1] - axis[0]) / length
        t = (p - axis[0]) @ d
        return (np.linalg.norm(p - axis[0] - np.outer(t, d), axis=1) < r) & (t > 0) & (t < length)

    p1, _ = sample(tube(main, 4, 4), 3000, 1)
    p2, _ = sample(tube(side, 4, 4), 1600, 2)
    pts = np.vstack([p1[~inside(p1, side)], p2[~inside(p2, main)]])
    skel = skeletonize(pts)
    m = skeleton_metrics(skel, {"main": main, "side": side})
    assert (m["n_components"], m["n_branch_nodes"], m["n_paths"], m["n_cycles"]) == (1, 1, 3, 0)
    assert len(skel.curves) == 2 and skel.curves[1].label.endswith("_branch")
    assert skel.curves[0].length_mm == pytest.approx(120, abs=3) and m["coverage"] > 0.98
    assert m["mean_dist_mm"] < 0.3


def test_skeleton_from_mesh_radius_comes_from_the_mesh():
    axis = straight(60, direction=(0, 1, 0))
    skel = skeleton_from_mesh(tube(axis, 3.0, 3.0), n_points=3000)
    assert len(skel.curves) == 1
    interior = skel.radius_mm[5:-5]
    assert np.median(interior) == pytest.approx(3.0, abs=0.1)


@pytest.mark.parametrize(
    "points, code",
    [
        (np.random.default_rng(0).normal(size=(10, 3)), "too_few_points"),
        (np.c_[np.random.default_rng(0).normal(size=(500, 2)) * 20, np.zeros(500)], "degenerate"),
        (np.outer(np.linspace(0, 100, 500), [1.0, 2.0, 3.0]), "degenerate"),
        (np.where(np.arange(1500)[:, None] == 7, np.nan, np.random.default_rng(0).normal(size=(1500, 3))),
         "non_finite"),
        (np.zeros((100, 2)), "bad_parameter"),
    ],
    ids=["too_few", "plane", "line", "nan", "shape"],
)
def test_degenerate_inputs_raise_clear_errors(points, code):
    with pytest.raises(RibPullInputError) as exc:
        skeletonize(points)
    assert exc.value.code == code and len(str(exc.value)) > 20
    with pytest.raises(RibPullInputError):
        laplacian_contraction(points, SkeletonConfig())


def test_too_sparse_for_separate_ribs_raises(straight_case):
    _, _, pts, _ = straight_case
    sparse_pts = pts[::40] * 3.0  # 75 points over a 300 mm tube: nothing links up
    with pytest.raises(RibPullInputError) as exc:
        skeletonize(sparse_pts)
    assert exc.value.code == "too_few_points"


def test_wrong_label_shape_is_rejected(straight_case):
    _, _, pts, _ = straight_case
    with pytest.raises(RibPullInputError) as exc:
        skeletonize(pts, point_labels=np.zeros(5, int))
    assert exc.value.code == "bad_parameter"


# ------------------------------------------------------------------------------------ labels


def test_label_names():
    assert totalseg_rib_name(98) == "L7" and totalseg_rib_name(110) == "R7"
    assert totalseg_rib_name(92) == "L1" and totalseg_rib_name(115) == "R12" and totalseg_rib_name(5) is None
    assert normalise_rib_name("rib_left_7") == "L7" and normalise_rib_name("rib_right_12") == "R12"
    assert normalise_rib_name("r3") == "R3" and normalise_rib_name("sternum") is None
    assert label_name(98, {98: "rib_left_7"}) == "L7" and label_name(98, None) == "L7"
    assert label_name(3, {3: "sternum"}) == "sternum" and label_name(3, None) == "label_3"


def test_numbering_skips_a_missing_rib():
    z = np.array([0.0, -20.0, -40.0, -80.0, -100.0])  # rib 4 missing
    assert number_by_height(z, 20.0).tolist() == [1, 2, 3, 5, 6]
    assert number_by_height(z[::-1], 20.0).tolist() == [6, 5, 3, 2, 1]


def test_geometric_labels_of_true_centerlines_and_their_mirror(phantom_mod):
    ph = phantom_mod.make_phantom(phantom_mod.PhantomConfig(seed=0, missing_ribs=("L1", "R6")))
    cl = ph.centerlines()
    names = list(cl)
    mid = 0.0
    assert geometric_labels([cl[n] for n in names], mid) == names
    mirrored = [cl[n] * [-1, 1, 1] for n in names]
    swapped = [("R" if n[0] == "L" else "L") + n[1:] for n in names]
    assert geometric_labels(mirrored, mid) == swapped


def test_mirrored_phantom_labels_swap_sides(phantom_mod):
    cfg = phantom_mod.PhantomConfig(seed=0, mirror=True)
    ph = phantom_mod.make_phantom(cfg)
    ph0 = phantom_mod.make_phantom(phantom_mod.PhantomConfig(seed=0))
    cloud = phantom_mod.sample_surface(ph, 20_000, 0.3, seed=0)
    skel = skeletonize(cloud.points, normals=cloud.normals)  # no labels: names from geometry
    m = skeleton_metrics(skel, ph.centerlines())
    assert (m["n_paths"], m["n_branch_nodes"], m["n_cycles"]) == (24, 0, 0)
    assert m["label_accuracy"] == 1.0 and m["coverage"] > 0.98 and m["mean_dist_mm"] < 0.45
    # the curve lying on the original phantom's L7, mirrored, is called R7
    l7 = ph0.centerlines()["L7"] * [-1, 1, 1]
    near = min(skel.curves, key=lambda c: cKDTree(l7).query(skel.curve_points(c))[0].mean())
    assert near.label == "R7"
    # head -> tip order: the first node is the posterior-medial end
    pts = skel.curve_points(near)
    assert np.linalg.norm(pts[0] - l7[0]) < 2.0 and np.linalg.norm(pts[-1] - l7[-1]) < 2.0


def test_point_labels_name_the_curves(phantom_mod):
    ph = phantom_mod.make_phantom(phantom_mod.PhantomConfig(seed=1))
    cloud = phantom_mod.sample_surface(ph, 20_000, 0.3, seed=0)
    keep = np.isin(cloud.labels, [96, 97, 98, 108, 109, 110])  # L5-L7, R5-R7
    skel = skeletonize(cloud.points[keep], point_labels=cloud.labels[keep], label_names=cloud.label_names)
    assert sorted(c.label for c in skel.curves) == sorted(["L5", "L6", "L7", "R5", "R6", "R7"])
    assert all(c.label_id == phantom_mod.label_id(c.label[0], int(c.label[1:])) for c in skel.curves)
    truth = {n: c for n, c in ph.centerlines().items() if n in ("L5", "L6", "L7", "R5", "R6", "R7")}
    m = skeleton_metrics(skel, truth)
    assert m["label_accuracy"] == 1.0 and m["n_paths"] == 6


# ---------------------------------------------------------------------------- export, metrics


def test_export_files(straight_case, tmp_path):
    _, mesh, pts, nrm = straight_case
    skel = skeletonize(pts, normals=nrm)
    paths = export_skeleton(skel, tmp_path, mesh_mm=mesh)
    assert set(paths) == {"skeleton.json", "skeleton.glb", "skeleton.obj", "scene.glb"}
    for name in ("skeleton.glb", "scene.glb"):
        gltf = pygltflib.GLTF2().load(str(paths[name]))
        modes = {p.mode for m in gltf.meshes for p in m.primitives}
        assert {1, 4} <= modes, f"{name} needs a LINES (1) and a TRIANGLES (4) primitive, has {modes}"
        scene = trimesh.load(str(paths[name]))
        kinds = {type(g).__name__ for g in scene.geometry.values()}
        assert {"Path3D", "Trimesh"} <= kinds
        lines = next(g for g in scene.geometry.values() if type(g).__name__ == "Path3D")
        assert np.abs(lines.vertices.min(0) - skel.nodes_mm.min(0)).max() < 1e-3  # still mm
    assert len(trimesh.load(str(paths["scene.glb"])).geometry) == 3
    data = json.loads(paths["skeleton.json"].read_text())
    assert data["units"] == "mm"
    assert len(data["nodes"]) == len(skel.nodes_mm) == len(data["radius"])
    comp = data["components"][0]
    assert set(comp) >= {"label", "label_id", "node_ids", "length_mm", "mean_radius_mm", "min_radius_mm",
                         "max_curvature_per_mm"}
    obj = paths["skeleton.obj"].read_text().splitlines()
    v = [ln for ln in obj if ln.startswith("v ")]
    ls = [ln for ln in obj if ln.startswith("l ")]
    assert len(v) == len(skel.nodes_mm) and len(ls) == 1
    assert len(ls[0].split()) - 1 == len(skel.curves[0].node_ids)


def test_metrics_of_the_truth_itself_and_ribseg_layout():
    a, b = straight(50, (0, 0, 0), (1, 0, 0), 51), straight(50, (0, 20, 0), (1, 0, 0), 51)
    nodes = np.vstack([a, b])
    edges = np.r_[np.c_[np.arange(50), np.arange(1, 51)], np.c_[np.arange(51, 101), np.arange(52, 102)]]
    from ribpull_core.skeleton import RibCurve
    curves = [RibCurve("L1", None, list(range(51)), 50, 1, 1, 0), RibCurve("L1", None, list(range(51, 102)), 50, 1, 1, 0)]
    skel = Skeleton(nodes, edges, np.ones(len(nodes)), curves)
    m = skeleton_metrics(skel, {"L1": a, "L2": b})
    assert m["mean_dist_mm"] < 1e-6 and m["coverage"] == 1.0
    assert (m["n_paths"], m["n_branch_nodes"], m["n_cycles"]) == (2, 0, 0)
    assert m["label_accuracy"] == 0.5  # the second curve lies on L2 but is called L1
    ribseg = np.full((24, 500, 3), -1.0)
    x = np.linspace(0, 50, 500)
    ribseg[0], ribseg[5] = np.c_[x, 0 * x, 0 * x], np.c_[x, 0 * x + 20, 0 * x]
    m2 = skeleton_metrics(skel, ribseg)
    assert m2["label_accuracy"] is None and m2["mean_dist_mm"] < 1e-6
    # a closed loop counts as one path and one cycle; a Y has one branch node and three paths
    loop = Skeleton(np.c_[np.cos(np.arange(10)), np.sin(np.arange(10)), np.zeros(10)],
                    np.c_[np.arange(10), (np.arange(10) + 1) % 10], np.ones(10))
    m3 = skeleton_metrics(loop, {"x": a})
    assert (m3["n_paths"], m3["n_cycles"]) == (1, 1)
    y = Skeleton(np.eye(4)[:, :3], [[0, 1], [0, 2], [0, 3]], np.ones(4))
    m4 = skeleton_metrics(y, {"x": a})
    assert (m4["n_paths"], m4["n_branch_nodes"], m4["n_cycles"]) == (3, 1, 0)


def test_ball_sample_matches_the_numpy_farthest_point_loop_ties_included():
    def numpy_ball_sample(points, radius):  # the loop the compiled kernel replaced
        first = int(np.argmax(np.linalg.norm(points - points.mean(axis=0), axis=1)))
        samples, dist = [first], np.linalg.norm(points - points[first], axis=1)
        assign = np.zeros(len(points), dtype=np.int64)
        while dist.max() > radius:
            far = int(np.argmax(dist))
            d_new = np.linalg.norm(points - points[far], axis=1)
            closer = d_new < dist
            assign[closer] = len(samples)
            dist = np.where(closer, d_new, dist)
            samples.append(far)
        return np.asarray(samples), assign

    rng = np.random.default_rng(5)
    t = np.linspace(0.0, 6.0, 3000)
    arc = np.c_[100 * np.cos(t), 80 * np.sin(t), 5 * t] + rng.normal(0.0, 1.5, (3000, 3))
    for points in (arc, np.round(arc)):  # rounded coordinates: equal distances, first one wins
        samples, assign = ball_sample(points, 3.0)
        want_samples, want_assign = numpy_ball_sample(points, 3.0)
        np.testing.assert_array_equal(samples, want_samples)
        np.testing.assert_array_equal(assign, want_assign)
        assert np.linalg.norm(points - points[samples][assign], axis=1).max() <= 3.0
    samples, assign = ball_sample(np.zeros((4, 3)), 1.0)  # one point's ball holds them all
    assert list(samples) == [0] and not assign.any()


def test_tree_paths_match_the_networkx_dijkstra_walks():
    import networkx as nx
    from scipy.sparse.csgraph import minimum_spanning_tree
    from scipy.spatial.distance import cdist

    def networkx_tree_paths(tree, pos, min_branch, clearance):  # the walks the adjacency lists replaced
        d0 = nx.single_source_dijkstra_path_length(tree, next(iter(tree.nodes)))
        dist_a, paths_a = nx.single_source_dijkstra(tree, max(d0, key=d0.get))
        paths = [paths_a[max(dist_a, key=dist_a.get)]]
        covered = set(paths[0])
        while len(covered) < tree.number_of_nodes():
            cov_tree, best = cKDTree(pos[sorted(covered)]), None
            for comp in nx.connected_components(tree.subgraph(set(tree.nodes) - covered)):
                attach = next(c for n in comp for c in tree.neighbors(n) if c in covered)
                dist, pth = nx.single_source_dijkstra(tree.subgraph(set(comp) | {attach}), attach)
                path = pth[max(dist, key=dist.get)]
                clear = cov_tree.query(pos[path])[0] > clearance
                outside = float(np.linalg.norm(np.diff(pos[path], axis=0), axis=1)[clear[:-1] & clear[1:]].sum())
                if best is None or outside > best[0]:
                    best = (outside, path)
            if best[0] < min_branch:
                break
            paths.append(best[1])
            covered.update(best[1])
        return paths

    rng = np.random.default_rng(11)
    for trial in range(4):
        # a rib-like arc with two side strands, scattered: its spanning tree has a trunk, branches and spurs
        t = rng.uniform(0.0, 3.0, 300)
        arc = np.c_[100 * np.cos(t), 80 * np.sin(t), np.zeros_like(t)]
        side = np.c_[rng.uniform(0, 40, 80), np.zeros(80), rng.uniform(0, 30, 80)] + arc[:80]
        pos = np.vstack([arc, side]) + rng.normal(0.0, 1.0, (380, 3))
        mst = minimum_spanning_tree(cdist(pos, pos)).tocoo()
        tree = nx.Graph()
        tree.add_nodes_from(rng.permutation(len(pos)).tolist())  # node order is not id order
        tree.add_weighted_edges_from(zip(mst.row.tolist(), mst.col.tolist(), mst.data.tolist()))
        got = tree_paths(tree, pos, 5.0, 4.0)
        assert got == networkx_tree_paths(tree, pos, 5.0, 4.0)
        assert len(got) >= 2  # the side strands come out as branches
    assert tree_paths(nx.Graph(), np.zeros((0, 3)), 5.0) == []
    single = nx.Graph()
    single.add_node(3)
    assert tree_paths(single, np.zeros((4, 3)), 5.0) == [[3]]
