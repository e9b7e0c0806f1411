"""SparseOcc (Ouasfi & Boukhayma 2024) as used by RibPull: occupancy from unoriented points.

Paper eq. 1: pull queries onto the zero set of the margin uncertainty U = p_in - p_out and match
them to their nearest input point. Paper eq. 2: minimax entropy regulariser. Presets:

- ``paper``: the reference configuration (8x256 MLP, 20k iterations, batch 5000, ribcage entropy
  settings, decaying query jitter) — faithful, and slow on a CPU (~0.46 s per iteration).
- ``default``: RibPull's CPU configuration. Same losses, plus (a) free-space supervision: points
  that a flood fill from the bounding box reaches without crossing the (voxelised, dilated) input
  are outside — the sign far from the points is otherwise unconstrained and the field can close the
  thorax into one blob; near-surface inside/outside points along normals oriented by that flood fill,
  both as hinges on U that agree with eq. 1's pull; (b) multi-scale queries; (c) a hash-grid encoded field with a tiny decoder;
  (d) early stopping when the loss stops improving.
- ``smoke``: a few seconds, for tests.
"""

from __future__ import annotations

import dataclasses
import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch
from scipy import ndimage
from scipy.spatial import cKDTree

from ..losses import (
    margin_uncertainty,
    minimax_entropy_loss,
    minimax_weight,
    pull_to_surface,
    sampling_loss,
    sign_margin_loss,
)
from ..pointcloud import distance_to_points, sampling_gap
from ..quadrics import LocalQuadrics, fit_local_quadrics, pca_normals, project_onto_quadrics
from ..volume_kernels import mark_offsets, within_l1
from .base import FittedField, KnownOccupancy, Method, knn_sigma, sample_pull_queries
from .training import ScheduleConfig


@dataclass
class FieldConfig:
    """The network. network: "mlp" (the Neural-Pull 8x256 MLP, `mlp_*`) or "grid"
    (GridOccupancyField, `grid_*`; grid_lr is the tables' Adam rate, the decoder uses schedule.lr).

    grid_finest_cell: when > 0, the finest grid level's cell edge is this multiple of the input's
    sampling gap (median distance to the 8th neighbour), capped by grid_max_resolution: a grid
    finer than the samples has nothing to constrain its fine levels but the noise.
    grid_finest_cell_label_map: the same for label maps (inputs with known occupancy; 0: as points),
    whose boundary-face points sit on a staircase denser than the information in it;
    grid_lr_label_map: the tables' rate for label maps (0: grid_lr). grid_domain: the
    grid covers [-grid_domain, grid_domain]^3 (unit frame). grid_solid_prior: when > 0 and the
    input states its solid as a signed distance volume (a label map,
    `LabelMapConfig.solid_distance_cell_mm`), the grid's prior is that solid instead of a sphere,
    with this slope (`GridOccupancyField.set_prior`; U starts as tanh(-slope x the distance in
    unit-frame units)): a warm start, the field's surface is the map's from the first step.
    0: the sphere. grid_flood_prior_cell_mm: when > 0 (and grid_solid_prior > 0), a point cloud's
    grid starts from the solid its flood fill encloses (`flood_fill_solid`, nodes about this far
    apart, mm) instead of the sphere, where that flood fill is trusted: no stray points were
    dropped and no two structures come closer than the gap term's reach (`gap_points`); the fit
    then runs at most grid_flood_prior_iterations steps (None: the schedule's)."""

    network: str = "mlp"
    mlp_hidden: int = 256
    mlp_layers: int = 8
    grid_levels: int = 12
    grid_features: int = 2
    grid_log2_table: int = 19
    grid_base_resolution: int = 16
    grid_max_resolution: int = 512
    grid_hidden: int = 64
    grid_lr: float = 1e-2
    grid_finest_cell: float = 0.0
    grid_finest_cell_label_map: float = 0.0
    grid_lr_label_map: float = 0.0
    grid_domain: float = 1.2
    grid_solid_prior: float = 0.0
    grid_flood_prior_cell_mm: float = 0.0
    grid_flood_prior_iterations: int | None = None


@dataclass
class QueryConfig:
    """Eq. 1's pull queries (unit frame: the input's longest side spans 2).

    n_queries: sampled once (Neural-Pull: p + s*sigma_knn*N(0, I), s = 0.25*sqrt(N/20000));
    scales: multipliers of s, several values give multi-scale queries, split evenly.
    batch_size: queries per step. jitter: (start, end) std of Gaussian jitter added each step,
    decaying linearly (RibPull's ribcage script: 0.05 -> 0.01); (0, 0) disables it.
    gradient: grad U by "autograd" (double backward) or "finite_difference" (forward differences,
    3 extra evaluations per query, step = the finest grid cell for grids, else fd_step).
    sampling_weight: weight of eq. 1's loss. max_input_points: inputs are subsampled to this.
    outlier_gap_factor: input points whose distance to their 8th neighbour exceeds this multiple of
    the median such distance are dropped before fitting (isolated samples: scanner or segmentation
    outliers); 0 keeps every point.
    targets: what each query is pulled to: "nearest" (the paper: its nearest input point) or
    "quadric" (that point's local quadric patch over target_knn neighbours, `ribpull_core.quadrics`:
    a smooth surface between the samples that averages their noise); a projection that moves more
    than target_max_shift sampling gaps from the nearest point falls back to the point.
    label_map_targets: the same choice for label maps (inputs with known occupancy), whose boundary
    points already sit on the smoothed mask's 0.5 crossing.
    noisy_residual_mm / noisy_min_facing / noisy_radius_mm: a point cloud is judged noisy when at
    least half its target patches span at most noisy_radius_mm (mm; dense enough that a patch does
    not reach a rib's far wall) and their median RMS residual exceeds noisy_residual_mm (0: never);
    then such a narrow patch counts as one-sided when at least noisy_min_facing of its neighbours
    face its point's way (the noise flips a few PCA normals: with all required, 41 % of the 60k /
    1 mm phantom's patches fell back to the raw noisy points, mean distance to the truth 0.82 mm
    against 0.52 mm for a projection; 0.8: 5 %). `SignConfig.near_surface_centres` uses the same
    judgement.
    """

    n_queries: int = 1_000_000
    knn: int = 50
    scales: tuple[float, ...] = (1.0,)
    batch_size: int = 5000
    jitter: tuple[float, float] = (0.05, 0.01)
    gradient: str = "autograd"
    fd_step: float = 0.005
    sampling_weight: float = 10.0
    max_input_points: int = 200_000
    outlier_gap_factor: float = 0.0
    targets: str = "nearest"
    label_map_targets: str = "nearest"
    target_knn: int = 20
    target_max_shift: float = 1.0
    noisy_residual_mm: float = 0.0
    noisy_min_facing: float = 0.8
    noisy_radius_mm: float = 6.0


