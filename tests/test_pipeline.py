"""End to end through run_pipeline (the function the CLI, worker and benchmark share), and the CLI."""

from __future__ import annotations

import json

import nibabel as nib
import numpy as np
import pygltflib
import pytest
import shareddata
import trimesh

from ribpull_core.cli import main as cli_main
from ribpull_core.dicom.export import DICOM_ARTIFACTS
from ribpull_core.dicom.nifti_source import STUDY_CT_ARTIFACT
from ribpull_core.errors import JobCanceled, RibPullInputError
from ribpull_core.io import write_point_cloud
from ribpull_core.phantom import PhantomConfig, make_phantom, sample_surface
from ribpull_core.pipeline import ARTIFACT_NAMES, PipelineOptions, run_pipeline
from ribpull_core.weights import load_field

TOTALSEG = shareddata.TOTALSEG_EXAMPLE
FOUR_RIBS = tuple(f"{s}{n}" for s in "LR" for n in range(1, 13) if n not in (5, 6))  # keep L5 L6 R5 R6


@pytest.fixture(scope="module")
def small_phantom(tmp_path_factory):
    cfg = PhantomConfig(seed=0, missing_ribs=FOUR_RIBS)
    phantom = make_phantom(cfg)
    cloud = sample_surface(phantom, 12_000, 0.3, seed=0)
    path = tmp_path_factory.mktemp("ph") / "points.ply"
    write_point_cloud(path, cloud)
    return phantom, path


@pytest.fixture(scope="module")
def fitted(small_phantom, tmp_path_factory):
    _, path = small_phantom
    out = tmp_path_factory.mktemp("fit") / "out"
    seen = []
    result = run_pipeline(path, out, PipelineOptions(preset="smoke", metrics_samples=20_000), progress=seen.append)
    return result, seen


def test_pipeline_writes_every_artifact_in_mm(fitted, small_phantom):
    result, seen = fitted
    phantom, _ = small_phantom
    assert set(result.artifacts) == set(ARTIFACT_NAMES) - {*DICOM_ARTIFACTS, STUDY_CT_ARTIFACT}  # a point cloud: no DICOM out
    for name in result.artifacts:
        assert (result.outdir / name).stat().st_size > 0, name
    mesh = trimesh.load(result.outdir / "mesh.ply", force="mesh")
    # the mesh lies in the input's mm frame, on top of the phantom
    lo, hi = phantom.mesh.bounds
    assert np.all(mesh.bounds[0] > lo - 10) and np.all(mesh.bounds[1] < hi + 10)
    # progress is monotone, covers the stages and ends at 1
    fr = [p.fraction for p in seen]
    assert fr == sorted(fr) and fr[-1] == pytest.approx(1.0)
    assert {"load", "fit", "mesh", "sdf", "skeleton", "metrics", "export"} <= {p.stage for p in seen}


def test_pipeline_metrics_and_weights(fitted):
    result, _ = fitted
    m = json.loads((result.outdir / "metrics.json").read_text())
    assert m["units"] == "mm" and m["method"] == "sparseocc" and m["iterations_run"] > 0
    s = m["surface"]
    assert s["cd_l1_mm"] < 3.0 and 0 < s["fscore"] <= 1
    assert s["cd_l1_paper"] == pytest.approx(s["cd_l1_mm"] * 100 / m["frame"]["half_extent_mm"], rel=1e-6)
    assert m["weights"]["weights_bytes_fp16"] * 2 == m["weights"]["weights_bytes_fp32"]
    # 12k points on four ribs are dense enough for the vertex refinement, which moved most vertices
    refine = m["mesh"]["refine"]
    assert refine["applied"] is True and refine["moved_fraction"] > 0.5, refine
    assert 0 < refine["mean_shift_mm"] < refine["patch_radius_mm"]
    # loading the weights reproduces the field exactly
    field, _frame, meta = load_field(result.outdir)
    assert meta["frame"] == m["frame"] and field.level == pytest.approx(m["surface_level"])


def test_pipeline_separates_the_ribs(fitted):
    result, _ = fitted
    m = json.loads((result.outdir / "metrics.json").read_text())
    assert m["mesh"]["components"] == 4
    skel = json.loads((result.outdir / "skeleton.json").read_text())
    assert skel["units"] == "mm" and sorted(c["label"] for c in skel["components"]) == ["L5", "L6", "R5", "R6"]


def test_skeleton_glb_has_lines_and_triangles(fitted):
    result, _ = fitted
    gltf = pygltflib.GLTF2().load(str(result.outdir / "skeleton.glb"))
    modes = {p.mode for mesh in gltf.meshes for p in mesh.primitives}
    assert 1 in modes and 4 in modes
    assert len(trimesh.load(result.outdir / "skeleton.glb").geometry) >= 2


