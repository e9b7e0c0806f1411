"""Synthetic adult ribcage with exact ground truth: 24 swept-ellipse ribs, true centerlines,
surface samples and a label volume.

Frame: millimetres in NIfTI/nibabel RAS+: +x = patient's right, +y = anterior, +z = superior, so
left ribs have x < 0 (as in real TotalSegmentator label maps read with nibabel). The seed-0 cage is 285 mm wide, 188 mm
deep and 246 mm tall; y and z are centred on the bounding box, x = 0 is the mid-sagittal plane.

Model (exact up to floating point): each rib is a tube around a smooth 3D centerline c(s)
(s = arc length, mm). Its cross-section in the normal plane at s is the ellipse
(v / a_v(s))^2 + (w / a_t(s))^2 <= 1, with v, w the coordinates along a rotation-minimising
(parallel-transport) frame (e_v ~ "vertical", the cage-surface normal; e_t = thickness). Both ends
are closed by half-ellipsoids centred at the centerline end points, semi-axes (a_v, a_t, c_cap).
The triangle mesh samples that surface (400 rings x 48 vertices + caps), so it deviates from the
analytic surface by < 0.03 mm (mean 0.006 mm, inscribed); `voxelize` and `tube_level` test the
analytic solid directly.

With PhantomConfig(sternum=True) a sternum (label 116: a straight flat tube on the midline, ~173 mm
long, 32 mm wide, 11 mm thick) and costal cartilages (label 117) for ribs 1-10 are added, built the
same way; each cartilage starts a designed gap (1.0-3.0 mm) beyond its rib's tip, so
`separable_ribs` / `isolated_ribs` can tell whether a reconstruction keeps the ribs apart.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh
from scipy import ndimage
from scipy.interpolate import CubicSpline, PchipInterpolator
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from .errors import RibPullInputError
from .pointcloud import PointCloud

N_CENTERLINE = 500  # points per true centerline (RibSeg v2 format)
N_RINGS = 400  # cross-section rings along each rib mesh
N_AROUND = 48  # vertices per ring
N_CAP_RINGS = 8  # latitude steps per end cap (the last one is the pole)
DENSE_STEP_MM = 0.2  # spacing of the analytic tube samples used by `tube_level` / `voxelize`
_FINE_SAMPLES = 20_000  # spline evaluations per rib before arc-length resampling

HEAD_UV_MM = (22.0, -60.0)  # rib head: (|x|, y) in mm, next to the vertebral body
SEMI_AXES_MID_MM = (5.5, 3.5)  # (vertical, thickness) semi-axes along the shaft
SEMI_AXES_END_MM = (4.0, 2.5)  # ... at both ends
TAPER_MM = 35.0  # length over which the cross-section grows from the end size to the shaft size
TILT_DEG = 20.0  # descent of the rib surfaces (towards anterolateral), degrees from horizontal
TILT_AZIMUTH_DEG = 60.0  # direction of steepest descent in the (lateral, anterior) plane
TILT_CURVE_PER_MM = 4.0e-4  # the slope grows with distance from the head (ribs steepen anteriorly)
HEAD_SPACING_MM = 21.0  # vertical distance between successive rib heads

# Template rib (a full "true" rib, head first) in plane coordinates (u = |x|, v = y), mm. Ribs 2-12
# are this curve scaled about the head and cut to a fraction of its length; rib 1 is a circular arc.
_TEMPLATE_UV = np.array(
    [
        [22.0, -60.0],
        [35.0, -78.0],
        [57.0, -93.0],
        [88.0, -98.0],
        [116.0, -82.0],
        [132.0, -47.0],
        [136.0, -6.0],
        [128.0, 35.0],
        [108.0, 65.0],
        [78.0, 84.0],
        [45.0, 93.0],
    ]
)
RIB1_TIP_UV_MM = (33.0, 30.0)  # rib 1: circular arc from the head to this tip (manubrium side)
RIB1_RADIUS_MM = 48.0
# Per rib 1..12: lateral scale, anteroposterior scale (both about the head), fraction of the
# template's length kept (ribs 8-10 stop anterolaterally, 11-12 are floating ribs ending laterally).
_RIB_SU = np.array([1.00, 0.66, 0.76, 0.85, 0.92, 0.97, 1.00, 1.00, 0.98, 0.95, 0.90, 0.82])
_RIB_SV = np.array([1.00, 0.70, 0.79, 0.87, 0.93, 0.97, 1.00, 1.00, 0.98, 0.95, 0.90, 0.86])
_RIB_KEEP = np.array([1.00, 0.92, 0.92, 0.93, 0.92, 0.90, 0.88, 0.84, 0.78, 0.69, 0.50, 0.40])

RIB_NAMES: tuple[str, ...] = tuple(f"L{n}" for n in range(1, 13)) + tuple(f"R{n}" for n in range(1, 13))

# Sternum and costal cartilages (PhantomConfig.sternum), TotalSegmentator v2 ids and names
STERNUM_LABEL = 116
CARTILAGE_LABEL = 117
STRUCTURE_LABEL_NAMES = {STERNUM_LABEL: "sternum", CARTILAGE_LABEL: "costal_cartilages"}
STERNUM_TOP_MM = 4.0  # the sternum's top end lies this far above rib 1's tip centre (mean of L/R)
STERNUM_BOTTOM_MM = 6.0  # ... and its bottom end this far below rib 7's cartilage end
STERNUM_FORWARD_MM = 3.0  # its midline lies this far anterior of the line fitted through rib tips 1-7
# semi-width (mm, along x) along the sternum at fractions of its length, top (manubrium) first
STERNUM_SEMI_WIDTH_MM = ((0.0, 15.0), (0.2, 16.0), (0.3, 12.5), (0.8, 13.0), (1.0, 8.0))
STERNUM_SEMI_THICKNESS_MM = 5.5  # along the anteroposterior direction: 11 mm thick
CARTILAGE_RISE_MM = (0.0, 0.0, 0.0, 0.0, 2.0, 5.0, 9.0)  # cartilages of ribs 1-7: end minus tip height
SHARED_CARTILAGE_AT = {8: 0.40, 9: 0.45, 10: 0.45}  # ribs 8-10 join the cartilage of the rib above here
CARTILAGE_END_GAP_MM = 1.0  # surface gap left at a cartilage's medial end (sternum / cartilage above)
CARTILAGE_GAP_RANGE_MM = (1.7, 3.0)  # rib tip -> cartilage gap of most ribs (separable at 1.5 mm) ...
CLOSE_GAP_RANGE_MM = (1.0, 1.25)  # ... and of N_CLOSE_CARTILAGES ribs drawn from the seed (not separable)
N_CLOSE_CARTILAGES = 4
STRUCTURE_RING_STEP_MM = 0.5  # ring spacing of the structure meshes


@dataclass
class PhantomConfig:
    """Parameters of a synthetic ribcage.

    seed: anatomical variation (global width/depth/height/tilt +-5 %, per rib +-2 %).
    n_points: surface samples in the point cloud written by `write_phantom`.
    noise_mm: isotropic Gaussian noise std (mm, per axis) on those samples.
    missing_ribs: names ("L11", "R3", ...) of ribs left out, in the output's naming.
    mirror: x -> -x; a rib that lands at x > 0 is named R (so names stay anatomically correct).
    scale: uniform size factor applied to everything (cross-sections included).
    sternum: also build a sternum (label 116) and costal cartilages (label 117) for ribs 1-10,
        each cartilage starting a small gap (1.0-3.0 mm, per rib from the seed) beyond its rib's
        tip; the ribs themselves are unchanged.
    """

    seed: int = 0
    n_points: int = 60_000
    noise_mm: float = 0.3
    missing_ribs: tuple[str, ...] = ()
    mirror: bool = False
    scale: float = 1.0
    sternum: bool = False


@dataclass
class Tube:
    """Analytic tube model of one rib, sampled every ~DENSE_STEP_MM along the centerline.

    points_mm: (M, 3) centerline samples, head first. tangents, e_v, e_t: (M, 3) orthonormal
    parallel-transport frame. a_v_mm, a_t_mm: (M,) elliptical semi-axes along e_v / e_t.
    cap_mm: (2,) semi-axis of the head / tip cap along the (outward) tangent. step_mm: spacing.
    """

    points_mm: np.ndarray
    tangents: np.ndarray
    e_v: np.ndarray
    e_t: np.ndarray
    a_v_mm: np.ndarray
    a_t_mm: np.ndarray
    cap_mm: np.ndarray
    step_mm: float


@dataclass
class Rib:
    """One rib. centerline_mm: (500, 3) head (vertebral end) -> tip, ends = end-cap centres.

    label_id: TotalSegmentator id (left n -> 91 + n, right n -> 103 + n).
    mesh: watertight closed surface, outward normals. tube: the analytic model behind both.
    """

    name: str
    side: str
    number: int
    label_id: int
    centerline_mm: np.ndarray
    mesh: trimesh.Trimesh
    tube: Tube | None = field(default=None, repr=False, compare=False)

    @property
    def length_mm(self) -> float:
        """Arc length of the centerline in mm."""
        return float(np.linalg.norm(np.diff(self.tube.points_mm, axis=0), axis=1).sum())


@dataclass
class Structure:
    """A non-rib solid of the phantom (sternum or one costal cartilage), modelled like a rib as an
    analytic tube (`tube`; its level function is `tube_level`) with a watertight outward mesh.

    name: "sternum" or "costal_cartilage_L3" (the cartilage of rib L3). label_id: 116 (sternum)
    or 117 (costal cartilages, one label for all of them, as in TotalSegmentator v2).
    rib: name of the rib the cartilage continues (None for the sternum). gap_mm: designed
    surface gap between that rib's tip and the cartilage (None for the sternum)."""

    name: str
    label_id: int
    mesh: trimesh.Trimesh
    tube: Tube = field(repr=False, compare=False)
    rib: str | None = None
    gap_mm: float | None = None