@dataclass
class EntropyConfig:
    """Eq. 2's minimax entropy: lambda_min x mean H at uniform_points points of the padded bounding
    box minus lambda_max x mean H at input_points input points, weight 10^(-8 i / n_minimax)."""

    input_points: int = 1000
    uniform_points: int = 10_000
    lambda_max: float = 10.0
    lambda_min: float = 1.0
    n_minimax: int = 1000


@dataclass
class SignConfig:
    """RibPull's data-derived sign supervision (0 weights disable it; see `space_labels`).

    free_space_weight / free_space_points: hinge "outside" at points a flood fill reaches from the
    border without crossing the dilated input. near_surface_weight / near_surface_points: hinges
    inside / outside at input points -/+ near_surface_offset (x the flood-fill spacing) along
    flood-fill-oriented normals, but at most near_surface_offset_max_mm millimetres (0: no cap;
    needs the method's unit_mm): a point pushed deeper than a thin bone's half-thickness lands
    beyond its far wall, where "inside" is false. known_weight / known_points: hinges at the occupancy the input
    states (a label map's voxel centres near its boundary: inside ones U >= margin, outside ones
    U <= -margin, margin = half of (distance to the other class - one voxel), so 0 at the first
    ring); used only when the input has it. gap_weight / gap_points: hinges "outside" at the
    midpoints of pairs of input points of different structures (labels) at most gap_max_mm
    millimetres apart (`gap_points`): a gap narrower than the flood fill's blocking shell (a rib
    tip 1.5-3 mm from its costal cartilage) gets free space that the flood fill never reaches; used
    only when the input has labels and the method its unit_mm; 0 disables it. gap_weight_label_map:
    the same weight for label maps (inputs with known occupancy; 0: gap_weight). Its hinges sit
    where a map's known voxel centres are few (a gap of one voxel or none): each gap point is drawn
    about once a step, each known centre about once in 70 steps, so at the points' weight the gap
    term outweighed a junction's known centres several hundred times over.
    near_surface_centres: where the near-surface pairs are centred: "points" (the input points),
    "quadric" (each point projected onto its own eq. 1 target patch, which averages the noise of
    its neighbours: a noisy point's "inside" hinge otherwise often lies outside the true surface
    and pushes a bump out) or "quadric_when_noisy" (only on inputs QueryConfig judges noisy);
    label maps always use their points. 6 mm: at 60k points
    no rib point of the sternum phantom's L6 lies within 4.3 mm of a cartilage point across its
    2.9 mm tip gap, and at a 4 mm reach L6, R6 and R8 stayed merged (17 of 20 isolated); at 5 mm
    R6 (2.5 mm tip gap) stayed merged in the sweep at 2480e20 and in 2 of 2 runs after it (19 of
    20), at 6 mm none in 3 of 3 runs (571 -> 600 gap points; none on the phantom without a sternum
    at 60k or 5k points, nor on the real TotalSegmentator map).
    """

    free_space_weight: float = 0.0
    free_space_points: int = 5000
    near_surface_weight: float = 0.0
    near_surface_points: int = 2048
    near_surface_offset: float = 0.5
    near_surface_offset_max_mm: float = 0.0
    known_weight: float = 0.0
    known_points: int = 4096
    gap_weight: float = 0.0
    gap_points: int = 1024
    gap_max_mm: float = 6.0
    gap_weight_label_map: float = 0.0
    near_surface_centres: str = "points"


@dataclass
class SparseOccConfig:
    """SparseOcc training configuration, nested by concern: field (network), queries (eq. 1),
    entropy (eq. 2), sign (RibPull's supervision), schedule (the shared loop's optimiser schedule)."""

    field: FieldConfig = dataclasses.field(default_factory=FieldConfig)
    queries: QueryConfig = dataclasses.field(default_factory=QueryConfig)
    entropy: EntropyConfig = dataclasses.field(default_factory=EntropyConfig)
    sign: SignConfig = dataclasses.field(default_factory=SignConfig)
    schedule: ScheduleConfig = dataclasses.field(
        default_factory=lambda: ScheduleConfig(iterations=20_000, lr=1e-3, warmup=1000))
    seed: int = 0

    @property
    def iterations(self) -> int:
        """The schedule's length (shorthand for schedule.iterations)."""
        return self.schedule.iterations


def paper_config() -> SparseOccConfig:
    """RibPull's reference SparseOcc configuration (methods.md): 8x256 MLP, 20k iterations."""
    return SparseOccConfig()