def test_sdf_is_negative_inside_and_in_mm(fitted, small_phantom):
    result, _ = fitted
    phantom, _ = small_phantom
    img = nib.load(result.outdir / "sdf.nii.gz")
    vol = np.asarray(img.dataobj)
    # a point on a true centerline is inside (negative), and its distance is about the rib's radius
    c = phantom.ribs[0].centerline_mm[250]
    ijk = np.round(np.linalg.inv(img.affine) @ np.append(c, 1))[:3].astype(int)
    assert vol[tuple(ijk)] < 0 and -8 < vol[tuple(ijk)]
    assert vol.max() > 10  # far corners are outside, distances in mm


def test_cancel_leaves_no_output(small_phantom, tmp_path):
    _, path = small_phantom
    out = tmp_path / "out"
    with pytest.raises(JobCanceled):
        run_pipeline(path, out, PipelineOptions(preset="smoke"), should_cancel=lambda: True)
    assert not out.exists() and not list(tmp_path.glob(".ribpull-*"))


def test_cancel_during_the_skeleton_leaves_no_output_and_no_sdf_thread(small_phantom, tmp_path):
    import threading

    _, path = small_phantom
    out = tmp_path / "out"
    stages = []
    with pytest.raises(JobCanceled):
        run_pipeline(path, out, PipelineOptions(preset="smoke"), progress=lambda p: stages.append(p.stage),
                     should_cancel=lambda: "skeleton" in stages)
    assert "sdf" in stages and "skeleton" in stages and "metrics" not in stages
    assert not out.exists() and not list(tmp_path.glob(".ribpull-*"))
    from ribpull_core.pipeline import ASIDE_THREAD_PREFIX

    assert not [t for t in threading.enumerate() if t.name.startswith(ASIDE_THREAD_PREFIX)]  # joined, not left running


def test_bad_options_are_input_errors(small_phantom, tmp_path):
    _, path = small_phantom
    for opts in (PipelineOptions(preset="nope"), PipelineOptions(method="nope"), PipelineOptions(iterations=0),
                 PipelineOptions(resolution=4), PipelineOptions(device="tpu")):
        with pytest.raises(RibPullInputError):
            run_pipeline(path, tmp_path / "o", opts)


@pytest.mark.skipif(not TOTALSEG.exists(), reason="shared data not present")
def test_real_totalsegmentator_map_is_reconstructed_on_the_mask(tmp_path):
    result = run_pipeline(TOTALSEG, tmp_path / "ts", PipelineOptions(preset="smoke", metrics_samples=20_000))
    m = result.metrics
    assert m["input"]["labels"] == list(range(98, 104)) + list(range(110, 116))
    # a label map is refined onto its boundary points when they allow it; 3 mm voxels' boundary points
    # lie more than 0.5 mm (RMS) off any smooth patch, so this one is not, and says so
    refine = m["mesh"]["refine"]
    assert refine["applied"] is False and refine["patch_residual_mm"] > 0.5 and "too noisy" in refine["reason"]
    # the SDF volume is on the input's own grid
    sdf, seg = nib.load(result.outdir / "sdf.nii.gz"), nib.load(TOTALSEG)
    assert sdf.shape == seg.shape and np.allclose(sdf.affine, seg.affine)
    # the surface lies on the mask (3 mm voxels): mesh samples are near the selected voxel centres
    from scipy.spatial import cKDTree

    from ribpull_core.io import load_point_cloud

    cloud = load_point_cloud(TOTALSEG)
    mesh = trimesh.load(result.outdir / "mesh.ply", force="mesh")
    d = cKDTree(cloud.points).query(mesh.sample(20_000))[0]
    assert d.mean() < 3.0
    names = {c["label"] for c in json.loads((result.outdir / "skeleton.json").read_text())["components"]}
    assert names & {f"L{n}" for n in range(7, 13)} and names & {f"R{n}" for n in range(7, 13)}


def test_cli_fit_and_phantom(tmp_path, capsys):
    assert cli_main(["phantom", str(tmp_path / "ph"), "--points", "8000", "--missing", *FOUR_RIBS]) == 0
    rc = cli_main(["fit", str(tmp_path / "ph" / "points.ply"), "-o", str(tmp_path / "fit"), "--preset", "smoke",
                   "--iterations", "150", "--no-skeleton", "--no-preview", "-q"])
    assert rc == 0 and (tmp_path / "fit" / "mesh.glb").exists()
    assert "CD-L1" in capsys.readouterr().out
    (tmp_path / "bad.ply").write_text("ply\nformat ascii 1.0\nelement vertex 500\nproperty float x\nproperty float y\n"
                                      "property float z\nend_header\n0 0 0\n")
    assert cli_main(["fit", str(tmp_path / "bad.ply"), "-o", str(tmp_path / "x"), "-q"]) == 2
    assert "header" in capsys.readouterr().err