@dataclass
class Phantom:
    """A ribcage: the config it came from, its ribs (order L1..L12, R1..R12, missing ones left
    out), the extra structures (sternum then cartilages, only with config.sternum) and all their
    meshes concatenated in that order (one connected component per rib / structure)."""

    config: PhantomConfig
    ribs: list[Rib]
    mesh: trimesh.Trimesh
    structures: list[Structure] = field(default_factory=list)

    @property
    def solids(self) -> list[Rib | Structure]:
        """Ribs then structures: the order of the pieces of `mesh`."""
        return [*self.ribs, *self.structures]

    @property
    def cartilage_gaps_mm(self) -> dict[str, float]:
        """rib name -> designed gap (mm) between its tip and its costal cartilage."""
        return {st.rib: st.gap_mm for st in self.structures if st.rib is not None}

    def centerlines(self) -> dict[str, np.ndarray]:
        """name -> (500, 3) true centerline in mm, head -> tip."""
        return {r.name: r.centerline_mm for r in self.ribs}

    def ribseg_centerlines(self) -> np.ndarray:
        """(24, 500, 3) centerlines in RibSeg v2 layout (rows L1..L12, R1..R12); -1 for missing ribs."""
        out = np.full((24, N_CENTERLINE, 3), -1.0)
        for r in self.ribs:
            out[RIB_NAMES.index(r.name)] = r.centerline_mm
        return out

    def face_labels(self) -> np.ndarray:
        """(F,) int32 label_id of every face of `mesh`."""
        solids = self.solids
        return np.repeat(
            np.array([r.label_id for r in solids], dtype=np.int32), [len(r.mesh.faces) for r in solids]
        )

    def face_solids(self) -> np.ndarray:
        """(F,) int index into `solids` of the rib / structure every face of `mesh` belongs to."""
        return np.repeat(np.arange(len(self.solids)), [len(r.mesh.faces) for r in self.solids])

    def label_names(self) -> dict[int, str]:
        """label_id -> TotalSegmentator name ("rib_left_7", "sternum", "costal_cartilages") for
        the ribs and structures present."""
        names = {r.label_id: rib_label_name(r.side, r.number) for r in self.ribs}
        names.update({st.label_id: STRUCTURE_LABEL_NAMES[st.label_id] for st in self.structures})
        return names


# ----------------------------------------------------------------------------------- naming


def label_id(side: str, number: int) -> int:
    """TotalSegmentator id of a rib: left n -> 91 + n, right n -> 103 + n."""
    return (91 if side == "L" else 103) + number


def rib_label_name(side: str, number: int) -> str:
    """TotalSegmentator class name, e.g. ("L", 7) -> "rib_left_7"."""
    return f"rib_{'left' if side == 'L' else 'right'}_{number}"


def _check_config(config: PhantomConfig) -> None:
    bad = [n for n in config.missing_ribs if n not in RIB_NAMES]
    if bad:
        raise RibPullInputError("bad_parameter", f"unknown rib names {bad}; use L1..L12, R1..R12")
    if len(set(config.missing_ribs)) >= 24:
        raise RibPullInputError("bad_parameter", "missing_ribs removes every rib")
    if not (np.isfinite(config.scale) and config.scale > 0):
        raise RibPullInputError("bad_parameter", f"scale must be > 0, got {config.scale}")
    if not (np.isfinite(config.noise_mm) and config.noise_mm >= 0):
        raise RibPullInputError("bad_parameter", f"noise_mm must be >= 0, got {config.noise_mm}")
    if int(config.n_points) < 1:
        raise RibPullInputError("bad_parameter", f"n_points must be >= 1, got {config.n_points}")


# ----------------------------------------------------------------------------- centerlines


def _variation(seed: int) -> dict:
    """Random anatomical factors for a seed: global (scalars) and per (side, rib) (dicts)."""
    rng = np.random.default_rng(seed)
    glob = {k: 1.0 + 0.05 * rng.uniform(-1, 1) for k in ("width", "depth", "height", "tilt")}
    per = {}
    for side in ("L", "R"):
        for n in range(1, 13):
            per[(side, n)] = {k: 1.0 + 0.02 * rng.uniform(-1, 1) for k in ("su", "sv", "keep", "dz")}
    return {"global": glob, "per": per}


def _arc_uv(head: tuple[float, float], tip: tuple[float, float], radius: float, n: int = 13) -> np.ndarray:
    """(n, 2) points on the circular arc (mm) from head to tip bulging laterally (+u)."""
    h, t = np.asarray(head, dtype=np.float64), np.asarray(tip, dtype=np.float64)
    chord = t - h
    half = np.linalg.norm(chord) / 2.0
    medial = np.array([-chord[1], chord[0]]) / (2.0 * half)  # left normal of head->tip: towards -u
    centre = (h + t) / 2.0 + medial * np.sqrt(radius**2 - half**2)
    a0 = np.arctan2(*(h - centre)[::-1])
    a1 = np.arctan2(*(t - centre)[::-1])
    if a1 < a0:  # counter-clockwise from the head goes round the lateral side
        a1 += 2 * np.pi
    ang = np.linspace(a0, a1, n)
    return centre + radius * np.column_stack([np.cos(ang), np.sin(ang)])


def _plane_curve(number: int, su: float, sv: float, keep: float) -> np.ndarray:
    """(K, 2) finely sampled (u = |x|, v = y) curve of rib `number`, head first, mm."""
    hu, hv = HEAD_UV_MM
    tmpl = _arc_uv(HEAD_UV_MM, RIB1_TIP_UV_MM, RIB1_RADIUS_MM) if number == 1 else _TEMPLATE_UV
    ctrl = np.column_stack([hu + (tmpl[:, 0] - hu) * su, hv + (tmpl[:, 1] - hv) * sv])
    knots = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(ctrl, axis=0), axis=1))])
    spline = CubicSpline(knots, ctrl, bc_type="natural")
    t = np.linspace(0.0, knots[-1] * min(keep, 1.0), _FINE_SAMPLES)
    return spline(t)


def _surface_height(u: np.ndarray, v: np.ndarray, z_head: float, tilt: float) -> np.ndarray:
    """z (mm) of the gently curved descending surface a rib lies on, at plane coords (u, v)."""
    az = np.deg2rad(TILT_AZIMUTH_DEG)
    d = (u - HEAD_UV_MM[0]) * np.cos(az) + (v - HEAD_UV_MM[1]) * np.sin(az)
    return z_head - np.tan(np.deg2rad(TILT_DEG * tilt)) * d - TILT_CURVE_PER_MM * np.maximum(d, 0.0) ** 2


