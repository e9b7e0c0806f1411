"""Typed configs for a whole `ribpull fit` run, with named presets.

A run = a method config (SparseOcc / Neural-Pull / DiGS, each owned by its method module) plus the
stage configs below. `get_preset(name)` returns a fresh `FitConfig`; CLI flags and service params
override fields of it with `dataclasses.replace`.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any


@dataclass
class MeshConfig:
    """Marching cubes on the inside score, coarse-to-fine.

    resolution: cells along the longest side of the (padded) input bounding box at the finest level.
    coarse_resolution: first, dense pass; finer levels only evaluate cells near the surface.
    padding: bounding-box padding as a fraction of the half extent (paper: 0.05 in unit frame).
    """

    resolution: int = 384
    coarse_resolution: int = 64
    padding: float = 0.05
    keep_components_min_fraction: float = 0.0  # drop components smaller than this fraction of faces


@dataclass
class TubePatchConfig:
    """Patches long along a rib and narrow across it (`tube_patches.project_onto_tube_patches`).

    along_mm, across_mm: the Gaussian weight's scales along the tube's axis and across it (mm;
    along_mm 0 disables); neighbours: a patch's ball holds about this many points (its radius:
    the median distance from the vertices to their neighbours-th nearest point); max_move_mm: a vertex
    whose patch is farther than this (mm) stays; max_axis_spread: a vertex where the surface bends
    both ways (`tube_patches.tube_axes` spread above it) stays (None: no such limit).
    """

    along_mm: float = 14.0
    across_mm: float = 2.5
    neighbours: int = 160
    max_move_mm: float = 2.0
    max_axis_spread: float | None = None


@dataclass
class SectionQuadricConfig:
    """Implicit quadrics that hold a rib's whole cross-section (`section_quadrics`), for input the
    round patches do not refine (too noisy or too sparse).

    along_mm, across_mm: the window's Gaussian scales along the tube axis and across it (mm; along_mm
    0 disables); centre_spacing_mm: one fit per cube of this edge (a vertex's nearest fit moves it);
    min_points: a window needs this many points; reweightings, robust_mm: refits with Cauchy
    weights of this scale on the points' distances to the quadric, or of robust_noise_factor x
    the window's own residual (1.4826 x the first fit's median distance) where larger (0: robust_mm
    alone; 2.5 against 0, 1M samples, /tmp harness on the `default` meshes: 10k / 1 mm 0.7791 ->
    0.7742, 20k / 1 mm 0.4875 -> 0.4818, 60k / 1 mm 0.3532 -> 0.3515, 10k / 0.3 mm 0.3714 -> 0.3715,
    5k / 0 mm 0.6172 -> 0.6190; 3.5: 0.7713, 0.4800, 0.3515, 0.3742, 0.6206); max_move_mm: a vertex whose
    quadric is farther stays; smoothing_iterations: Taubin smoothing (lambda 0.5, nu -0.53) before
    and after each pass; passes: fit-and-project rounds. refined_patch_radius_mm: a point cloud the
    round patches do refine gets them too, after those, when its patches had to reach farther than
    this (mm) to hold their points (`RefinePlan.patch_radius_mm`; None: never): on the bench's 20k
    points (5.4-5.5 mm patches) CD-L1 0.2986 -> 0.2876 mm (0 mm noise), 0.3726 -> 0.2998 (0.3 mm),
    0.3732 -> 0.3033 (0.3 mm + 2 % outliers), screened Poisson 0.413 / 0.425 / 0.418; on 60k points
    (3.9 mm patches) they made it worse: 0.2130 -> 0.2763 (0 mm), 0.2569 -> 0.2840 (0.3 mm) (1M
    samples, /tmp harness on the refined `default` meshes, 2026-12-06).
    Measured (benchmarks/section_quadrics_ab.py, 1M samples, CD-L1 mm, 2026-12-06; screened
    Poisson / off / one pass / two passes): 10k points / 1 mm noise 0.868 / 0.922 / 0.796 / 0.779;
    20k / 1 mm 0.572 / 0.576 / 0.488 / 0.487; 60k / 1 mm 0.449 / 0.410 / 0.346 / 0.353; 5k / 0, 0.3, 1
    mm 1.550, 1.527, 1.757 / 0.832, 0.852, 1.261 / 0.638, 0.690, 1.179 / 0.617, 0.671, 1.164; 10k / 0,
    0.3 mm 0.664, 0.683 / 0.486, 0.534 / 0.337, 0.375 / 0.334, 0.371. On the `default` meshes of 20k /
    1 mm (/tmp harness): fits at every vertex / 1.5 / 2.5 / 3.5 mm apart 0.503 / 0.502 / 0.501 / 0.501
    (7.8 / 3.8 / 2.1 / 2.1 s, without the tube patches); 3 / 5 / 8 smoothing iterations 0.502 /
    0.501 / 0.516.
    """

    along_mm: float = 10.0
    across_mm: float = 4.0
    centre_spacing_mm: float = 2.5
    min_points: int = 20
    reweightings: int = 2
    robust_mm: float = 2.0
    robust_noise_factor: float = 2.5
    max_move_mm: float = 2.0
    smoothing_iterations: int = 5
    passes: int = 2
    refined_patch_radius_mm: float | None = 4.5


@dataclass
class RefineConfig:
    """Mesh vertices projected onto the input points' local quadric patches (`ribpull_core.refine`).

    radius_mm: a patch holds the input points within this radius (mm), but at least min_neighbours
    (noise is averaged over that many) and at most max_neighbours.
    max_radius_mm: where min_neighbours points spread farther than this (sparse input) the mesh is
    left as meshed: such a patch would flatten the rib's curvature.
    max_patch_noise_mm: where the points' median RMS distance from their patches, divided by the
    square root of the points per patch (the noise left in a patch that averages them), exceeds
    this (noisy input for its density), the mesh is left as meshed too. 0.15 mm: the bench's 200k
    points / 1 mm noise (0.81 / sqrt(32) = 0.14) are refined, CD-L1 0.602 -> 0.510 mm (300k
    samples), where the former 0.5 mm bound on the residual alone skipped them; 20k / 1 mm (0.81 /
    sqrt(13) = 0.22) stays unrefined (refining it made it worse, below).
    blend: patches averaged per vertex. max_shift_gaps: a vertex moves onto the patches only if that
    is at most this many sampling gaps (median nearest-neighbour distance) away.
    fair_order: the vertices that did not move are faired between those that did (refine.fair_vertices:
    1 membrane, 2 thin plate; 0 leaves them where the field put them). On the bench's 60k / 0.3 mm
    phantom case 202 of 176k vertices did not move; faired (order 2) the mesh's HD went 4.00 -> 1.60
    mm, CD-L1 0.406 -> 0.405 (300k samples; order 1: 1.58, 0.405).
    fit_iterations: an input that will be refined is fitted for at most this many iterations (None:
    the method's; an explicit `iterations` option wins). The refinement replaces the
    field's last fine convergence, which then bought nothing measurable: 400 against 600
    iterations (300k-sample CD-L1 / HD, mm; /tmp A/B at the grid-kernel commit): 60k / 0.3 mm
    points 0.404 / 1.44 against 0.405 / 1.47; 1.5 mm label map 0.406 / 1.49 against 0.404 / 1.47;
    0.75x0.75x2.5 mm map 0.415 / 1.51 against 0.415 / 1.61; 20k / 0.3 mm 0.501 / 4.94 against
    0.500 / 3.77 (no HD floor there); 250 iterations left a 3.9 mm HD at 60k.
    dense_fit_iterations: point clouds of more than dense_points points (whose field's finest
    grid level is finer, so slower to settle) are fitted for at most this many instead: at 200k
    points 400 iterations left HD 2.16 / 2.74 / 5.83 mm at 0 / 0.3 / 1 mm noise and 4 ribs merged
    at 1 mm, against 0.88 / 0.89 / 4.01 mm and none at 600 (sweeps at 3107389 and dff2da3, 1M
    samples); 800 against 600 at 0.3 mm noise: HD 0.90 against 2.54 mm and 24 parts against 25,
    CD-L1 0.2272 against 0.2275 (0 / 1 mm noise: CD-L1 0.2056 / 0.3945 against 0.2055 / 0.3941;
    1M samples, benchmarks/refine_ab.py, 2026-12-03). Label maps keep fit_iterations (their
    boundary points number ~100k) unless warm_fit_iterations applies.
    warm_fit_iterations: an input whose field starts from a solid instead of a sphere is fitted for
    at most this many instead (None: fit_iterations): the training then corrects a surface already
    within about a voxel. That is a label map whose solid the load stage measured
    (`LabelMapConfig.solid_distance_cell_mm`; the preset's method then starts its field from it,
    `FieldConfig.grid_solid_prior`), and a refined point cloud whose flood fill the method trusts
    (flood_prior_cell_mm; above dense_points points dense_warm_fit_iterations instead). On the
    sternum map, HD at
    seeds 0 / 1 / 2 the same at 150 as from the sphere at 400 (1.03 / 1.14 / 1.01 mm; 200: 1.16 /
    1.13 / 1.11); from the sphere, 200 iterations left 2.46 mm (`sparseocc.default_config`).
    flood_prior_cell_mm: a refined point cloud whose sampling gap (median distance to the 8th
    neighbour) is at most flood_prior_max_gap_mm starts its field from the solid its flood fill
    encloses, at nodes this far apart (`sparseocc.flood_fill_solid`,
    `FieldConfig.grid_flood_prior_cell_mm`), where the method trusts that flood fill (no stray
    points, no structures closer than the gap term's reach), and is then fitted for
    warm_fit_iterations (dense_warm_fit_iterations above dense_points points); 0: from the sphere.
    60k / 0.3 mm, seeds 0 / 1 / 2, CD-L1 / HD mm (1M samples): 150 from the flood fill 0.1296 /
    1.34, 0.1319 / 2.69, 0.1259 / 1.68 against 400 from the sphere 0.1292 / 1.28, 0.1308 / 3.08,
    0.1257 / 1.41 (200 / 250 warm at seed 0: 0.1296 / 1.35, 0.1295 / 1.33). 200k points, 300 warm
    against 800 from the sphere: 0.3 mm 0.0763 / 0.64 against 0.0764 / 0.68, 0 mm 0.0190 / 0.39
    against 0.0190 / 0.42 (25 parts against 24, every rib its own); back to back, 200k / 0.3 mm
    took 48.1 s against 75.7 s. A sparser cloud's flood-fill shell (one gap each side of the
    points) fills its ribs and bridges their gaps: at 20k points (4.3 mm gap) 150 warm iterations
    gave CD-L1 0.217 against 0.180 mm and 18 of 24 ribs isolated.
    dense_mesh_resolution: such dense point clouds, when refined, are meshed at (at least) this
    many cells instead of the preset's: the refined vertices lie on the patches, and between them
    the flat triangles cut a rib's curvature (a 1.2 mm edge on a 4 mm radius: ~0.05 mm): at 200k /
    0.3 mm, 384 against 256 cells gave CD-L1 0.2244 against 0.2272 mm, Poisson 0.2270 (1M samples,
    800 iterations, 2026-12-03). 0 keeps the preset's.
    dense_max_neighbours: such dense point clouds' patches hold up to this many points instead of
    max_neighbours (their radius_mm holds more): at 200k points / 0.3 mm noise, 48 against 32
    averaged the noise to CD-L1 0.227 against 0.229 mm, Poisson 0.227 (1M samples, +4.4 s of
    refinement; 64: 0.228, +8.3 s).

    noise_flow_factor: an input not refined because it is too noisy has its mesh moved by
    `curvature_bias.remove_noise_bias` instead: a mean-curvature flow for factor x sigma^2 / 2 (sigma:
    the noise along the normal, from the plan's patch residual), which takes off the sigma^2 H
    offset that noise on a curved surface puts on a fit (0 disables). On the bench's phantom (1M
    samples, 2026-12-03; meshes of the default with 70 % facing): 60k / 1 mm 0.4594 -> 0.4393 mm
    (screened Poisson 0.4487), 20k / 1 mm 0.6879 -> 0.6452 (0.5724); factor 0.5 / 1.5 / 2: 0.4447 /
    0.4402 / 0.4460 at 60k, 0.6575 / 0.6449 / 0.6529 at 20k.

    smoothing_bias_factor: a label map's boundary points lie on its blurred mask, which sits inside
    the surface by 2 H t (t: PointCloud.boundary_smoothing_mm2, from the blur and the voxel box);
    the refined mesh is moved back out by factor x that (`curvature_bias.restore_smoothing_bias`; 0
    disables). On the bench's partial-volume phantom maps (1M samples, 2026-12-03,
    benchmarks/label_map_bias_ab.py, blur 0.9 mm), CD-L1 / HD without -> with it: 1.5 mm 0.2730 /
    1.18 -> 0.2471 / 0.96 mm (marching cubes + 20 Taubin 0.2672 / 1.03); 0.75 x 0.75 x 2.5 mm
    0.2727 / 1.32 -> 0.2597 / 1.25 (0.3096 / 1.33); sternum 1.5 mm 0.2944 -> 0.2678 (0.2852).

    terrace_weight: a label map's boundary points on terraces (faces across the voxel axis nearest
    the surface normal: they only bound the surface to half a voxel) count this much in the patches,
    the risers between them 1 (`refine.terrace_weights`; 1 disables).

    tube: after the noise flow, a too-noisy input's mesh is projected onto quadrics of its points
    over patches long along the rib and narrow across it (a TubePatchConfig; along_mm 0 disables).
    1M samples, flow then 14 x 2.5 mm patches against the flow alone (/tmp harness on the meshes of
    `default` without the flow, 2026-12-05, screened Poisson beside): 60k / 1 mm 0.4398 -> 0.4109
    mm (0.4488), 20k / 1 mm 0.6439 -> 0.5738 (0.5725); 10 x 2.5 mm: 0.4128, 0.5782; the patches
    before the flow instead: 0.4483, 0.6174. Not everywhere: on a circular 4 mm tube with 1 mm
    noise (tests/test_tube_patches.py's) they leave the flowed mesh worse (radial RMS 0.14 -> 0.28
    mm); the phantom's ribs are 5.5 x 3.5 mm ellipses.

    label_map_tube: a label map's refined mesh, before the smoothing bias is restored, is projected
    onto tube patches of its boundary points (all alike, without the isotropic patches' terrace
    weights), which
    average the voxel staircase over a rib's length; short moves only (max_move_mm) and only where
    the surface is a tube's (max_axis_spread), since where it bends both ways (rib ends, the
    cartilages' junctions with the sternum) the patches cut the corner (benchmarks/label_map_tube_ab.py).

    label_map_radius_voxels: a label map's patches hold its boundary points within this many of its
    largest voxel edges (instead of radius_mm): 2.5 mm on a 1.5 mm map, where a 4 mm patch spans
    most of a thin cartilage's cross-section and pulls its edges inside (the sternum phantom's
    worst spots), and 4.2 mm on a 0.75 x 0.75 x 2.5 mm map, whose 2.5 mm steps a smaller patch
    does not average. 1M samples, CD-L1 / HD mm at radius 4 / 3 / 2.5 mm (/tmp harness over
    benchmarks/abkit.py, 2026-12-06, mc_taubin beside): sternum 1.5 mm map 0.2530 / 1.38, 0.2523 /
    1.23, 0.2535 / 1.11 (0.2852 / 1.21); 1.5 mm map 0.2320 / 0.92, 0.2326 / 0.98, 0.2337 / 0.89
    (0.2672 / 1.03); 0.75 x 0.75 x 2.5 mm map 0.2371 / 1.15, 0.2419 / 1.19, 0.2501 / 1.18 (0.3096 /
    1.33). None: radius_mm for label maps too.

    section: an input the round patches do not refine (too noisy: after the flow and the tube
    patches; too sparse: as meshed), and a point cloud they refine with patches wider than
    section.refined_patch_radius_mm, is then projected onto implicit quadrics of its points over
    windows that hold a rib's whole cross-section (a SectionQuadricConfig; along_mm 0 disables).

    Chosen on the phantom (300k-sample CD-L1 of the refined mesh, mm): the best patch held ~20
    points at 60k points (4.0 mm) and ~13 at 20k (5.5 mm); patches wider than ~6 mm (10k points and
    fewer) made the 10k and 5k meshes worse (0.842 -> 0.945, 1.461 -> 1.637), and so did 1 mm noise
    at 20k (0.783 -> 0.823). Refined after 600 against 1000 iterations: 60k / 0.3 mm 0.4019 against
    0.4014, 20k 0.4941 against 0.4955. 32 against 64 neighbours at 200k points: 0.3829 against
    0.3826 in half the time.
    """

    radius_mm: float = 4.0
    label_map_radius_voxels: float | None = 5.0 / 3.0
    min_neighbours: int = 13
    max_neighbours: int = 32
    max_radius_mm: float = 6.0
    max_patch_noise_mm: float = 0.15
    blend: int = 8
    max_shift_gaps: float = 1.5
    fair_order: int = 2
    fit_iterations: int | None = 400
    dense_points: int = 100_000
    dense_fit_iterations: int | None = 800
    warm_fit_iterations: int | None = 150
    dense_warm_fit_iterations: int | None = 300
    flood_prior_cell_mm: float = 3.0
    flood_prior_max_gap_mm: float = 3.5
    dense_max_neighbours: int = 48
    dense_mesh_resolution: int = 384
    noise_flow_factor: float = 1.0
    smoothing_bias_factor: float = 1.0
    terrace_weight: float = 0.3
    tube: TubePatchConfig = field(default_factory=TubePatchConfig)
    label_map_tube: TubePatchConfig = field(default_factory=lambda: TubePatchConfig(
        along_mm=8.0, across_mm=2.0, max_move_mm=0.5, max_axis_spread=0.03))
    section: SectionQuadricConfig = field(default_factory=SectionQuadricConfig)


@dataclass
class SdfConfig:
    """Signed distance volume in mm (negative inside), written as NIfTI.

    voxel_mm: grid spacing; None means the input NIfTI's spacing for NIfTI inputs, else the longest
    side of the input's box / cells_per_side. padding_mm: margin around the input bounding box
    (non-NIfTI inputs).
    """

    voxel_mm: float | None = None
    cells_per_side: int = 128
    padding_mm: float = 5.0
    max_voxels: int = 16_000_000


@dataclass
class MetricsConfig:
    """ConvONet-style surface metrics; n_samples per side (paper: 100k)."""

    n_samples: int = 100_000
    fscore_tau_mm: float = 1.0


@dataclass
class LabelMapConfig:
    """How a NIfTI label map becomes training data (the load stage).

    boundary_sigma_mm: the fitted points are the centres of the voxel faces between selected and
    unselected voxels; when > 0 each moves along its axis to where the mask, smoothed by a Gaussian
    of this std (mm), crosses 0.5 (a sub-voxel boundary instead of the staircase).
    band_voxels: voxel centres within this many voxels of the boundary become known-occupancy
    samples (inside / outside) for methods that use them; 0 disables.
    between_labels: faces between voxels of two different labels are boundary points of both
    structures too (`pointcloud.mask_boundary_cloud`).
    solid_distance_cell_mm: when > 0, the map's solid also becomes a signed distance volume with
    cells of about this edge (`pointcloud.mask_signed_distance`), a warm start for methods that
    take one (`FieldConfig.grid_solid_prior`); 0 disables.
    """

    boundary_sigma_mm: float = 0.0
    band_voxels: float = 0.0
    between_labels: bool = False
    solid_distance_cell_mm: float = 0.0


@dataclass
class FitConfig:
    """Everything one fit needs. `method_config` is the method's own dataclass."""

    preset: str
    method: str
    method_config: Any
    mesh: MeshConfig = field(default_factory=MeshConfig)
    sdf: SdfConfig = field(default_factory=SdfConfig)
    metrics: MetricsConfig = field(default_factory=MetricsConfig)
    label_map: LabelMapConfig = field(default_factory=LabelMapConfig)
    #: vertex refinement onto the input points after meshing (None: the mesh as the field gives it)
    refine: RefineConfig | None = None
    seed: int = 0

    def to_dict(self) -> dict:
        return asdict(self)