def default_config() -> SparseOccConfig:
    """RibPull's CPU default: hash-grid field trained with the SparseOcc losses plus data-derived
    sign supervision (free space and near-surface hinges), multi-scale queries, early stopping.

    The finest grid level follows the input's sampling gap (one gap per cell, at most 256 cells):
    on the 60k-point phantom that is ~133 cells, which left the Hausdorff distance at 2.1 mm
    instead of 4.6 mm at a fixed 256, and on 5k points ~43 cells, where a fixed 256 had nothing to
    constrain its fine levels and fell apart into 66 parts (CD-L1 5.4 mm -> 1.5 mm). Label maps
    (known occupancy at the voxel centres near the boundary, a hinge per centre) use 1.5 gaps per
    cell and mesh at the level that best separates those centres. The tables learn at 5e-3 on
    points (2e-2 left the surface following the sample noise: on 60k / 0.3 mm points CD-L1 0.323 ->
    0.309 mm, HD 3.3 -> 1.9 mm; neutral at 5k and 20k) and at 2e-2 on label maps (5e-3 there: 0.293
    -> 0.300 mm). On point clouds eq. 1 pulls each query to its nearest point's local quadric patch
    (20 neighbours) instead of the point, wherever all the patch's samples face one way: a smooth
    target between the samples (60k / 0.3 mm: CD-L1 0.309 -> 0.284 mm); at 5k points no patch
    is one-sided (a 20-point patch wraps around a rib), so sparse inputs keep the paper's targets.
    Noisy dense inputs (`QueryConfig.noisy_residual_mm`) count a narrow patch as one-sided with 80 %
    of its neighbours facing its point's way, and centre the near-surface hinges on each point's
    own patch: 60k / 1 mm CD-L1 0.4996 -> 0.4614 mm (Poisson 0.4487), 200k / 1 mm 0.3928 -> 0.3910
    (Poisson 0.3953), 1M samples; at 20k / 1 mm (patches ~6.5 mm wide) it was worse and is not applied.
    The near-surface hinges sit half a sampling gap off the points but at most 1 mm: at 10k points
    half a gap is 3 mm, deeper than a rib's 2.5-3.5 mm half-thickness, so "inside" points landed
    beyond the far wall and the ribs merged (5k / 0 mm: CD-L1 1.455 -> 0.938 mm; 10k / 0.3 mm:
    0.833 -> 0.643 mm, Poisson 0.763; 60k unchanged; 300k samples per side). Inputs with labels
    (a rib's points, a cartilage's) add free space in the gaps between different structures up to 6
    mm wide (`gap_points`), which the flood fill closes: on the sternum phantom the ribs isolated
    went 9 -> 20 of 20 from 60k / 0.3 mm points (Poisson 16; 19 in the sweep at 2480e20 with a
    5 mm reach) and 15 -> 20 of 20 from the 1.5 mm label map (marching cubes + Taubin 20), CD-L1
    unchanged (0.447 / 0.442 mm, 300k samples).
    A label map's step hinges 8192 of its voxel centres (known occupancy), not 4096: with 4096 each
    centre is drawn about 3 times in a fit, and thin sheets of the wrong sign grew between them
    where structures nearly touch (a fissure across a costal cartilage's end, a fin from the
    sternum's edge into a cartilage's 1 mm gap), so the sternum map's Hausdorff distance hung on the
    seed: 2.48 / 2.04 / 1.42 mm at seeds 1 / 2 / 0 (400k samples per side), 1.60 / 1.46 / 1.44 with
    8192 (phantom 0 at fit seeds 1 / 2: 1.46 / 1.49; 16384 was no better: 1.50 / 1.44 / 1.94). In
    `ribpull bench` (1M samples, seeds 0-2): sternum map 1.17 / 2.47 / 2.08 -> 1.40 / 1.42 / 1.30 mm
    (mc_taubin 1.21 / 1.32 / 1.22: still over it), 1.5 mm map 0.90 / 0.89 / 1.01 -> 0.94 / 0.89 /
    0.88 (mc_taubin 1.03 / 1.02 / 1.00), CD-L1 the same; the fit ~6 % slower.
    A label map's gap hinge weighs 1, not 10 (`SignConfig.gap_weight_label_map`): at 10 it cut
    costal-cartilage tips back 1.5-2 mm past the map's inside centres where they meet the sternum.
    Sternum map, HD measured to the true surface (1M samples), seeds 0 / 1 / 2: 1.32 / 1.40 / 1.30
    mm (MeshLab on the 4d401ed fits) -> 1.03 / 1.14 / 1.01 mm (`ribpull bench` at b0cecc7;
    mc_taubin 1.06 / 1.30 / 1.05), all 20 separable ribs isolated (17 of 20 with no gap hinge).
    A label map's field starts from the map's own solid instead of a sphere (`grid_solid_prior`,
    slope 2, on the signed distance of its boundary points at 3 mm nodes,
    `pointcloud.mask_signed_distance`), so it is fitted for 150 iterations instead of 400
    (`RefineConfig.warm_fit_iterations`). Sternum map, CD-L1 / HD mm (1M samples, /tmp
    harness over benchmarks/abkit.py, 2026-12-07), seeds 0 / 1 / 2: 400 iterations from the sphere
    0.096 / 1.03, 0.093 / 1.14, 0.096 / 1.01 (`ribpull bench` at b0cecc7); 150 from the map's solid
    0.096 / 1.03, 0.094 / 1.14, 0.096 / 1.01; 200 from the sphere 0.097 / 2.46 at seed 0, 120 from it 0.198 / 9.26
    and 6 of 20 ribs isolated. Slope 1 / 4 at seed 0: HD 1.16 / 1.34 mm (4 at full voxel resolution;
    at 3 mm nodes and 200 iterations 2.73). The 1.5 mm map 0.091 / 0.82 and the 0.75 x 0.75 x 2.5 mm
    map 0.090 / 1.07 at seed 0 (0.091 / 0.83, 0.089 / 1.10 from the sphere at 400).
    Measured in docs/benchmarks.md (benchmarks/pull_targets_ab.py, benchmarks/offset_cap_ab.py,
    benchmarks/gap_ab.py)."""
    return SparseOccConfig(
        field=FieldConfig(network="grid", grid_levels=8, grid_log2_table=18, grid_max_resolution=256, grid_lr=5e-3,
                          grid_lr_label_map=2e-2, grid_finest_cell=1.0, grid_finest_cell_label_map=1.5,
                          grid_solid_prior=2.0),
        queries=QueryConfig(n_queries=400_000, scales=(0.5, 1.0, 2.0), batch_size=2048, jitter=(0.0, 0.0),
                            gradient="finite_difference", outlier_gap_factor=2.5, targets="quadric",
                            noisy_residual_mm=0.5),
        entropy=EntropyConfig(input_points=1000, uniform_points=1000, lambda_max=1.0, n_minimax=200),
        sign=SignConfig(free_space_weight=10.0, free_space_points=2048, near_surface_weight=10.0,
                        near_surface_points=4096, near_surface_offset_max_mm=1.0, known_weight=10.0,
                        known_points=8192, gap_weight=10.0, gap_weight_label_map=1.0,
                        near_surface_centres="quadric_when_noisy"),
        schedule=ScheduleConfig(iterations=1000, lr=2e-3, warmup=30, final_lr_ratio=0.05, early_stop_window=100,
                                early_stop_rel_tol=0.005, early_stop_min_fraction=0.6),
    )


def smoke_config() -> SparseOccConfig:
    """A short `default` (tens of seconds on a CPU): coarse but correct surfaces, for tests and CI."""
    c = default_config()
    return dataclasses.replace(
        c,
        queries=dataclasses.replace(c.queries, n_queries=100_000, batch_size=1024),
        sign=dataclasses.replace(c.sign, free_space_points=1024, near_surface_points=2048, known_points=4096),
        schedule=dataclasses.replace(c.schedule, iterations=250, early_stop_window=0),
    )


# --- free space ------------------------------------------------------------------------------


@dataclass
class SpaceLabels:
    """Occupancy labels derived from the data (unit frame).

    free: (M, 3) points certainly outside; free_distance: (M,) their distance to the nearest input
    point. near_in / near_out: (K, 3) points just inside / outside
    the sampled surface (input point -/+ offset along its normal, oriented by the flood fill).
    spacing: flood-fill voxel size; offset: the normal offset used; normals (N, 3): the input
    points' flood-fill-oriented unit normals. outside / blocked / origin: the flood fill itself
    (`outside_mask`: (X, Y, Z) bool volumes of voxels `spacing` wide, the corner of voxel 0).
    """

    free: np.ndarray
    free_distance: np.ndarray
    near_in: np.ndarray
    near_out: np.ndarray
    spacing: float
    offset: float
    normals: np.ndarray
    outside: np.ndarray | None = None
    blocked: np.ndarray | None = None
    origin: np.ndarray | None = None