def test_one_thread_count_for_torch_and_the_grid_kernels():
    """RIBPULL_TORCH_THREADS (or the argument) sets both pools: torch's and numba's, whose kernels
    train the hash grid; one left at all cores oversubscribes a machine shared by several workers."""
    import numba
    import torch

    from ribpull_core.pipeline import configure_torch_threads

    before_torch, before_numba = torch.get_num_threads(), numba.get_num_threads()
    try:
        assert configure_torch_threads(1) == 1
        assert (torch.get_num_threads(), numba.get_num_threads()) == (1, 1)
        full = numba.config.NUMBA_NUM_THREADS
        configure_torch_threads(full + 5)  # more than numba's pool: numba keeps its whole pool
        assert numba.get_num_threads() == full
    finally:
        torch.set_num_threads(before_torch)
        numba.set_num_threads(before_numba)


def test_refined_fit_length_follows_the_point_count_and_the_input_kind():
    import dataclasses

    from ribpull_core.methods import build_fit_config
    from ribpull_core.pipeline import _plan_refinement
    from ribpull_core.pointcloud import PointCloud

    v = np.random.default_rng(0).normal(size=(20_000, 3))
    # mm, dense: refined, and ~90 points within the 4 mm patch radius (so the neighbour cap decides k)
    sphere = PointCloud(points=30.0 * v / np.linalg.norm(v, axis=1, keepdims=True))

    flood_cells = []

    def planned(cloud, dense_points, max_gap_mm=None, **options):
        config = build_fit_config("default")
        config.refine = dataclasses.replace(config.refine, dense_points=dense_points)
        if max_gap_mm is not None:
            config.refine = dataclasses.replace(config.refine, flood_prior_max_gap_mm=max_gap_mm)
        plan = _plan_refinement(cloud, config, PipelineOptions(**options))
        assert plan.applies
        field = config.method_config.field
        flood_cells.append((field.grid_flood_prior_cell_mm, field.grid_flood_prior_iterations))
        return config.method_config.schedule.iterations, plan.neighbours, config.mesh.resolution

    defaults = build_fit_config("default")
    refine, preset_resolution = defaults.refine, defaults.mesh.resolution
    # fewer points than dense_points: the short fit, patches of at most max_neighbours, the preset's mesh
    assert planned(sphere, dense_points=100_000) == (400, refine.max_neighbours, preset_resolution)
    # ... and, its sampling gap (~1 mm) being under flood_prior_max_gap_mm, the method may start from
    # its flood fill's solid and then fit warm_fit_iterations (the method judges the flood fill)
    assert flood_cells[-1] == (refine.flood_prior_cell_mm, refine.warm_fit_iterations) and refine.flood_prior_cell_mm > 0
    planned(sphere, dense_points=100_000, max_gap_mm=0.5)  # too sparse a cloud for its flood fill: the sphere
    assert flood_cells[-1] == (0.0, None)
    # a dense point cloud is fitted longer, averages over larger patches and is meshed finer
    assert planned(sphere, dense_points=10_000) == (800, refine.dense_max_neighbours, refine.dense_mesh_resolution)
    assert flood_cells[-1] == (refine.flood_prior_cell_mm, refine.dense_warm_fit_iterations)
    assert refine.dense_max_neighbours > refine.max_neighbours and refine.dense_mesh_resolution > preset_resolution
    # ... unless the user names a resolution (build_fit_config applied it already)
    assert planned(sphere, dense_points=10_000, resolution=preset_resolution)[2] == preset_resolution
    label_map = dataclasses.replace(sphere, nifti_affine=np.eye(4))
    # a label map's boundary points do not count as dense; its patches reach 5/3 of a voxel edge
    # (here 1 mm voxels: 1.7 mm, fewer points than the 4 mm of a point cloud's)
    iterations, neighbours, resolution = planned(label_map, dense_points=10_000)
    assert (iterations, resolution) == (400, preset_resolution)
    assert refine.min_neighbours <= neighbours < refine.max_neighbours
    # a label map whose field starts from the map's own solid (the default's warm start) settles sooner
    warm = dataclasses.replace(label_map, solid_distance_mm=np.zeros((2, 2, 2), np.float32),
                               solid_distance_affine=np.eye(4))
    assert planned(warm, dense_points=10_000)[0] == refine.warm_fit_iterations < 400
    from scipy.spatial import cKDTree

    from ribpull_core.refine import patch_size
    probe = np.arange(0, len(label_map.points), max(1, len(label_map.points) // 4000))
    at_radius = dataclasses.replace(refine, radius_mm=refine.label_map_radius_voxels * 1.0)
    assert neighbours == patch_size(label_map.points, at_radius, cKDTree(label_map.points), probe)[0]