def _surface_normal(u: float, v: float, tilt: float, sx: float) -> np.ndarray:
    """(3,) upward unit normal of that surface at (u, v), in x/y/z (x = sx * u)."""
    az = np.deg2rad(TILT_AZIMUTH_DEG)
    d = (u - HEAD_UV_MM[0]) * np.cos(az) + (v - HEAD_UV_MM[1]) * np.sin(az)
    slope = np.tan(np.deg2rad(TILT_DEG * tilt)) + 2 * TILT_CURVE_PER_MM * max(d, 0.0)
    n = np.array([sx * slope * np.cos(az), slope * np.sin(az), 1.0])
    return n / np.linalg.norm(n)


def _resample(fine: np.ndarray, n: int | None = None, step: float | None = None) -> np.ndarray:
    """Resample a fine (K, 3) polyline uniformly by arc length to n points (or ~step mm apart)."""
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(fine, axis=0), axis=1))])
    if n is None:
        n = max(int(np.ceil(s[-1] / step)) + 1, 2)
    q = np.linspace(0.0, s[-1], n)
    return np.column_stack([np.interp(q, s, fine[:, k]) for k in range(3)])


def _rib_fine_curve(
    side_sign: float, number: int, z_head: float, factors: dict, glob: dict
) -> tuple[np.ndarray, float]:
    """(K, 3) fine 3D centerline (mm, uncentred; head at height z_head) and the tilt factor used."""
    uv = _plane_curve(
        number,
        _RIB_SU[number - 1] * glob["width"] * factors["su"],
        _RIB_SV[number - 1] * glob["depth"] * factors["sv"],
        _RIB_KEEP[number - 1] * factors["keep"],
    )
    tilt = glob["tilt"]
    z = _surface_height(uv[:, 0], uv[:, 1], z_head, tilt)
    return np.column_stack([side_sign * uv[:, 0], uv[:, 1], z]), tilt


# ------------------------------------------------------------------------------------ tubes


def _tangents(points: np.ndarray) -> np.ndarray:
    """(M, 3) unit tangents of a polyline (central differences)."""
    t = np.gradient(points, axis=0)
    return t / np.linalg.norm(t, axis=1, keepdims=True)


def parallel_transport(tangents: np.ndarray, e0: np.ndarray) -> np.ndarray:
    """(M, 3) rotation-minimising transport of the unit vector e0 (perpendicular to tangents[0])
    along unit tangents (M, 3), by the double-reflection method (Wang et al. 2008)."""
    out = np.empty_like(tangents)
    e = np.asarray(e0, dtype=np.float64)
    e = e - (e @ tangents[0]) * tangents[0]
    e = e / np.linalg.norm(e)
    out[0] = e
    # reflecting in the plane normal to (t_i + t_{i+1}) and then in the plane normal to t_{i+1} is
    # the rotation about t_i x t_{i+1} that takes t_i to t_{i+1}: the minimal (parallel) transport
    # (plain floats: this sequential loop runs ~1,500 times per rib)
    ex, ey, ez = (float(c) for c in e)
    tl = tangents.tolist()
    for i in range(len(tl) - 1):
        ax, ay, az = tl[i]
        tx, ty, tz = tl[i + 1]
        bx, by, bz = ax + tx, ay + ty, az + tz
        k = 2.0 * (bx * ex + by * ey + bz * ez) / (bx * bx + by * by + bz * bz)
        ex, ey, ez = ex - k * bx, ey - k * by, ez - k * bz
        k = tx * ex + ty * ey + tz * ez  # ~0: e is now normal to t_{i+1}; drop the rounding residue
        ex, ey, ez = ex - k * tx, ey - k * ty, ez - k * tz
        n = (ex * ex + ey * ey + ez * ez) ** 0.5
        ex, ey, ez = ex / n, ey / n, ez / n
        out[i + 1] = (ex, ey, ez)
    return out