def outside_mask(points_unit: np.ndarray, block_factor: float = 1.0, max_cells: int = 384, gap: float | None = None
                 ) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """Flood-fill the empty space around the points; returns (outside (X,Y,Z) bool, blocked bool,
    spacing, origin (3,)).

    A voxel is blocked when it lies within r = block_factor x (median distance to the 8th neighbour)
    of an input point: r closes the gaps between neighbouring samples, so the blocked shell has no
    holes, yet stays thin enough that narrow gaps between ribs stay open. Voxels are r/2 wide (at
    most max_cells along the longest side; gap: that median distance, when the caller has it). Every voxel reached from the border of a padded box
    without crossing the shell is outside. Cavities (rib interiors) are never reached, so they are
    never labelled.
    """
    block = block_factor * (gap if gap is not None else sampling_gap(points_unit))
    lo, hi = points_unit.min(0), points_unit.max(0)
    spacing = max(block / 2.0, float((hi - lo).max() + 8 * block) / max_cells)
    origin = lo - 3 * block
    shape = np.ceil((hi - lo + 6 * block) / spacing).astype(int) + 1
    ijk = np.unique(np.clip(np.round((points_unit - origin) / spacing).astype(int), 0, shape - 1), axis=0)
    # voxels whose centre lies within block + half a voxel of slack of a voxel holding a point: a
    # ball stamped around each such voxel (the same set as thresholding a distance transform of
    # the whole volume, for a fraction of its cost: the points occupy few voxels)
    blocked = mark_offsets(shape.astype(np.int64), ijk.astype(np.int64), _ball_offsets(block / spacing + 0.5))
    labels, n_labels = ndimage.label(~blocked)
    border = np.unique(np.concatenate([labels[[0, -1]].ravel(), labels[:, [0, -1]].ravel(), labels[:, :, [0, -1]].ravel()]))
    reaches_border = np.zeros(n_labels + 1, bool)  # a lookup per label: np.isin sorts the whole volume
    reaches_border[border[border > 0]] = True
    outside = reaches_border[labels]
    return outside, blocked, spacing, origin - 0.5 * spacing


def _ball_offsets(radius: float) -> np.ndarray:
    """(M, 3) integer offsets of the voxels whose centres lie within `radius` (voxels) of the origin."""
    r = int(np.floor(radius))
    grid = np.stack(np.meshgrid(*[np.arange(-r, r + 1)] * 3, indexing="ij"), -1).reshape(-1, 3)
    return grid[(grid**2).sum(1) <= radius * radius]


def oriented_normals(points_unit: np.ndarray, outside: np.ndarray, spacing: float, origin: np.ndarray, k: int = 16,
                     tree: cKDTree | None = None) -> np.ndarray:
    """(N, 3) unit normals by PCA over k neighbours, flipped to point towards the flood-filled outside
    (the gradient of a smoothed outside indicator). This orients the unoriented input from the data.
    tree: a kd-tree of `points_unit` to reuse."""
    normals = pca_normals(points_unit, k, tree)
    smooth = ndimage.gaussian_filter(outside.astype(np.float32), 1.0)
    coords = ((points_unit - origin) / spacing - 0.5).T
    flip = np.einsum("ij,ij->i", normals, indicator_gradient(smooth, coords)) < 0
    normals[flip] *= -1
    return normals


def indicator_gradient(volume: np.ndarray, coords: np.ndarray) -> np.ndarray:
    """(N, 3) gradient (per voxel) of the trilinear interpolant of `volume` at (3, N) voxel
    coordinates, by central differences of one voxel: what interpolating np.gradient(volume) gives
    away from the volume's border (the same numbers to float rounding), without the three
    full-volume gradients (0.34 -> 0.05 s on a 1.5 mm label map's 17M-voxel flood fill)."""
    return np.stack([0.5 * (ndimage.map_coordinates(volume, coords + e[:, None], order=1)
                            - ndimage.map_coordinates(volume, coords - e[:, None], order=1))
                     for e in np.eye(3)], 1)


@dataclass
class OrientedShell:
    """The flood fill around a point cloud and the points' normals it orients (unit frame):
    `outside_mask`'s outside / blocked (X, Y, Z) bool volumes of voxels `spacing` wide (origin: the
    corner of voxel 0) and `oriented_normals`' (N, 3) unit normals."""

    outside: np.ndarray
    blocked: np.ndarray
    spacing: float
    origin: np.ndarray
    normals: np.ndarray


def oriented_shell(points_unit: np.ndarray, tree: cKDTree | None = None, gap: float | None = None) -> OrientedShell:
    """`outside_mask` of the points and their `oriented_normals` (no random draws: `SparseOcc.setup`
    makes it beside the queries). tree / gap: a kd-tree of `points_unit` and its sampling gap, to reuse."""
    outside, blocked, spacing, origin = outside_mask(points_unit, gap=gap)
    normals = oriented_normals(points_unit, outside, spacing, origin, tree=tree)
    return OrientedShell(outside, blocked, spacing, origin, normals)


