"""Data types of the skeleton stage: its config, one rib's curve, and the whole skeleton graph.

All lengths are millimetres in the input's own frame (see docs/architecture.md).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np


@dataclass
class SkeletonConfig:
    """Every knob of `skeletonize`, with units. Defaults are tuned for adult ribs (tube radius 2-6 mm).

    Components (ribs are contracted one by one, so the Laplacian never links two ribs):
      link_mm: two points belong to the same component when a chain of points closer than this joins
        them. None = auto: `link_factor` x the median distance to the 3rd nearest neighbour, capped at
        `link_max_mm` (below the ~7 mm gap between adjacent ribs; 3 x that when point labels are
        given, since clusters never mix labels).
      min_component_points: components with fewer points are merged into the nearest big component
        (when within 2 x link) or dropped. Raises RibPullInputError when fewer than `min_points`
        distinct points are given or more than `max_dropped_fraction` of them would be dropped.
    Contraction (paper eq. 3-4, Cao et al. 2010 schedule):
      normalised_side: each component is scaled so its longest bounding-box side is this (Cao: 1.6)
        before contracting, and mapped back to mm after; the schedule below is in those units.
      n_neighbors: k of the kNN point-cloud Laplacian; None = Cao's clamp(0.012 N, 8, 30) per component.
      mollify_factor: robust-laplacian's intrinsic mollification (relative to mean edge length).
      w_l0: initial contraction weight; None = 1 / (5 x mean kNN edge length) (Cao), normalised units.
      w_h0: initial attraction weight (Cao: 1).
      w_l_growth / w_l_max: W_L <- min(growth x W_L, max) per iteration (Cao: 3 and 2048).
      w_h_max: cap on W_H_i = W_H0 x ring0_i / ring_i (keeps the system well conditioned).
      max_iterations: at most this many solves (Cao: 20). stop_shrink: stop when the mean ring size
        shrinks by less than this fraction in one iteration (Cao: 1 %).
      recompute_laplacian: rebuild the robust Laplacian on the contracted points every iteration
        (pc-skeletor). With the first Laplacian kept fixed, a tube keeps shrinking along its length
        towards a point, so leave this on.
    Curve extraction (mm):
      sample_radius_mm: farthest-point ball sampling radius on the contracted points.
      prune_length_mm / branch_clearance_mm: a side branch of a cluster's tree becomes an extra
        curve only when it runs at least prune_length_mm farther than branch_clearance_mm from the
        paths kept so far (a clean rib is one head->tip path; strands inside the same tube and short
        spurs are dropped).
      min_curve_length_mm: curves shorter than this are dropped.
      merge_gap_mm / merge_angle_deg: two curves whose ends are closer than merge_gap_mm and whose
        end tangents face each other within merge_angle_deg are one rib split by a sampling gap and
        are joined (0 disables).
      step_mm: spacing of the output curve nodes.
      path_smooth_sigma_mm: Gaussian smoothing (arc-length sigma) of the raw sample path, which
        zigzags across the half-contracted ribbon of a flat tube; recentring undoes its bias.
      smooth_sigma_mm: Gaussian smoothing along the curve between recentring passes.
      recentre_sigma_mm / recentre_iterations: each node moves to the centre of an ellipse fitted to the
        surface points in its cross-section (Gaussian window of this sigma along the curve); removes the
        contraction's bias toward the thick side of the tube.
      extend_ends: extend (or trim) each end along its tangent to the cap of the tube, then back off
        by the local radius, the fitted section's minor semi-axis (lands on the cap centre of a
        capsule-like or half-ellipsoid end; see curves.end_cap_offset).
    Deterministic: the same input and config give the same skeleton.
    Radius:
      radius_k: with no distance function, the radius is the mean of the 3 smallest distances to the
        tangent planes of the `radius_k` nearest surface points (normals given, else PCA-estimated),
        capped by the nearest-point distance (extract.surface_distance_fn).
    Names (only used without point labels):
      left_is_positive_x: False (default) = NIfTI/nibabel RAS+ world mm, the patient's left at -x
        (real label maps read through their affine, and ribpull_core.phantom). True for LPS-style
        or "+x = left" frames. +y must be anterior and +z superior either way.
    Runtime:
      n_jobs: worker threads for the per-cluster contraction (None = all cores). Default 1:
        robust-laplacian holds the GIL, so threads gave no speed-up on the 2-core test machine.
    """

    link_mm: float | None = None
    link_factor: float = 2.5
    link_max_mm: float = 5.0
    min_component_points: int = 40
    min_points: int = 50
    max_dropped_fraction: float = 0.5
    normalised_side: float = 1.6
    n_neighbors: int | None = None
    mollify_factor: float = 1e-5
    w_l0: float | None = None
    w_h0: float = 1.0
    w_l_growth: float = 3.0
    w_l_max: float = 2048.0
    w_h_max: float = 1e4
    max_iterations: int = 20
    stop_shrink: float = 0.01
    recompute_laplacian: bool = True
    sample_radius_mm: float = 3.0
    prune_length_mm: float = 20.0
    branch_clearance_mm: float = 8.0
    min_curve_length_mm: float = 10.0
    merge_gap_mm: float = 15.0
    merge_angle_deg: float = 45.0
    step_mm: float = 1.0
    path_smooth_sigma_mm: float = 6.0
    smooth_sigma_mm: float = 2.0
    recentre_sigma_mm: float = 3.0
    recentre_iterations: int = 3
    extend_ends: bool = True
    radius_k: int = 8
    left_is_positive_x: bool = False
    n_jobs: int | None = 1

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class RibCurve:
    """One rib's medial curve: node ids into `Skeleton.nodes_mm`, ordered head -> tip.

    label: "L7" / "R12" style name, or the input label's name when it is not a rib name.
    label_id: the input label value the curve's points carry (e.g. TotalSegmentator 98), or None.
    length_mm: polyline length. mean/min_radius_mm: distance from the nodes to the surface.
    max_curvature_per_mm: largest curvature (1/mm) along the (smoothed) curve.
    """

    label: str
    label_id: int | None
    node_ids: list[int]
    length_mm: float
    mean_radius_mm: float
    min_radius_mm: float
    max_curvature_per_mm: float

    def to_json(self) -> dict:
        return {
            "label": self.label,
            "label_id": None if self.label_id is None else int(self.label_id),
            "node_ids": [int(i) for i in self.node_ids],
            "length_mm": float(self.length_mm),
            "mean_radius_mm": float(self.mean_radius_mm),
            "min_radius_mm": float(self.min_radius_mm),
            "max_curvature_per_mm": float(self.max_curvature_per_mm),
        }


@dataclass
class Skeleton:
    """The medial-axis graph of a ribcage.

    nodes_mm: (K, 3) float64 node positions, mm. edges: (E, 2) int64 node-id pairs.
    radius_mm: (K,) distance from each node to the surface, mm. curves: one RibCurve per rib path.
    info: diagnostics (timings in s, contraction iterations, component sizes, ...).
    """

    nodes_mm: np.ndarray
    edges: np.ndarray
    radius_mm: np.ndarray
    curves: list[RibCurve] = field(default_factory=list)
    info: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.nodes_mm = np.asarray(self.nodes_mm, dtype=np.float64).reshape(-1, 3)
        self.edges = np.asarray(self.edges, dtype=np.int64).reshape(-1, 2)
        self.radius_mm = np.asarray(self.radius_mm, dtype=np.float64).reshape(-1)

    def curve_points(self, curve: RibCurve) -> np.ndarray:
        """(n, 3) mm node positions of one curve, head -> tip."""
        return self.nodes_mm[np.asarray(curve.node_ids, dtype=np.int64)]

    def by_label(self) -> dict[str, RibCurve]:
        return {c.label: c for c in self.curves}

    def to_json(self) -> dict:
        """JSON-ready dict: units, nodes, edges, radius, components (one per curve), counts, info."""
        return {
            "units": "mm",
            "n_nodes": len(self.nodes_mm),
            "n_edges": len(self.edges),
            "nodes": np.round(self.nodes_mm, 4).tolist(),
            "edges": self.edges.astype(int).tolist(),
            "radius": np.round(self.radius_mm, 4).tolist(),
            "components": [c.to_json() for c in self.curves],
            "info": _jsonable(self.info),
        }

    @classmethod
    def from_json(cls, d: dict) -> Skeleton:
        """Inverse of `to_json` (nodes rounded to 1e-4 mm), e.g. to score a saved skeleton.json."""
        if d.get("units", "mm") != "mm":
            raise ValueError(f"skeleton units {d.get('units')!r}; expected 'mm'")
        fields = ("label", "label_id", "node_ids", "length_mm", "mean_radius_mm", "min_radius_mm", "max_curvature_per_mm")
        curves = [RibCurve(**{k: c[k] for k in fields}) for c in d.get("components", [])]
        return cls(d["nodes"], d["edges"], d["radius"], curves, d.get("info", {}))


def _jsonable(x):
    """Convert numpy scalars/arrays nested in dicts/lists to plain Python for json.dump."""
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    return x