def _taper(s: np.ndarray, length: float, ramp: float) -> np.ndarray:
    """(M,) weight in [0, 1] at arc lengths s (mm): 0 at both ends, 1 along the shaft (C1
    smoothstep over `ramp` mm, at most 40 % of the length from each end)."""
    ramp = min(ramp, 0.4 * length)
    x = np.clip(np.minimum(s, length - s) / ramp, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _build_tube(fine: np.ndarray, e0: np.ndarray, scale: float) -> Tube:
    """Dense analytic tube model from a fine 3D centerline (mm) and the initial 'vertical' vector."""
    pts = _resample(fine, step=DENSE_STEP_MM)
    step = float(np.linalg.norm(pts[1] - pts[0]))
    tan = _tangents(pts)
    e_v = parallel_transport(tan, e0)
    e_t = np.cross(tan, e_v)
    s = np.arange(len(pts)) * step
    w = _taper(s, s[-1], TAPER_MM * scale)
    a_v = (SEMI_AXES_END_MM[0] + (SEMI_AXES_MID_MM[0] - SEMI_AXES_END_MM[0]) * w) * scale
    a_t = (SEMI_AXES_END_MM[1] + (SEMI_AXES_MID_MM[1] - SEMI_AXES_END_MM[1]) * w) * scale
    cap = np.array([a_t[0], a_t[-1]])
    return Tube(pts, tan, e_v, e_t, a_v, a_t, cap, step)


def _interp_rows(arr: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Linear interpolation of the rows of arr (M, ...) at fractional indices idx (R,)."""
    i0 = np.clip(np.floor(idx).astype(int), 0, len(arr) - 2)
    f = (idx - i0).reshape((-1,) + (1,) * (arr.ndim - 1))
    return arr[i0] * (1.0 - f) + arr[i0 + 1] * f


def tube_mesh(
    tube: Tube, n_rings: int = N_RINGS, n_around: int = N_AROUND, n_cap: int = N_CAP_RINGS
) -> trimesh.Trimesh:
    """Watertight triangle mesh of the tube (mm): n_rings ellipses + two half-ellipsoid caps,
    outward-facing. Vertices: n_rings * n_around + 2 * ((n_cap - 1) * n_around + 1)."""
    m = len(tube.points_mm)
    idx = np.linspace(0.0, m - 1, n_rings)
    c = _interp_rows(tube.points_mm, idx)
    ev = _interp_rows(tube.e_v, idx)
    tg = _interp_rows(tube.tangents, idx)
    tg /= np.linalg.norm(tg, axis=1, keepdims=True)
    ev -= np.einsum("ij,ij->i", ev, tg)[:, None] * tg
    ev /= np.linalg.norm(ev, axis=1, keepdims=True)
    et = np.cross(tg, ev)
    av, at = np.interp(idx, np.arange(m), tube.a_v_mm), np.interp(idx, np.arange(m), tube.a_t_mm)
    ang = np.linspace(0.0, 2 * np.pi, n_around, endpoint=False)
    ca, sa = np.cos(ang), np.sin(ang)
    rings = (
        c[:, None, :]
        + (av[:, None] * ca[None, :])[..., None] * ev[:, None, :]
        + (at[:, None] * sa[None, :])[..., None] * et[:, None, :]
    )  # (n_rings, n_around, 3)

    def cap(k: int, out_dir: np.ndarray, c_len: float) -> np.ndarray:
        beta = np.linspace(0.0, np.pi / 2, n_cap + 1)[1:-1]
        equator = (av[k] * ca)[:, None] * ev[k] + (at[k] * sa)[:, None] * et[k]  # (n_around, 3)
        ring = equator[None] * np.cos(beta)[:, None, None]
        ring = c[k] + ring + (np.sin(beta) * c_len)[:, None, None] * out_dir
        pole = c[k] + c_len * out_dir
        return np.concatenate([ring.reshape(-1, 3), pole[None]])

    head = cap(0, -tg[0], tube.cap_mm[0])
    tip = cap(-1, tg[-1], tube.cap_mm[1])
    verts = np.concatenate([rings.reshape(-1, 3), head, tip])

    j = np.arange(n_around)
    jn = (j + 1) % n_around

    def band(r0: np.ndarray, r1: np.ndarray) -> np.ndarray:
        """Triangles joining two rings of vertex ids (K, n_around) row-wise."""
        a, b = r0[:, j], r0[:, jn]
        cc, d = r1[:, jn], r1[:, j]
        return np.concatenate([np.stack([a, b, cc], -1), np.stack([a, cc, d], -1)]).reshape(-1, 3)

    tube_ids = np.arange(n_rings * n_around).reshape(n_rings, n_around)
    faces = [band(tube_ids[:-1], tube_ids[1:])]
    base = n_rings * n_around
    for first_ring, start, flip in (
        (tube_ids[0], base, True),
        (tube_ids[-1], base + (n_cap - 1) * n_around + 1, False),
    ):
        cap_ids = start + np.arange((n_cap - 1) * n_around).reshape(n_cap - 1, n_around)
        chain = np.vstack([first_ring[None], cap_ids])
        pole = start + (n_cap - 1) * n_around
        cap_faces = np.concatenate(
            [
                band(chain[:-1], chain[1:]),
                np.column_stack([chain[-1, j], chain[-1, jn], np.full(n_around, pole)]),
            ]
        )
        faces.append(cap_faces[:, ::-1] if flip else cap_faces)  # the head cap runs against s
    faces = np.concatenate(faces)
    if _signed_volume(verts, faces) < 0:  # consistent winding by construction; make it outward
        faces = faces[:, ::-1]
    return trimesh.Trimesh(verts, np.ascontiguousarray(faces), process=False)


def _signed_volume(verts: np.ndarray, faces: np.ndarray) -> float:
    """Signed volume (mm^3) enclosed by a closed triangle mesh (positive for outward winding)."""
    a, b, c = (verts[faces[:, k]] for k in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def _tube_local(tube: Tube, points_mm: np.ndarray) -> dict:
    """Local coordinates of points (N, 3) mm in the tube's frame at their foot points.

    Returns fi (N,) fractional sample index of the foot point (clipped to the ends), v, w (N,)
    coordinates along e_v / e_t, t (N,) along the tangent (0 for interior foot points, the signed
    overshoot beyond an end), frame rows ev, et, tg (N, 3), and the interpolated semi-axes av, at."""
    p = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    m = len(tube.points_mm)
    _, i = cKDTree(tube.points_mm).query(p)
    t0 = np.einsum("ij,ij->i", p - tube.points_mm[i], tube.tangents[i])
    # refine the foot point along the curve (fractional sample index; two Newton-like steps), then
    # use the interpolated frame there
    fi = np.clip(i + t0 / tube.step_mm, 0.0, m - 1)
    for _ in range(2):
        c = _interp_rows(tube.points_mm, fi)
        tg = _interp_rows(tube.tangents, fi)
        tg /= np.linalg.norm(tg, axis=1, keepdims=True)
        fi = np.clip(fi + np.einsum("ij,ij->i", p - c, tg) / tube.step_mm, 0.0, m - 1)
    c = _interp_rows(tube.points_mm, fi)
    tg = _interp_rows(tube.tangents, fi)
    ev = _interp_rows(tube.e_v, fi)
    tg /= np.linalg.norm(tg, axis=1, keepdims=True)
    ev -= np.einsum("ij,ij->i", ev, tg)[:, None] * tg
    ev /= np.linalg.norm(ev, axis=1, keepdims=True)
    et = np.cross(tg, ev)
    d = p - c
    v, w, t = (np.einsum("ij,ij->i", d, e) for e in (ev, et, tg))
    idx = np.arange(m)
    return {
        "fi": fi, "v": v, "w": w, "t": t, "d": d, "ev": ev, "et": et, "tg": tg,
        "av": np.interp(fi, idx, tube.a_v_mm), "at": np.interp(fi, idx, tube.a_t_mm),
        "head": (fi <= 0.0) & (t < 0), "tip": (fi >= m - 1) & (t > 0),
    }  # fmt: skip


def tube_level(rib: Rib | Structure, points_mm: np.ndarray) -> np.ndarray:
    """(N,) normalised elliptical radius of points (N, 3) mm w.r.t. the rib's analytic solid:
    < 1 inside, 1 on the surface, > 1 outside. Exact for points within ~one tube radius of the
    surface (the tube's reach); farther away it is only guaranteed to be > 1."""
    tube = rib.tube
    loc = _tube_local(tube, points_mm)
    rho2 = (loc["v"] / loc["av"]) ** 2 + (loc["w"] / loc["at"]) ** 2
    # caps: beyond an end (along that end's outward tangent) the solid is a half-ellipsoid
    for mask, c in ((loc["head"], tube.cap_mm[0]), (loc["tip"], tube.cap_mm[1])):
        rho2[mask] += (loc["t"][mask] / c) ** 2
    return np.sqrt(rho2)


def tube_normals(rib: Rib | Structure, points_mm: np.ndarray) -> np.ndarray:
    """(N, 3) outward unit normals of the analytic surface through points (N, 3) mm: the
    normalised gradient of `tube_level` (closed form; exact on the surface, where level = 1).

    With a parallel-transport frame dv/dp = e_v and dw/dp = e_t exactly; the foot point moves as
    ds/dp = T / (1 - kappa . (p - c)), which only matters through the taper da/ds."""
    tube = rib.tube
    loc = _tube_local(tube, points_mm)
    av, at, v, w = loc["av"], loc["at"], loc["v"], loc["w"]
    grad = (v / av**2)[:, None] * loc["ev"] + (w / at**2)[:, None] * loc["et"]
    m = len(tube.points_mm)
    dav = np.interp(loc["fi"], np.arange(m), np.gradient(tube.a_v_mm, tube.step_mm))
    dat = np.interp(loc["fi"], np.arange(m), np.gradient(tube.a_t_mm, tube.step_mm))
    kappa = _interp_rows(np.gradient(tube.tangents, tube.step_mm, axis=0), loc["fi"])
    stretch = 1.0 - np.einsum("ij,ij->i", kappa, loc["d"])
    grad -= ((v**2 * dav / av**3 + w**2 * dat / at**3) / stretch)[:, None] * loc["tg"]
    for mask, c in ((loc["head"], tube.cap_mm[0]), (loc["tip"], tube.cap_mm[1])):
        grad[mask] = (
            (v[mask] / av[mask] ** 2)[:, None] * loc["ev"][mask]
            + (w[mask] / at[mask] ** 2)[:, None] * loc["et"][mask]
            + (loc["t"][mask] / c**2)[:, None] * loc["tg"][mask]
        )
    return grad / np.linalg.norm(grad, axis=1, keepdims=True)


# ------------------------------------------------------------------- sternum and cartilages


def _straight_tube(points_mm: np.ndarray, e0: np.ndarray, a_v_mm: np.ndarray, a_t_mm: np.ndarray) -> Tube:
    """Tube along a dense (M, 3) centerline (mm, ~DENSE_STEP_MM apart) with semi-axes a_v, a_t (M,)
    and end caps of semi-axis a_t at each end; e0 (3,) is the initial e_v direction."""
    step = float(np.linalg.norm(np.diff(points_mm, axis=0), axis=1).mean())
    tan = _tangents(points_mm)
    e_v = parallel_transport(tan, e0)
    e_t = np.cross(tan, e_v)
    cap = np.array([a_t_mm[0], a_t_mm[-1]])
    return Tube(points_mm, tan, e_v, e_t, np.asarray(a_v_mm, float), np.asarray(a_t_mm, float), cap, step)


def _structure_mesh(tube: Tube, n_around: int = N_AROUND) -> trimesh.Trimesh:
    """Watertight mesh of a structure tube, rings ~STRUCTURE_RING_STEP_MM apart."""
    length = (len(tube.points_mm) - 1) * tube.step_mm
    return tube_mesh(
        tube, n_rings=max(8, int(np.ceil(length / STRUCTURE_RING_STEP_MM)) + 1), n_around=n_around
    )


def _rib_tip_pole(tube: Tube) -> tuple[np.ndarray, np.ndarray]:
    """(3,) pole of the tip cap (mm) and (3,) outward tip tangent."""
    return tube.points_mm[-1] + tube.cap_mm[1] * tube.tangents[-1], tube.tangents[-1]


def _cartilage_gaps(seed: int) -> dict[str, float]:
    """Designed rib tip -> cartilage gap (mm) for L1..L10, R1..R10: uniform in
    CARTILAGE_GAP_RANGE_MM except N_CLOSE_CARTILAGES ribs (drawn from the seed) in CLOSE_GAP_RANGE_MM.
    Its own random stream: the ribs' anatomy does not depend on it."""
    rng = np.random.default_rng([int(seed), STERNUM_LABEL])
    names = [f"{side}{n}" for side in ("L", "R") for n in range(1, 11)]
    gaps = rng.uniform(*CARTILAGE_GAP_RANGE_MM, size=len(names))
    close = rng.choice(len(names), N_CLOSE_CARTILAGES, replace=False)
    gaps[close] = rng.uniform(*CLOSE_GAP_RANGE_MM, size=N_CLOSE_CARTILAGES)
    return {n: float(g) for n, g in zip(names, gaps)}


def _sternum_tube(tubes: dict[str, Tube], scale: float) -> Tube:
    """Sternum: a straight flat tube on the mid-sagittal plane from above rib 1's tips to below
    rib 7's cartilage ends, through (STERNUM_FORWARD_MM anterior of) the line fitted to tips 1-7."""
    tips = np.array([[tubes[f"{side}{n}"].points_mm[-1] for n in range(1, 8)] for side in "LR"]).mean(axis=0)
    slope, offset = np.polyfit(tips[:, 2], tips[:, 1], 1)  # y = slope * z + offset (mm)
    z_top = tips[0, 2] + STERNUM_TOP_MM * scale
    z_bottom = tips[6, 2] + (CARTILAGE_RISE_MM[6] - STERNUM_BOTTOM_MM) * scale
    forward = STERNUM_FORWARD_MM * scale * np.sqrt(1 + slope**2)  # measured normal to the line
    ends = np.array([[0.0, slope * z + offset + forward, z] for z in (z_top, z_bottom)])
    length = float(np.linalg.norm(ends[1] - ends[0]))
    n = int(np.ceil(length / DENSE_STEP_MM)) + 1
    pts = ends[0] + np.linspace(0.0, 1.0, n)[:, None] * (ends[1] - ends[0])
    frac, width = np.array(STERNUM_SEMI_WIDTH_MM).T
    a_v = PchipInterpolator(frac, width * scale)(np.linspace(0.0, 1.0, n))
    a_t = np.full(n, STERNUM_SEMI_THICKNESS_MM * scale)
    return _straight_tube(pts, np.array([1.0, 0.0, 0.0]), a_v, a_t)


def _hermite(p0: np.ndarray, t0: np.ndarray, p1: np.ndarray, t1: np.ndarray) -> np.ndarray:
    """Dense (K, 3) cubic Hermite curve (mm) from p0 leaving along unit t0 to p1 arriving along
    unit t1, tangent lengths = the chord; resampled ~DENSE_STEP_MM apart."""
    chord = float(np.linalg.norm(p1 - p0))
    u = np.linspace(0.0, 1.0, 4000)[:, None]
    h00, h10, h01, h11 = 2 * u**3 - 3 * u**2 + 1, u**3 - 2 * u**2 + u, -2 * u**3 + 3 * u**2, u**3 - u**2
    fine = h00 * p0 + h10 * chord * t0 + h01 * p1 + h11 * chord * t1
    return _resample(fine, step=DENSE_STEP_MM)


def _cartilage_tube(rib_tube: Tube, gap_mm: float, end_mm: np.ndarray, end_dir: np.ndarray) -> Tube:
    """Cartilage continuing a rib: its start cap's pole lies gap_mm beyond the rib's tip pole along
    the tip tangent (same cross-section and frame as the rib's tip, so the gap is exactly gap_mm,
    pole to pole); it ends (cap centre) at end_mm (3,) arriving along end_dir (3,)."""
    a_v, a_t = float(rib_tube.a_v_mm[-1]), float(rib_tube.a_t_mm[-1])
    pole, tangent = _rib_tip_pole(rib_tube)
    start = pole + (gap_mm + a_t) * tangent
    pts = _hermite(start, tangent, end_mm, end_dir / np.linalg.norm(end_dir))
    n = len(pts)
    return _straight_tube(pts, rib_tube.e_v[-1], np.full(n, a_v), np.full(n, a_t))


def _build_structures(tubes: dict[str, Tube], config: PhantomConfig) -> list[Structure]:
    """Sternum and the costal cartilages of the ribs present (1-7 end next to the sternum's edge,
    8-10 below the cartilage of the rib above; every end CARTILAGE_END_GAP_MM short of it)."""
    scale = config.scale
    sternum = _sternum_tube(tubes, scale)
    end_gap = CARTILAGE_END_GAP_MM * scale
    gaps = {name: g * scale for name, g in _cartilage_gaps(config.seed).items()}
    cart: dict[str, Tube] = {}
    for side in ("L", "R"):
        for n in range(1, 11):
            name = f"{side}{n}"
            rib = tubes[name]
            a_t = float(rib.a_t_mm[-1])
            if n <= 7:  # true ribs: to the sternum's lateral edge, arriving horizontally (medially)
                lateral = np.sign(rib.points_mm[-1, 0])
                z_end = rib.points_mm[-1, 2] + CARTILAGE_RISE_MM[n - 1] * scale
                fi = (sternum.points_mm[0, 2] - z_end) / (sternum.points_mm[0, 2] - sternum.points_mm[-1, 2])
                k = fi * (len(sternum.points_mm) - 1)
                centre = _interp_rows(sternum.points_mm, np.array([k]))[0]
                half_width = float(np.interp(k, np.arange(len(sternum.a_v_mm)), sternum.a_v_mm))
                end = centre + np.array([lateral * (half_width + end_gap + a_t), 0.0, 0.0])
                end_dir = np.array([-lateral, 0.0, 0.0])
            else:  # false ribs 8-10: up to the underside of the cartilage above
                above = cart[f"{side}{n - 1}"]
                i = round(SHARED_CARTILAGE_AT[n] * (len(above.points_mm) - 1))
                up = above.e_v[i] if above.e_v[i, 2] > 0 else -above.e_v[i]
                end = above.points_mm[i] - up * (above.a_v_mm[i] + end_gap + a_t)
                end_dir = up
            cart[name] = _cartilage_tube(rib, gaps[name], end, end_dir)
    out = [Structure("sternum", STERNUM_LABEL, _structure_mesh(sternum, n_around=64), sternum)]
    for name, tube in cart.items():
        if name not in config.missing_ribs:
            out.append(
                Structure(f"costal_cartilage_{name}", CARTILAGE_LABEL, _structure_mesh(tube), tube,
                          rib=name, gap_mm=gaps[name])
            )  # fmt: skip
    return out


# ------------------------------------------------------------------- gaps and isolated ribs


def _gap_info(solid: Rib | Structure) -> dict:
    """What `_mesh_gap_mm` needs of a solid: its mesh, a kd-tree of its face centroids, its longest
    edge (mm), a kd-tree of its centerline ~1 mm apart and its largest semi-axis (mm)."""
    mesh, tube = solid.mesh, solid.tube
    tri = mesh.triangles
    edge = max(float(np.linalg.norm(tri[:, k] - tri[:, (k + 1) % 3], axis=1).max()) for k in range(3))
    axis = _resample(tube.points_mm, step=1.0)
    reach = float(max(tube.a_v_mm.max(), tube.a_t_mm.max(), tube.cap_mm.max()))
    return {
        "mesh": mesh, "faces": cKDTree(mesh.triangles_center), "edge": edge,
        "axis_mm": axis, "axis": cKDTree(axis), "reach": reach,
    }  # fmt: skip


def _points_to_mesh_mm(
    points: np.ndarray, mesh: trimesh.Trimesh, face_tree: cKDTree, k: int = 12
) -> np.ndarray:
    """(N,) distance (mm) from points (N, 3) to mesh: exact point-to-triangle distance to the k faces
    with the nearest centroids (the closest face is among them on these fine, regular meshes)."""
    _, faces = face_tree.query(points, k=k)
    pi = np.repeat(np.arange(len(points)), k)
    closest = trimesh.triangles.closest_point(mesh.triangles[faces.ravel()], points[pi])
    return np.linalg.norm(closest - points[pi], axis=1).reshape(len(points), k).min(axis=1)


def _mesh_gap_mm(a: dict, b: dict, cutoff_mm: float) -> float:
    """Smallest distance (mm) between two disjoint solids' triangle meshes (vertex-to-triangle both
    ways; `_gap_info` dicts); inf when it is more than cutoff_mm. A point's distance to a mesh is at
    most its distance to the nearest face centroid and at least that minus the longest edge, so only
    vertices within one edge of the closest centroid distance are refined exactly."""
    best = np.inf
    axis_bound = a["reach"] + b["reach"] + cutoff_mm + 1.0  # centerlines ~1 mm apart: +1 mm
    if not np.isfinite(a["axis"].query(b["axis_mm"], distance_upper_bound=axis_bound)[0]).any():
        return np.inf
    for src, dst in ((a, b), (b, a)):
        v = src["mesh"].vertices
        near_axis = dst["axis"].query(v, distance_upper_bound=dst["reach"] + cutoff_mm + 1.0)[0]
        v = v[np.isfinite(near_axis)]  # the others are farther than cutoff from dst's solid
        if not len(v):
            continue
        dc = dst["faces"].query(v, distance_upper_bound=cutoff_mm + dst["edge"])[0]
        if not np.isfinite(dc).any():
            continue
        near = v[dc <= dc.min() + dst["edge"]]
        best = min(best, float(_points_to_mesh_mm(near, dst["mesh"], dst["faces"]).min()))
    return best if best <= cutoff_mm else np.inf


def rib_gaps_mm(phantom: Phantom, cutoff_mm: float = 5.0) -> dict[str, float]:
    """rib name -> smallest surface distance (mm) from the rib to any other solid of the phantom
    (other ribs, sternum, cartilages); inf when that is more than cutoff_mm.

    Computed on the truth meshes (vertex-to-triangle distances both ways): they are inscribed in the
    analytic surfaces within 0.03 mm and the cartilage / rib-tip poles are mesh vertices, so this is
    the analytic gap to within ~0.05 mm (a designed tip -> cartilage gap comes out exactly)."""
    solids = phantom.solids
    cache: dict[int, dict] = {}

    def info(k: int) -> dict:
        if k not in cache:
            cache[k] = _gap_info(solids[k])
        return cache[k]

    gaps = {}
    for i, rib in enumerate(phantom.ribs):
        best = np.inf
        for j, other in enumerate(solids):
            if j == i:
                continue
            (alo, ahi), (blo, bhi) = rib.mesh.bounds, other.mesh.bounds
            if np.any(alo - cutoff_mm > bhi) or np.any(blo - cutoff_mm > ahi):
                continue  # bounding boxes farther apart than the cutoff
            best = min(best, _mesh_gap_mm(info(i), info(j), cutoff_mm))
        gaps[rib.name] = best
    return gaps


def separable_ribs(phantom: Phantom, min_gap_mm: float = 1.5) -> list[str]:
    """Names (phantom order) of the ribs whose surface is at least min_gap_mm (mm) from every other
    structure's surface (other ribs, sternum, cartilages), by `rib_gaps_mm` (precision ~0.05 mm)."""
    gaps = rib_gaps_mm(phantom, cutoff_mm=max(5.0, 2.0 * min_gap_mm))
    return [name for name, gap in gaps.items() if gap >= min_gap_mm]


def _vertex_components(mesh: trimesh.Trimesh) -> np.ndarray:
    """(V,) connected-component id of every vertex (edges of the faces; unused vertices alone)."""
    f = np.asarray(mesh.faces)
    n = len(mesh.vertices)
    rows = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
    cols = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    return connected_components(graph, directed=False)[1]


def _vertex_areas(mesh: trimesh.Trimesh) -> np.ndarray:
    """(V,) a third of the area (mm^2) of the faces around each vertex."""
    return np.bincount(
        np.asarray(mesh.faces).ravel(),
        weights=np.repeat(mesh.area_faces / 3.0, 3),
        minlength=len(mesh.vertices),
    )


def isolated_ribs(
    mesh: trimesh.Trimesh,
    phantom: Phantom,
    names: list[str] | None = None,
    assign_mm: float = 5.0,
    cover_mm: float = 3.0,
) -> dict[str, bool]:
    """name -> whether the rib comes out of a reconstruction `mesh` (mm, the phantom's frame) as a
    connected component of its own. Default names: every rib of the phantom.

    Every vertex of `mesh` is assigned to the nearest true solid (rib, sternum or cartilage; nearest
    truth-mesh vertex, < 1 mm from the surface) if one is within assign_mm (farther vertices are
    ignored); shares are by vertex area (a third of the adjacent faces' area). A rib is isolated iff
      (a) some connected component has >= 95 % of its assigned area on the rib and comes within
          cover_mm of >= 50 % of the rib's true area, and
      (b) no component holding >= 5 % of its assigned area, or >= 5 % of the rib's true area, on the
          rib has more than 5 % of its assigned area on any other structure (no rib merged into a
          neighbour, even partly)."""
    solids = phantom.solids
    by_name = {r.name: i for i, r in enumerate(phantom.ribs)}
    names = list(by_name) if names is None else list(names)
    unknown = [n for n in names if n not in by_name]
    if unknown:
        raise RibPullInputError("bad_parameter", f"ribs {unknown} are not in the phantom")
    truth_tree = cKDTree(np.concatenate([s.mesh.vertices for s in solids]))
    truth_owner = np.repeat(np.arange(len(solids)), [len(s.mesh.vertices) for s in solids])
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    comp = _vertex_components(mesh)
    n_comp = int(comp.max()) + 1 if len(comp) else 0
    dist, nearest = truth_tree.query(verts, distance_upper_bound=assign_mm)
    assigned = np.isfinite(dist)
    owner = np.where(assigned, truth_owner[np.minimum(nearest, len(truth_owner) - 1)], -1)
    area = _vertex_areas(mesh)
    # (components, solids) assigned area
    share = np.zeros((n_comp, len(solids)))
    np.add.at(share, (comp[assigned], owner[assigned]), area[assigned])
    total = share.sum(axis=1)
    frac = share / np.maximum(total, 1e-12)[:, None]
    out = {}
    for name in names:
        k = by_name[name]
        rib_mesh = solids[k].mesh
        rib_area = float(rib_mesh.area)
        touching = (frac[:, k] >= 0.05) | (share[:, k] >= 0.05 * rib_area)
        other = np.delete(frac, k, axis=1).max(axis=1) if len(solids) > 1 else np.zeros(n_comp)
        merged = bool(np.any(touching & (other > 0.05)))
        own = False
        centres, areas = rib_mesh.triangles_center[::4], rib_mesh.area_faces[::4]  # regular faces: every 4th
        for c in np.nonzero((frac[:, k] >= 0.95) & (total > 0))[0]:
            covered = cKDTree(verts[comp == c]).query(centres, distance_upper_bound=cover_mm)[0]
            if areas[np.isfinite(covered)].sum() >= 0.5 * areas.sum():
                own = True
                break
        out[name] = own and not merged
    return out


# ---------------------------------------------------------------------------------- phantom


def make_phantom(config: PhantomConfig | None = None) -> Phantom:
    """Build the ribcage for `config` (defaults: seed 0, 24 ribs, scale 1). Deterministic. With
    config.sternum the sternum and costal cartilages are added; the ribs are the same either way."""
    config = config or PhantomConfig()
    _check_config(config)
    var = _variation(config.seed)
    glob = var["global"]
    # geometry of every original rib (side as built, before mirroring), uncentred
    built = {}
    for side in ("L", "R"):
        sx = -1.0 if side == "L" else 1.0  # RAS+: the patient's left is -x
        z_head = 0.0
        for n in range(1, 13):
            if n > 1:  # the spacing above rib n varies per interval, not cumulatively
                z_head -= HEAD_SPACING_MM * glob["height"] * var["per"][(side, n)]["dz"]
            fine, tilt = _rib_fine_curve(sx, n, z_head, var["per"][(side, n)], glob)
            e0 = _surface_normal(abs(fine[0, 0]), fine[0, 1], tilt, sx)
            built[(side, n)] = (fine, e0)
    all_pts = np.concatenate([b[0] for b in built.values()])
    lo, hi = all_pts.min(axis=0), all_pts.max(axis=0)
    shift = np.array([0.0, -(lo[1] + hi[1]) / 2, -(lo[2] + hi[2]) / 2])
    flip = np.array([-1.0 if config.mirror else 1.0, 1.0, 1.0])
    ribs = []
    tubes = {}  # output name -> tube (every rib when the structures need them, else those present)
    for out_side in ("L", "R"):
        for n in range(1, 13):
            name = f"{out_side}{n}"
            if name in config.missing_ribs and not config.sternum:
                continue
            src_side = out_side if not config.mirror else ("R" if out_side == "L" else "L")
            fine, e0 = built[(src_side, n)]
            fine = (fine + shift) * flip * config.scale
            tube = _build_tube(fine, e0 * flip, config.scale)
            tubes[name] = tube
            if name in config.missing_ribs:
                continue
            ribs.append(
                Rib(
                    name=name,
                    side=out_side,
                    number=n,
                    label_id=label_id(out_side, n),
                    centerline_mm=_resample(fine, n=N_CENTERLINE),
                    mesh=tube_mesh(tube),
                    tube=tube,
                )
            )
    structures = _build_structures(tubes, config) if config.sternum else []
    mesh = trimesh.util.concatenate([r.mesh for r in ribs] + [st.mesh for st in structures])
    return Phantom(config=config, ribs=ribs, mesh=mesh, structures=structures)


def sample_surface(phantom: Phantom, n_points: int, noise_mm: float = 0.3, seed: int = 0) -> PointCloud:
    """PointCloud of n_points (N, 3) mm samples uniform by area on the true surface (the truth
    mesh: ribs and, when present, sternum and cartilages), plus isotropic Gaussian noise of std
    noise_mm per axis. normals (N, 3): outward normals of the analytic surface at the noise-free
    samples (`tube_normals`); labels (N,): label_id of the rib / structure sampled. The same seed
    gives the same samples whatever noise_mm is."""
    if int(n_points) < 1 or not noise_mm >= 0:
        raise RibPullInputError("bad_parameter", "n_points must be >= 1 and noise_mm >= 0")
    rng = np.random.default_rng(seed)
    pts, face = trimesh.sample.sample_surface(phantom.mesh, int(n_points), seed=rng)
    labels = phantom.face_labels()[face]
    owner = phantom.face_solids()[face]
    normals = np.empty_like(pts)
    for k, solid in enumerate(phantom.solids):
        sel = owner == k
        if sel.any():
            normals[sel] = tube_normals(solid, pts[sel])
    noisy = pts + rng.normal(0.0, 1.0, pts.shape) * float(noise_mm)
    return PointCloud(
        points=noisy,
        normals=normals,
        labels=labels,
        source_format="phantom",
        label_names=phantom.label_names(),
    )


def _spacing_xyz(spacing_mm: float | tuple[float, float, float]) -> np.ndarray:
    """(3,) voxel size (mm) along x, y, z from one number or a 3-sequence; all must be > 0."""
    sp = np.asarray(spacing_mm, dtype=np.float64).ravel()
    sp = np.repeat(sp, 3) if sp.size == 1 else sp
    if sp.shape != (3,) or not np.all(np.isfinite(sp) & (sp > 0)):
        raise RibPullInputError(
            "bad_parameter", f"spacing_mm must be > 0 (one number or three), got {spacing_mm}"
        )
    return sp.copy()


def _ellipsoid_offsets(radius_mm: float, spacing: np.ndarray) -> np.ndarray:
    """(K, 3) integer voxel offsets whose centres lie within radius_mm of the origin (voxel size
    spacing (3,) mm)."""
    r = np.ceil(radius_mm / spacing).astype(int)
    g = np.mgrid[-r[0] : r[0] + 1, -r[1] : r[1] + 1, -r[2] : r[2] + 1].reshape(3, -1).T
    return g[((g * spacing) ** 2).sum(axis=1) <= radius_mm * radius_mm]


def _candidate_voxels(
    tube: Tube, lo: np.ndarray, spacing: np.ndarray, shape: tuple[int, int, int], margin_mm: float
) -> np.ndarray:
    """(K, 3) int indices of the voxels (grid origin lo (3,) mm, voxel size spacing (3,) mm) whose
    centres lie within the tube's largest semi-axis + margin_mm (+ half a curve step) of its
    centerline: a superset of the voxels whose centre (margin = half a voxel diagonal) or any part
    (margin = a diagonal) is inside the tube."""
    reach = float(max(tube.a_v_mm.max(), tube.a_t_mm.max(), tube.cap_mm.max()))
    curve = _resample(tube.points_mm, step=float(spacing.max()))
    step = float(np.linalg.norm(curve[1] - curve[0]))
    offsets = _ellipsoid_offsets(reach + step / 2 + margin_mm, spacing)
    centre_idx = np.rint((curve - lo) / spacing).astype(int)
    base = centre_idx.min(axis=0) - offsets.max(axis=0)
    box = np.zeros(centre_idx.max(axis=0) + offsets.max(axis=0) - base + 1, dtype=bool)
    for chunk in np.array_split(
        np.arange(len(centre_idx)), max(1, len(centre_idx) * len(offsets) // 2_000_000)
    ):
        cand = (centre_idx[chunk] - base)[:, None, :] + offsets[None, :, :]
        box[cand[..., 0].ravel(), cand[..., 1].ravel(), cand[..., 2].ravel()] = True
    ijk = np.argwhere(box) + base
    return ijk[np.all((ijk >= 0) & (ijk < np.array(shape)), axis=1)]


PV_SUBSTEP_MM = 0.375  # partial volume: sub-sample spacing (at most), an odd count >= 3 per axis
PV_SAFETY = 0.7  # partial volume: factor on the distance bounds that skip whole voxels (curvature, taper)


def _subvoxel_offsets(spacing: np.ndarray) -> np.ndarray:
    """(K, 3) sub-sample positions (mm) relative to a voxel centre: a regular grid of an odd number
    (>= 3, <= PV_SUBSTEP_MM apart) of cell-centred points per axis (odd: a plane through the centre
    splits them unevenly, so "more than half" never ties)."""
    counts = [max(3, int(np.ceil(sp / PV_SUBSTEP_MM - 1e-9)) | 1) for sp in spacing]
    axes = [((np.arange(k) + 0.5) / k - 0.5) * sp for k, sp in zip(counts, spacing)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


def _inside_fractions(tube: Tube, centres_mm: np.ndarray, spacing: np.ndarray) -> np.ndarray:
    """(N,) fraction of the volume of each voxel (centres (N, 3) mm, size spacing (3,) mm) inside the
    tube's analytic solid, estimated on `_subvoxel_offsets` sub-samples.

    Voxels whose centre is provably more than half a diagonal from the surface are 1 or 0 outright
    (outside: level convexity gives distance >= (rho - 1) / |grad rho|; inside: the level is
    1 / min(semi-axis)-Lipschitz, distance >= (1 - rho) * min semi-axis; both times PV_SAFETY).
    The others are sub-sampled in the tube's local frame at the centre's foot point, linearised
    (the foot point slides along the tangent; curvature is neglected: < 0.03 mm at these offsets)."""
    loc = _tube_local(tube, centres_mm)
    v, w, t, av, at = loc["v"], loc["w"], loc["t"], loc["av"], loc["at"]
    rho2 = (v / av) ** 2 + (w / at) ** 2
    grad2 = (v / av**2) ** 2 + (w / at**2) ** 2
    a_min = np.minimum(av, at)
    for mask, c in ((loc["head"], tube.cap_mm[0]), (loc["tip"], tube.cap_mm[1])):
        rho2[mask] += (t[mask] / c) ** 2
        grad2[mask] += (t[mask] / c**2) ** 2
        a_min[mask] = np.minimum(a_min[mask], c)
    rho = np.sqrt(rho2)
    grad = np.sqrt(grad2) / np.maximum(rho, 1e-12)
    dist_lb = np.where(rho > 1.0, (rho - 1.0) / np.maximum(grad, 1e-12), (1.0 - rho) * a_min) * PV_SAFETY
    frac = (rho <= 1.0).astype(np.float64)
    band = np.nonzero(dist_lb <= 0.5 * float(np.linalg.norm(spacing)))[0]
    sub = _subvoxel_offsets(spacing)  # (K, 3)
    m = len(tube.points_mm)
    arc = np.arange(m) * tube.step_mm
    length = arc[-1]
    for chunk in np.array_split(band, max(1, len(band) * len(sub) // 4_000_000)):
        sv = v[chunk, None] + loc["ev"][chunk] @ sub.T  # (n, K) local coordinates of the sub-samples
        sw = w[chunk, None] + loc["et"][chunk] @ sub.T
        s_arc = (loc["fi"][chunk] * tube.step_mm + t[chunk])[:, None] + loc["tg"][chunk] @ sub.T
        s_in = np.clip(s_arc, 0.0, length)
        r2 = (sv / np.interp(s_in, arc, tube.a_v_mm)) ** 2 + (sw / np.interp(s_in, arc, tube.a_t_mm)) ** 2
        r2 += (np.maximum(s_arc - length, 0.0) / tube.cap_mm[1]) ** 2 + (
            np.maximum(-s_arc, 0.0) / tube.cap_mm[0]
        ) ** 2
        frac[chunk] = (r2 <= 1.0).mean(axis=1)
    return frac


def voxelize(
    phantom: Phantom,
    spacing_mm: float | tuple[float, float, float] = 1.0,
    padding_mm: float = 10.0,
    partial_volume: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Label volume of the phantom: (X, Y, Z) uint8 with the label_id of each rib / structure inside
    it, 0 elsewhere, and its voxel -> mm affine (4, 4) (diagonal = the voxel size, axes along +x,
    +y, +z). spacing_mm: one voxel size or (sx, sy, sz) mm, e.g. (0.75, 0.75, 2.5). The grid covers
    the mesh's bounding box plus padding_mm on every side.

    partial_volume=False: a voxel is set iff its centre lies inside the solid's analytic model
    (`tube_level` <= 1). True: iff more than half of its volume does (`_inside_fractions`,
    odd sub-sample grids <= 0.375 mm apart); where two solids claim a voxel the larger fraction wins."""
    spacing = _spacing_xyz(spacing_mm)
    if not padding_mm >= 0:
        raise RibPullInputError("bad_parameter", "spacing_mm must be > 0 and padding_mm >= 0")
    lo = phantom.mesh.bounds[0] - padding_mm
    hi = phantom.mesh.bounds[1] + padding_mm
    shape = tuple(int(k) for k in np.ceil((hi - lo) / spacing).astype(int) + 1)
    affine = np.diag([*spacing, 1.0])
    affine[:3, 3] = lo
    vol = np.zeros(shape, dtype=np.uint8)
    best = np.zeros(shape, dtype=np.float32) if partial_volume else None
    half_diag = 0.5 * float(np.linalg.norm(spacing))
    for solid in phantom.solids:
        margin = (2.0 if partial_volume else 1.0) * half_diag + 1e-6 * float(spacing.min())
        ijk = _candidate_voxels(solid.tube, lo, spacing, shape, margin)
        xyz = lo + ijk * spacing
        if not partial_volume:
            ijk = ijk[tube_level(solid, xyz) <= 1.0]
            vol[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = solid.label_id
            continue
        frac = _inside_fractions(solid.tube, xyz, spacing)
        keep = frac > 0.5
        ijk, frac = ijk[keep], frac[keep]
        wins = frac > best[ijk[:, 0], ijk[:, 1], ijk[:, 2]]
        ijk, frac = ijk[wins], frac[wins]
        vol[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = solid.label_id
        best[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = frac
    return vol, affine


def roughen_label_map(volume: np.ndarray, flip_fraction: float = 0.08, seed: int = 0,
                      correlation_voxels: float = 1.0) -> np.ndarray:
    """A copy of an (X, Y, Z) integer label volume with the boundary a real segmentation draws: a
    smooth random field (white noise under a Gaussian of correlation_voxels) flips
    about flip_fraction of the voxels on either side of the boundary (6-neighbourhood), in patches
    a voxel or two wide. Inside voxels where the field is high are cleared (dents); outside voxels
    where it is as low take a neighbour's label (bumps), as many of each.

    Why: a partial-volume map of the phantom (`voxelize`) is as clean as a label map can be; the
    real TotalSegmentator map in ../shared/data lies 0.95 mm (RMS) off smooth patches at 3 mm voxels,
    so `refine.plan_refinement` judges it too noisy for the patches, while the clean phantom at 3 mm
    is refined. Roughened 3 mm phantom maps (8 %: 0.57-0.58 mm RMS) take the same path, with a
    true surface to score against (benchmarks/noisy_label_map_ab.py)."""
    vol = np.asarray(volume)
    rng = np.random.default_rng(seed)
    noise = ndimage.gaussian_filter(rng.standard_normal(vol.shape), float(correlation_voxels))
    inside = vol > 0
    six = ndimage.generate_binary_structure(3, 1)
    inner_border = inside & ~ndimage.binary_erosion(inside, six)
    outer_border = ~inside & ndimage.binary_dilation(inside, six)
    threshold = np.quantile(noise[inner_border | outer_border], 1.0 - float(flip_fraction))
    dents, bumps = inner_border & (noise > threshold), outer_border & (noise < -threshold)
    out = vol.copy()
    out[dents] = 0
    out[bumps] = ndimage.grey_dilation(vol, footprint=six)[bumps]  # a neighbour's label
    return out


# ---------------------------------------------------------------------------------- writing


def centerlines_json(phantom: Phantom) -> dict:
    """{"units": "mm", "ribs": {name: {"label_id": int, "points": [[x, y, z], ...] (500)}}}."""
    return {
        "units": "mm",
        "ribs": {r.name: {"label_id": r.label_id, "points": r.centerline_mm.tolist()} for r in phantom.ribs},
    }


def write_phantom(
    outdir: str | Path,
    config: PhantomConfig | None = None,
    nifti: bool = False,
    spacing_mm: float | tuple[float, float, float] = 1.0,
    partial_volume: bool = False,
) -> dict[str, Path]:
    """Write a phantom to outdir: points.ply (config.n_points noisy samples with normals and labels),
    truth_mesh.ply (ribs, then sternum and cartilages with config.sternum), centerlines.json (ribs)
    and, when nifti, mask.nii.gz (uint8 labels; voxels of spacing_mm, one size or (sx, sy, sz) mm;
    `voxelize` with partial_volume). Returns {"points", "truth_mesh", "centerlines"[, "mask"]} -> path."""
    config = config or PhantomConfig()
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    phantom = make_phantom(config)
    cloud = sample_surface(phantom, config.n_points, config.noise_mm, seed=config.seed)
    paths = {
        "points": outdir / "points.ply",
        "truth_mesh": outdir / "truth_mesh.ply",
        "centerlines": outdir / "centerlines.json",
    }
    try:
        from .io import write_point_cloud
    except ImportError:  # pragma: no cover - io.py is optional for this module
        write_point_cloud = None
    if write_point_cloud is not None:
        write_point_cloud(paths["points"], cloud)
    else:  # pragma: no cover
        trimesh.PointCloud(cloud.points).export(paths["points"])
    phantom.mesh.export(paths["truth_mesh"])
    paths["centerlines"].write_text(json.dumps(centerlines_json(phantom)))
    if nifti:
        import nibabel as nib

        vol, affine = voxelize(phantom, spacing_mm=spacing_mm, partial_volume=partial_volume)
        img = nib.Nifti1Image(vol, affine)
        img.set_qform(affine, code=1)
        img.set_sform(affine, code=1)
        paths["mask"] = outdir / "mask.nii.gz"
        nib.save(img, paths["mask"])
    return paths


def timing_report(config: PhantomConfig | None = None) -> dict[str, float]:
    """Seconds for make_phantom, sample_surface(60k) and voxelize(1 mm) (for benchmarks/reports)."""
    t0 = time.perf_counter()
    ph = make_phantom(config)
    t1 = time.perf_counter()
    sample_surface(ph, 60_000, 0.3, 0)
    t2 = time.perf_counter()
    voxelize(ph, 1.0)
    t3 = time.perf_counter()
    return {"make_phantom": t1 - t0, "sample_surface": t2 - t1, "voxelize": t3 - t2}