def space_labels(points_unit: np.ndarray, rng: np.random.Generator, n_free: int = 400_000,
                 offset_fraction: float = 0.5, tree: cKDTree | None = None, gap: float | None = None,
                 max_offset: float | None = None, shell: OrientedShell | None = None) -> SpaceLabels:
    """Free-space points (half near the surface, within 8 voxels (L1) of the dilated input, half
    anywhere outside) and near-surface inside/outside pairs at +-offset along the oriented normals,
    with offset = offset_fraction x the flood-fill spacing (a length derived from the sampling
    density), at most max_offset (unit frame; None: no cap). tree / gap: a kd-tree of
    `points_unit` and its sampling gap, to reuse; shell: their `oriented_shell`, when made already."""
    tree = tree if tree is not None else cKDTree(points_unit)
    shell = shell if shell is not None else oriented_shell(points_unit, tree, gap)
    outside, blocked, spacing, origin = shell.outside, shell.blocked, shell.spacing, shell.origin
    near = outside & within_l1(blocked, 8)  # binary_dilation(blocked, iterations=8)'s voxels
    pools = []
    for mask, n in ((near, n_free // 2), (outside, n_free - n_free // 2)):
        cells = np.flatnonzero(mask)  # flat indices: the voxels of millions are not all unravelled
        if len(cells):
            pick = np.stack(np.unravel_index(cells[rng.integers(0, len(cells), n)], mask.shape), axis=1)
            pools.append(origin + (pick + rng.random((n, 3))) * spacing)
    free = np.concatenate(pools).astype(np.float32) if pools else np.zeros((0, 3), np.float32)
    normals = shell.normals
    offset = offset_fraction * 2 * spacing  # in units of the blocking radius (2 voxels)
    if max_offset is not None:
        offset = min(offset, max_offset)
    free_distance = distance_to_points(points_unit, free, tree, exact_within=0.05 * float(np.ptp(points_unit, 0).max()))
    return SpaceLabels(free, free_distance, (points_unit - offset * normals).astype(np.float32),
                       (points_unit + offset * normals).astype(np.float32), spacing, offset, normals,
                       outside, blocked, origin)


def flood_fill_solid(points_unit: np.ndarray, labels: SpaceLabels, cell: float, exact_cells: int = 2,
                     tree: cKDTree | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The solid a point cloud's flood fill encloses as a coarse signed distance volume, for the
    grid's prior (`GridOccupancyField.set_prior`): ((X, Y, Z) float32 unit-frame distances,
    negative inside; (3, 4) unit frame -> node index affine). Nodes are every s-th flood-fill voxel
    centre (s = cell / labels.spacing, rounded, at least 1); each holds its distance to the nearest
    input point (`pointcloud.node_distances`: exact within exact_cells cells of a point). Its sign:
    positive where the flood fill reached, negative in the cavities it never reached, and inside
    the blocked shell around the points (both sides of the surface) the side of the nearest
    point's oriented normal. Stray points' blocked balls would be small solids in it, and
    structures closer than a node would be bridged: `SparseOcc.setup` takes it only where neither
    can happen.

    Why: the flood fill already states which side of the points every voxel lies on; starting the
    field from that solid instead of a sphere leaves the training to correct a surface within a
    voxel or so of the data (label maps do the same from their own solid)."""
    from ..pointcloud import node_distances

    stride = max(1, round(float(cell / labels.spacing)))
    outside = labels.outside[::stride, ::stride, ::stride]
    blocked = labels.blocked[::stride, ::stride, ::stride]
    step = stride * labels.spacing
    index_to_unit = np.diag([step, step, step, 1.0])
    index_to_unit[:3, 3] = np.asarray(labels.origin, dtype=np.float64) + 0.5 * labels.spacing
    distance, nearest = node_distances(outside.shape, index_to_unit, points_unit, exact_cells, tree)
    sign = np.where(outside, 1.0, -1.0)
    shell = np.flatnonzero(blocked)
    if len(shell):
        node = np.stack(np.unravel_index(shell, blocked.shape), 1) * step + index_to_unit[:3, 3]
        p = nearest.ravel()[shell]
        side = np.einsum("ij,ij->i", node - points_unit[p], labels.normals[p])
        sign.ravel()[shell] = np.where(side >= 0, 1.0, -1.0)
    return (sign * distance).astype(np.float32), np.linalg.inv(index_to_unit)[:3]


def nearest_other_structure(points: np.ndarray, labels: np.ndarray, max_gap: float) -> np.ndarray:
    """(M, 2) index pairs (i, j): each point i of (N, 3) `points` with its nearest point j of another
    structure (labels (N,)) when that is at most max_gap away (the points' units); each pair once.
    Structures whose bounding boxes lie farther apart than max_gap are never searched."""
    groups = {lab: np.flatnonzero(labels == lab) for lab in np.unique(labels)}
    boxes = {lab: (points[idx].min(0), points[idx].max(0)) for lab, idx in groups.items()}
    trees: dict = {}
    best_d, best_j = np.full(len(points), np.inf), np.full(len(points), -1)
    for a, ia in groups.items():
        for b, ib in groups.items():
            (lo_a, hi_a), (lo_b, hi_b) = boxes[a], boxes[b]
            if a == b or np.any(lo_a - max_gap > hi_b) or np.any(lo_b - max_gap > hi_a):
                continue
            if b not in trees:
                trees[b] = cKDTree(points[ib])
            d, j = trees[b].query(points[ia], k=1, distance_upper_bound=max_gap, workers=-1)
            closer = d < best_d[ia]
            best_d[ia[closer]], best_j[ia[closer]] = d[closer], ib[j[closer]]
    found = np.flatnonzero(np.isfinite(best_d))
    return np.unique(np.sort(np.stack([found, best_j[found]], axis=1), axis=1), axis=0)


def gap_points(points: np.ndarray, labels: np.ndarray, tree: cKDTree, max_gap: float, balance: float = 0.1,
               k: int = 16, min_support: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Free space between neighbouring structures: ((M, 3) float32 points, (M,) float32 distance to
    the nearest input point), the units of (N, 3) `points`.

    Each point is paired with its nearest point of another structure (labels (N,), e.g. a rib and its
    costal cartilage) at most max_gap away (`nearest_other_structure`). The pair's midpoint m lies in
    the gap between the two when it is about as far from the one structure as from the other: among
    m's k nearest input points, the nearest of each pair member's label are both there and their
    distances differ by at most `balance` x the pair's length; and no input point is nearer to m
    than a quarter of that length; and each of the two labels holds at least `min_support` of those
    k points (a gap lies between two surfaces: a stray sample labelled like a neighbour, e.g. a
    uniform outlier next to a rib, makes pairs with one point on its side; on the bench's 60k /
    0.3 mm phantom with 2 % outliers 33 of 33 midpoints were such, and the hinge punched a 4.8 mm
    bump; the sternum phantom keeps 593 of 600, its label map 612 of 612). A midpoint inside one
    structure (a pair across a rib tip's corner) is much nearer to that structure and is dropped.
    Nearest pairs rather than every pair
    within reach: they cross a gap straight, so the reach can cover sparse tips without the
    corner-cutting pairs (5 mm on the sternum phantom's 60k points: 6 of 662 midpoints inside a
    solid; every pair within 5 mm: 109 of 3,006). (Flood-fill-oriented normals do not help here:
    at a rib tip inside a closed gap they point sideways.) Such gaps are narrower than the flood
    fill's blocking shell, which closes them, so no other free space reaches them. tree: kd-tree
    of `points`.
    """
    empty = (np.zeros((0, 3), np.float32), np.zeros(0, np.float32))
    if labels is None or len(points) < 2 or not max_gap > 0:
        return empty
    pairs = nearest_other_structure(points, np.asarray(labels), max_gap)
    if len(pairs) == 0:
        return empty
    mid = 0.5 * (points[pairs[:, 0]] + points[pairs[:, 1]])
    length = np.linalg.norm(points[pairs[:, 1]] - points[pairs[:, 0]], axis=1)
    dist, nn = tree.query(mid, k=min(k, len(points)), workers=-1)
    near_labels = labels[nn]
    of_p = near_labels == labels[pairs[:, 0]][:, None]  # (M, k): which of m's neighbours are p's structure
    of_q = near_labels == labels[pairs[:, 1]][:, None]
    d_p = np.where(of_p, dist, np.inf).min(axis=1)
    d_q = np.where(of_q, dist, np.inf).min(axis=1)
    keep = np.isfinite(d_p) & np.isfinite(d_q) & (np.abs(d_p - d_q) <= balance * length) \
        & (dist[:, 0] >= 0.25 * length) & (of_p.sum(axis=1) >= min_support) & (of_q.sum(axis=1) >= min_support)
    return mid[keep].astype(np.float32), dist[keep, 0].astype(np.float32)


def classification_level(u: np.ndarray, inside: np.ndarray) -> float:
    """The threshold t that makes {u > t} agree with the known labels `inside` (M,) bool at the most
    samples, u (M,) the field there; the midpoint between the two values around the best cut."""
    order = np.argsort(u, kind="stable")
    u_sorted, ins = u[order], np.asarray(inside, bool)[order]
    inside_below = np.concatenate([[0], np.cumsum(ins)])  # cut before index i: 0..i-1 called outside
    outside_above = (~ins).sum() - np.concatenate([[0], np.cumsum(~ins)])
    i = int(np.argmin(inside_below + outside_above))
    if i == 0:
        return float(u_sorted[0]) - 1e-6
    if i == len(u_sorted):
        return float(u_sorted[-1]) + 1e-6
    return float(0.5 * (u_sorted[i - 1] + u_sorted[i]))


# --- the method ------------------------------------------------------------------------------


def field_resolution(f: FieldConfig, sampling_gap: float, label_map: bool = False) -> int:
    """Finest grid resolution (cells across the domain) for inputs whose sampling gap (unit frame,
    median distance to the 8th neighbour) is `sampling_gap`: 2*domain / (grid_finest_cell x gap),
    between 2 x grid_base_resolution and grid_max_resolution (the fixed value when grid_finest_cell is 0)."""
    factor = f.grid_finest_cell_label_map if label_map and f.grid_finest_cell_label_map > 0 else f.grid_finest_cell
    if factor <= 0 or not sampling_gap > 0:
        return int(f.grid_max_resolution)
    res = round(2 * f.grid_domain / (factor * sampling_gap))
    return int(min(max(res, 2 * f.grid_base_resolution), f.grid_max_resolution))


def drop_isolated_points(points: np.ndarray, factor: float, k: int = 8) -> np.ndarray:
    """(N, 3) -> the points whose distance to their k-th neighbour is at most `factor` x the median
    of that distance (any units). A surface sample has neighbours about one sampling gap away; a
    uniform outlier in the bounding box has its nearest ones tens of gaps away."""
    return points[connected_point_mask(points, factor, k)]


def connected_point_mask(points: np.ndarray, factor: float, k: int = 8) -> np.ndarray:
    """(N,) bool: the points `drop_isolated_points` keeps."""
    if len(points) <= k + 1:
        return np.ones(len(points), bool)
    d, _ = cKDTree(points).query(points, k=k + 1, workers=-1)
    gap = d[:, -1]
    return gap <= factor * float(np.median(gap))


def _arch(f: FieldConfig, max_resolution: int | None = None) -> dict:
    if f.network == "mlp":
        return {"name": "NeuralPullMLP", "kwargs": {"out_dim": 2, "hidden": f.mlp_hidden, "layers": f.mlp_layers}}
    if f.network == "grid":
        return {
            "name": "GridOccupancyField",
            "kwargs": {
                "n_levels": f.grid_levels,
                "features": f.grid_features,
                "log2_table": f.grid_log2_table,
                "base_resolution": f.grid_base_resolution,
                "max_resolution": int(max_resolution or f.grid_max_resolution),
                "hidden": f.grid_hidden,
                "domain": f.grid_domain,
            },
        }
    raise ValueError(f"unknown network {f.network!r}")


def margin_and_gradient(module: torch.nn.Module, q: torch.Tensor, method: str, fd_step: float):
    """U(q) (B,) and grad U(q) (B, 3), differentiable w.r.t. the weights.

    "autograd": exact gradient through a double backward. "finite_difference": forward differences
    (3 extra evaluations) — cheaper for grid encodings and smoother across grid cells."""
    if method == "autograd":
        q = q.requires_grad_(True)
        u = margin_uncertainty(module(q))
        (g,) = torch.autograd.grad(u.sum(), q, create_graph=True)
        return u, g
    eye = torch.eye(3, dtype=q.dtype, device=q.device) * fd_step
    u_all = margin_uncertainty(module(torch.cat([q, (q[:, None, :] + eye).reshape(-1, 3)])))
    b = q.shape[0]
    u = u_all[:b]
    return u, (u_all[b:].view(b, 3) - u[:, None]) / fd_step


def free_margin(distance: np.ndarray) -> torch.Tensor:
    """(M,) float32 hinge margins of points known to be outside, from their (M,) distance to the
    data (unit frame): half of it, at most 0.5 (free space far away need not be any more certain)."""
    return torch.from_numpy(np.minimum(0.5 * np.asarray(distance, np.float32), 0.5))


def outside_loss(logits: torch.Tensor, margin: torch.Tensor) -> torch.Tensor:
    """`sign_margin_loss` of (B, 2) logits at points known to be outside, margins (B,)."""
    u = margin_uncertainty(logits)
    return sign_margin_loss(u, torch.zeros_like(u, dtype=torch.bool), margin)


class SparseOcc(Method):
    """SparseOcc occupancy fitting (paper eq. 1-2) with RibPull's optional sign supervision.

    Loss terms (get_loss_dict): "sampling" (eq. 1), "entropy" (eq. 2, while its weight is on),
    "free_space", "near_surface" and "gap" (RibPull's hinges, when enabled), "known_occupancy"
    (label maps)."""

    name = "sparseocc"
    kind = "occupancy"
    config_class = SparseOccConfig
    presets: ClassVar[dict] = {"paper": paper_config, "default": default_config, "smoke": smoke_config}

    def arch(self) -> dict:
        arch = _arch(self.config.field, self.resolution)
        if self.solid_prior is not None:
            arch["kwargs"].update(prior_shape=list(self.solid_prior[0].shape), prior_slope=self.config.field.grid_solid_prior)
        return arch

    def setup(self, points_unit: np.ndarray, device: torch.device, known: KnownOccupancy | None = None,
              labels: np.ndarray | None = None) -> None:
        """Queries and their targets, the sign labels and the entropy box, sampled once."""
        cfg: SparseOccConfig = self.config
        rng = np.random.default_rng(cfg.seed)
        pts = np.asarray(points_unit, dtype=np.float64)
        kept = np.arange(len(pts))  # the input points used, so that their labels follow them
        if len(pts) > cfg.queries.max_input_points:  # the loss only needs a dense enough sample
            kept = kept[rng.choice(len(pts), cfg.queries.max_input_points, replace=False)]
        sampled = len(kept)
        if cfg.queries.outlier_gap_factor > 0:
            kept = kept[connected_point_mask(pts[kept], cfg.queries.outlier_gap_factor)]
        stray = sampled - len(kept)  # points dropped as stray: the flood fill blocked around them too
        pts = pts[kept]
        point_labels = None if labels is None or len(labels) != len(points_unit) else np.asarray(labels)[kept]
        self.points = pts
        tree = cKDTree(pts)
        gap = sampling_gap(pts, tree=tree)
        s = cfg.sign
        if s.near_surface_centres not in ("points", "quadric", "quadric_when_noisy"):
            raise ValueError(f"unknown near_surface_centres {s.near_surface_centres!r}: "
                             "'points', 'quadric' or 'quadric_when_noisy'")
        target_kind = cfg.queries.label_map_targets if known is not None else cfg.queries.targets
        if target_kind not in ("nearest", "quadric"):
            raise ValueError(f"unknown pull targets {target_kind!r}: 'nearest' or 'quadric'")
        want_labels = s.free_space_weight > 0 or s.near_surface_weight > 0
        near_wanted = want_labels and s.near_surface_weight > 0
        centred = near_wanted and known is None and s.near_surface_centres != "points"
        self.free = self.near = self.gap = None
        labels = None
        # The flood fill and its normals (no random draws) are made in a thread beside the queries
        # (the first draws), and the quadric patches beside the free space's distances: the same
        # numbers as one after the other, with the single-threaded numpy of each overlapping the other
        with ThreadPoolExecutor(max_workers=1, thread_name_prefix="ribpull-setup") as pool:
            shell_job = pool.submit(oriented_shell, pts, tree, gap) if want_labels else None
            queries, nearest = self._queries(pts, rng, tree)
            if s.gap_weight > 0 and self.unit_mm and point_labels is not None:
                # needs neither the shell nor random draws: made while the flood fill finishes
                # (sternum label map: the 0.3 s of it came off the ~0.5 s the queries waited)
                gaps, gap_distance = gap_points(pts, point_labels, tree, s.gap_max_mm / self.unit_mm)
                if len(gaps):
                    self.gap = torch.from_numpy(gaps).to(device)
                    self.gap_margin = free_margin(gap_distance).to(device)
            shell = shell_job.result() if shell_job is not None else None
            # one set of patches serves eq. 1's targets and the hinges' centres (a label map's hinges keep its points)
            patches_job = pool.submit(self._target_patches, pts, shell.normals if shell else None, tree) \
                if target_kind == "quadric" or centred else None
            if want_labels:
                max_offset = s.near_surface_offset_max_mm / self.unit_mm \
                    if s.near_surface_offset_max_mm > 0 and self.unit_mm else None
                labels = space_labels(pts, rng, offset_fraction=s.near_surface_offset, tree=tree, gap=gap,
                                      max_offset=max_offset, shell=shell)
                if s.free_space_weight > 0 and len(labels.free):
                    self.free = torch.from_numpy(labels.free).to(device)
                    # hinge margins: half the distance to the data (capped) and half the normal offset
                    self.free_margin = free_margin(labels.free_distance).to(device)
            self.target_patches, self.noisy_input = patches_job.result() if patches_job is not None else (None, False)
        self.q_all = torch.from_numpy(queries).to(device)
        self.pts_t = torch.from_numpy(pts.astype(np.float32)).to(device)
        max_shift = cfg.queries.target_max_shift * gap
        if near_wanted:
            near_in, near_out = labels.near_in, labels.near_out
            if centred and (s.near_surface_centres == "quadric" or self.noisy_input):
                centres = project_onto_quadrics(pts, np.arange(len(pts)), self.target_patches, fallback=pts,
                                                max_shift=max_shift)
                near_in = (centres - labels.offset * labels.normals).astype(np.float32)
                near_out = (centres + labels.offset * labels.normals).astype(np.float32)
            self.near = torch.from_numpy(np.concatenate([near_in, near_out])).to(device)
            self.near_margin = 0.5 * labels.offset
        targets = pts[nearest] if target_kind == "nearest" else project_onto_quadrics(
            queries, nearest, self.target_patches, fallback=pts[nearest], max_shift=max_shift)
        self.target_all = torch.from_numpy(targets.astype(np.float32)).to(device)
        self.known = None
        if known is not None and s.known_weight > 0 and len(known.points):
            self.known = torch.from_numpy(np.asarray(known.points, np.float32)).to(device)
            self.known_inside = torch.from_numpy(np.asarray(known.inside, bool)).to(device)
            first_ring = float(np.min(known.distance))
            margin = 0.5 * np.maximum(np.asarray(known.distance) - first_ring, 0.0)
            self.known_margin = torch.from_numpy(margin.astype(np.float32)).to(device)
        self.grid = cfg.field.network == "grid"
        # the grid's prior, a warm start: the solid the input states (a label map's), else the one
        # its flood fill encloses (a point cloud's, when asked for)
        self.solid_prior = None
        if self.grid and cfg.field.grid_solid_prior > 0 and self.known is not None and known.solid_distance is not None:
            self.solid_prior = (np.asarray(known.solid_distance, np.float32), np.asarray(known.unit_to_index))
        elif self.grid and cfg.field.grid_solid_prior > 0 and cfg.field.grid_flood_prior_cell_mm > 0 \
                and known is None and labels is not None and self.unit_mm and stray == 0 and self.gap is None:
            # trusted only on clean input: stray points (up to 2% uniform outliers at 60k) left blobs and
            # bridges the 150 steps did not remove (HD 6.3 mm against 1.4), and gaps between
            # structures narrower than the nodes (a sternum's cartilage) left HD 3.3-4.4 against 2.75
            self.solid_prior = flood_fill_solid(pts, labels, cfg.field.grid_flood_prior_cell_mm / self.unit_mm, tree=tree)
            warm = cfg.field.grid_flood_prior_iterations
            if warm and warm < cfg.schedule.iterations:  # a surface already near the data settles sooner
                from . import with_iterations

                self.config = cfg = with_iterations(cfg, warm)
        # label maps (known occupancy) have their own gap weight when one is set
        self.gap_weight = s.gap_weight_label_map if self.known is not None and s.gap_weight_label_map > 0 \
            else s.gap_weight
        self.lo = torch.from_numpy(pts.min(0).astype(np.float32)).to(device) - 0.05
        self.hi = torch.from_numpy(pts.max(0).astype(np.float32)).to(device) + 0.05
        self.resolution = field_resolution(cfg.field, gap, self.known is not None) if self.grid else None
        self.fd_step = cfg.queries.fd_step
        self.gen = torch.Generator(device=device).manual_seed(cfg.seed)

    def initialize(self, module: torch.nn.Module) -> None:
        if self.grid and self.config.queries.gradient == "finite_difference":
            self.fd_step = module.finest_cell  # differences over one finest cell
        if self.solid_prior is not None:
            module.set_prior(*self.solid_prior)

    def get_param_groups(self, module: torch.nn.Module) -> list[dict]:
        lr = self.config.schedule.lr
        if self.grid:
            f = self.config.field
            table_lr = f.grid_lr_label_map if self.known is not None and f.grid_lr_label_map > 0 else f.grid_lr
            return [{"params": module.embedding.parameters(), "base_lr": table_lr},
                    {"params": module.decoder.parameters(), "base_lr": lr}]
        return [{"params": module.parameters(), "base_lr": lr}]

    def get_loss_dict(self, module: torch.nn.Module, step: int) -> dict[str, torch.Tensor]:
        """All points of the step go through the network in ONE forward pass (on a CPU the per-call
        overhead dominates small batches), then each term takes its slice: pull queries
        (+ finite-difference probes), entropy points, free space, near surface."""
        cfg: SparseOccConfig = self.config
        qc, ec, sc = cfg.queries, cfg.entropy, cfg.sign
        device, gen = self.q_all.device, self.gen
        idx = torch.randint(0, len(self.q_all), (qc.batch_size,), device=device, generator=gen)
        q, target = self.q_all[idx], self.target_all[idx]
        j0, j1 = qc.jitter
        if j0 > 0 or j1 > 0:
            frac = step / max(1, cfg.schedule.iterations - 1)
            q = q + (j0 + (j1 - j0) * frac) * torch.randn(q.shape, device=device, generator=gen)
        parts: dict[str, torch.Tensor] = {}
        if qc.gradient == "autograd":
            u, grad_u = margin_and_gradient(module, q.clone(), "autograd", self.fd_step)
        else:
            eye = torch.eye(3, dtype=q.dtype, device=device) * self.fd_step
            parts = {"q": q, "probe": (q[:, None, :] + eye).reshape(-1, 3)}
        w_entropy = minimax_weight(step, ec.n_minimax)
        use_entropy = w_entropy > 1e-6 and (ec.lambda_max > 0 or ec.lambda_min > 0)
        if use_entropy:
            parts["uniform"] = self.lo + (self.hi - self.lo) * torch.rand((ec.uniform_points, 3), device=device, generator=gen)
            parts["on_input"] = self.pts_t[torch.randint(0, len(self.pts_t), (ec.input_points,), device=device, generator=gen)]
        if self.free is not None:
            fidx = torch.randint(0, len(self.free), (sc.free_space_points,), device=device, generator=gen)
            parts["free"] = self.free[fidx]
        if self.near is not None:
            nidx = torch.randint(0, len(self.near), (sc.near_surface_points,), device=device, generator=gen)
            parts["near"] = self.near[nidx]
        if self.gap is not None:
            gidx = torch.randint(0, len(self.gap), (sc.gap_points,), device=device, generator=gen)
            parts["gap"] = self.gap[gidx]
        if self.known is not None:
            kidx = torch.randint(0, len(self.known), (sc.known_points,), device=device, generator=gen)
            parts["known"] = self.known[kidx]
        logits = {}
        if parts:
            out = module(torch.cat(list(parts.values())))
            logits = dict(zip(parts, torch.split(out, [len(v) for v in parts.values()])))
        if qc.gradient != "autograd":
            u = margin_uncertainty(logits["q"])
            grad_u = (margin_uncertainty(logits["probe"]).view(-1, 3) - u[:, None]) / self.fd_step
        terms = {"sampling": sampling_loss(pull_to_surface(q, u, grad_u), target, qc.sampling_weight)}
        if use_entropy:
            terms["entropy"] = w_entropy * minimax_entropy_loss(logits["uniform"], logits["on_input"],
                                                                ec.lambda_min, ec.lambda_max)
        if "free" in logits:
            terms["free_space"] = sc.free_space_weight * outside_loss(logits["free"], self.free_margin[fidx])
        if "near" in logits:
            inside = nidx < len(self.near) // 2  # the first half of `near` are the inside points
            u_near = margin_uncertainty(logits["near"])
            terms["near_surface"] = sc.near_surface_weight * sign_margin_loss(
                u_near, inside, torch.full_like(u_near, self.near_margin))
        if "gap" in logits:
            terms["gap"] = self.gap_weight * outside_loss(logits["gap"], self.gap_margin[gidx])
        if "known" in logits:
            terms["known_occupancy"] = sc.known_weight * sign_margin_loss(
                margin_uncertainty(logits["known"]), self.known_inside[kidx], self.known_margin[kidx])
        return terms

    def surface_level(self, fitted: FittedField, points_unit: np.ndarray) -> float:
        """RibPull meshes at the median of U over the input points (paper, Figure 3 caption); when
        the input states occupancy (label maps), at the level that best agrees with it instead."""
        if self.known is not None:
            u = fitted.evaluate(self.known.cpu().numpy())["U"]
            return classification_level(u, self.known_inside.cpu().numpy())
        return float(np.median(fitted.evaluate(self.points.astype(np.float32))["U"]))

    def _target_patches(self, pts: np.ndarray, normals: np.ndarray | None, tree: cKDTree
                        ) -> tuple[LocalQuadrics, bool]:
        """(patches, noisy): the local quadric patches of eq. 1's "quadric" targets and of the
        near-surface hinges' centres, over target_knn neighbours (tree: a kd-tree of `pts`), and
        whether the input is judged noisy (QueryConfig.noisy_*). With oriented `normals` (N, 3), a
        patch whose neighbours do not all face its point's way (it spans both sides of a thin rib:
        sparse input) is not used (its queries keep their nearest point); on a noisy input a patch
        narrow enough not to reach a rib's far wall is used with a few neighbours' normals flipped
        by the noise."""
        qc = self.config.queries
        patches = fit_local_quadrics(pts, qc.target_knn, normals=normals, tree=tree)
        if not (qc.noisy_residual_mm > 0 and self.unit_mm and normals is not None):
            return patches, False
        narrow = patches.radius * self.unit_mm <= qc.noisy_radius_mm
        # sparse input (most patches wider than noisy_radius_mm) has large residuals from patches
        # wrapping round a rib, not from noise: it is never judged noisy
        noisy = bool(narrow.mean() >= 0.5 and float(np.median(patches.residual)) * self.unit_mm > qc.noisy_residual_mm)
        if noisy:
            patches.one_sided |= narrow & (patches.facing >= qc.noisy_min_facing)
        return patches, noisy

    def _queries(self, pts: np.ndarray, rng: np.random.Generator, tree: cKDTree) -> tuple[np.ndarray, np.ndarray]:
        """Neural-Pull queries, split evenly over `queries.scales` (tree: a kd-tree of `pts`)."""
        qc = self.config.queries
        base = 0.25 * math.sqrt(len(pts) / 20000.0)
        per = qc.n_queries // len(qc.scales)
        sigma = knn_sigma(pts, qc.knn, tree)
        qs, nn = zip(*(sample_pull_queries(pts, per, rng, k=qc.knn, scale=base * s, sigma=sigma, tree=tree)
                       for s in qc.scales))
        return np.concatenate(qs), np.concatenate(nn)
