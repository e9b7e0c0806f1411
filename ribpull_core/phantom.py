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
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh
from scipy.interpolate import CubicSpline
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


@dataclass
class PhantomConfig:
    """Parameters of a synthetic ribcage.

    seed: anatomical variation (global width/depth/height/tilt +-5 %, per rib +-2 %).
    n_points: surface samples in the point cloud written by `write_phantom`.
    noise_mm: isotropic Gaussian noise std (mm, per axis) on those samples.
    missing_ribs: names ("L11", "R3", ...) of ribs left out, in the output's naming.
    mirror: x -> -x; a rib that lands at x > 0 is named R (so names stay anatomically correct).
    scale: uniform size factor applied to everything (cross-sections included).
    """

    seed: int = 0
    n_points: int = 60_000
    noise_mm: float = 0.3
    missing_ribs: tuple[str, ...] = ()
    mirror: bool = False
    scale: float = 1.0


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
class Phantom:
    """A ribcage: the config it came from, its ribs (order L1..L12, R1..R12, missing ones left
    out) and all rib meshes concatenated in that order (one connected component per rib)."""

    config: PhantomConfig
    ribs: list[Rib]
    mesh: trimesh.Trimesh

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
        return np.repeat(
            np.array([r.label_id for r in self.ribs], dtype=np.int32), [len(r.mesh.faces) for r in self.ribs]
        )

    def label_names(self) -> dict[int, str]:
        """label_id -> TotalSegmentator name ("rib_left_7") for the ribs present."""
        return {r.label_id: rib_label_name(r.side, r.number) for r in self.ribs}


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


def tube_level(rib: Rib, points_mm: np.ndarray) -> np.ndarray:
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


def tube_normals(rib: Rib, points_mm: np.ndarray) -> np.ndarray:
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


# ---------------------------------------------------------------------------------- phantom


def make_phantom(config: PhantomConfig | None = None) -> Phantom:
    """Build the ribcage for `config` (defaults: seed 0, 24 ribs, scale 1). Deterministic."""
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
    for out_side in ("L", "R"):
        for n in range(1, 13):
            name = f"{out_side}{n}"
            if name in config.missing_ribs:
                continue
            src_side = out_side if not config.mirror else ("R" if out_side == "L" else "L")
            fine, e0 = built[(src_side, n)]
            fine = (fine + shift) * flip * config.scale
            tube = _build_tube(fine, e0 * flip, config.scale)
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
    mesh = trimesh.util.concatenate([r.mesh for r in ribs])
    return Phantom(config=config, ribs=ribs, mesh=mesh)


def sample_surface(phantom: Phantom, n_points: int, noise_mm: float = 0.3, seed: int = 0) -> PointCloud:
    """PointCloud of n_points (N, 3) mm samples uniform by area on the true surface (the truth
    mesh), plus isotropic Gaussian noise of std noise_mm per axis. normals (N, 3): outward normals
    of the analytic rib surface at the noise-free samples (`tube_normals`); labels (N,): label_id
    of the rib sampled. The same seed gives the same samples whatever noise_mm is."""
    if int(n_points) < 1 or not noise_mm >= 0:
        raise RibPullInputError("bad_parameter", "n_points must be >= 1 and noise_mm >= 0")
    rng = np.random.default_rng(seed)
    pts, face = trimesh.sample.sample_surface(phantom.mesh, int(n_points), seed=rng)
    labels = phantom.face_labels()[face]
    normals = np.empty_like(pts)
    for rib in phantom.ribs:
        sel = labels == rib.label_id
        if sel.any():
            normals[sel] = tube_normals(rib, pts[sel])
    noisy = pts + rng.normal(0.0, 1.0, pts.shape) * float(noise_mm)
    return PointCloud(
        points=noisy,
        normals=normals,
        labels=labels,
        source_format="phantom",
        label_names=phantom.label_names(),
    )


def _ball_offsets(radius: float) -> np.ndarray:
    """(K, 3) integer offsets within `radius` (voxel units) of the origin."""
    r = int(np.ceil(radius))
    g = np.mgrid[-r : r + 1, -r : r + 1, -r : r + 1].reshape(3, -1).T
    return g[(g**2).sum(axis=1) <= radius * radius]


def voxelize(
    phantom: Phantom, spacing_mm: float = 1.0, padding_mm: float = 10.0
) -> tuple[np.ndarray, np.ndarray]:
    """Label volume of the phantom: (X, Y, Z) uint8 with label_id inside each rib, 0 elsewhere, and
    its voxel -> mm affine (4, 4) (diagonal spacing_mm, axes along +x, +y, +z). A voxel is set iff
    its centre lies inside the rib's analytic solid (`tube_level` <= 1). The grid covers the
    mesh's bounding box plus padding_mm on every side."""
    if not (spacing_mm > 0 and padding_mm >= 0):
        raise RibPullInputError("bad_parameter", "spacing_mm must be > 0 and padding_mm >= 0")
    lo = phantom.mesh.bounds[0] - padding_mm
    hi = phantom.mesh.bounds[1] + padding_mm
    shape = tuple(int(k) for k in np.ceil((hi - lo) / spacing_mm).astype(int) + 1)
    affine = np.diag([spacing_mm, spacing_mm, spacing_mm, 1.0])
    affine[:3, 3] = lo
    vol = np.zeros(shape, dtype=np.uint8)
    for rib in phantom.ribs:
        tube = rib.tube
        reach = float(max(tube.a_v_mm.max(), tube.a_t_mm.max(), tube.cap_mm.max()))
        curve = _resample(tube.points_mm, step=spacing_mm)
        step = float(np.linalg.norm(curve[1] - curve[0]))
        offsets = _ball_offsets((reach + step / 2) / spacing_mm + np.sqrt(3) / 2 + 1e-6)
        centre_idx = np.rint((curve - lo) / spacing_mm).astype(int)
        base = centre_idx.min(axis=0) - offsets.max()
        box_shape = centre_idx.max(axis=0) + offsets.max() - base + 1
        box = np.zeros(box_shape, dtype=bool)
        cand = (centre_idx - base)[:, None, :] + offsets[None, :, :]
        box[cand[..., 0].ravel(), cand[..., 1].ravel(), cand[..., 2].ravel()] = True
        ijk = np.argwhere(box) + base
        ijk = ijk[np.all((ijk >= 0) & (ijk < np.array(shape)), axis=1)]
        inside = tube_level(rib, lo + ijk * spacing_mm) <= 1.0
        ijk = ijk[inside]
        vol[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = rib.label_id
    return vol, affine


# ---------------------------------------------------------------------------------- writing


def centerlines_json(phantom: Phantom) -> dict:
    """{"units": "mm", "ribs": {name: {"label_id": int, "points": [[x, y, z], ...] (500)}}}."""
    return {
        "units": "mm",
        "ribs": {r.name: {"label_id": r.label_id, "points": r.centerline_mm.tolist()} for r in phantom.ribs},
    }


def write_phantom(
    outdir: str | Path, config: PhantomConfig | None = None, nifti: bool = False, spacing_mm: float = 1.0
) -> dict[str, Path]:
    """Write a phantom to outdir: points.ply (config.n_points noisy samples with normals and labels),
    truth_mesh.ply, centerlines.json and, when nifti, mask.nii.gz (uint8 labels, spacing_mm voxels).
    Returns {"points", "truth_mesh", "centerlines"[, "mask"]} -> path."""
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

        vol, affine = voxelize(phantom, spacing_mm=spacing_mm)
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
