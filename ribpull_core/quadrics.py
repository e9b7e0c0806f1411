"""Local quadric surface patches of a point cloud (second-order moving least squares).

Every input point gets a height field w(u, v) = a0 + a1 u + a2 v + a3 u^2 + a4 uv + a5 v^2 fitted by
Gaussian-weighted least squares to its k nearest neighbours, in the frame (e1, e2, n) of their
principal axes (n: the least-variance axis), centred on their centroid. Projecting a query onto
the patch of its nearest input point gives a point of a smooth local surface instead of a discrete
sample: as eq. 1's pull targets these lie between the samples (the field is not pulled into bumps
one sampling gap apart) and average the sample noise over k neighbours.

Units are those of the points (RibPull calls this in the unit frame).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, prange
from scipy.spatial import cKDTree

#: coefficients of a patch's height field (a0..a5): a least-squares fit of k points keeps (k - 6) / k
#: of the sample noise's variance in its residuals (curvature_bias.normal_noise_mm)
HEIGHT_FIELD_TERMS = 6


@dataclass
class LocalQuadrics:
    """Per-point patches. centre (N, 3): neighbourhood centroid; frame (N, 3, 3): rows e1, e2, n;
    coef (N, 6): height-field coefficients (a0..a5 above); radius (N,): distance to the k-th
    neighbour (the patch's extent); residual (N,): weighted RMS distance of the neighbours from the
    fitted height field (sample noise on a smooth sheet; a large fraction of `radius` where the
    neighbourhood is no height field: around a thin tube, across two sheets); one_sided (N,) bool:
    every neighbour's oriented normal faces the point's way (all True when no normals were given);
    facing (N,): the fraction of the neighbours whose normal does (1 without normals).
    """

    centre: np.ndarray
    frame: np.ndarray
    coef: np.ndarray
    radius: np.ndarray
    residual: np.ndarray
    one_sided: np.ndarray
    facing: np.ndarray


def _monomials(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(...) u, v -> (..., HEIGHT_FIELD_TERMS) the height field's basis 1, u, v, u^2, uv, v^2."""
    return np.stack([np.ones_like(u), u, v, u * u, u * v, v * v], axis=-1)


def pca_normals(points: np.ndarray, k: int = 16, tree: cKDTree | None = None) -> np.ndarray:
    """(N, 3) points -> (N, 3) unit normals, unoriented: the least eigenvector of the covariance of
    each point's k nearest neighbours (itself included). tree: a kd-tree of `points` to reuse."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    tree = tree if tree is not None else cKDTree(points)
    k = min(int(k), len(points))
    nn = tree.query(points, k=k, workers=-1)[1].reshape(len(points), k)
    return _least_axes(points, np.ascontiguousarray(nn, dtype=np.int64))


@njit(parallel=True, cache=True)
def _least_axes(points, nn):  # pragma: no cover - compiled
    """(N, 3) float64 least eigenvector (LAPACK's, as np.linalg.eigh) of the covariance of each
    point's neighbours points[nn[i]] (nn (N, k) int64). One pass per point instead of numpy's
    (N, k, 3) centred copies and batched eigh: a label map's 120k boundary points at k = 16
    0.43-0.73 -> 0.20 s, the same axes to 2e-15 with the same signs."""
    out = np.empty((nn.shape[0], 3))
    for q in prange(nn.shape[0]):
        out[q] = np.linalg.eigh(_centroid_and_scatter(points, nn[q])[1])[1][:, 0]
    return out


@njit(inline="always")
def _centroid_and_scatter(points, idx):  # pragma: no cover - compiled
    """((3,) centroid, (3, 3) scatter sum (x - c)(x - c)^T) of the points points[idx], float64."""
    c = np.zeros(3)
    for t in range(idx.shape[0]):
        c += points[idx[t]]
    c /= idx.shape[0]
    cov = np.zeros((3, 3))
    for t in range(idx.shape[0]):
        x = points[idx[t]] - c
        for a in range(3):
            for b in range(a, 3):
                cov[a, b] += x[a] * x[b]
    cov[1, 0], cov[2, 0], cov[2, 1] = cov[0, 1], cov[0, 2], cov[1, 2]
    return c, cov


def fit_local_quadrics(points: np.ndarray, k: int = 20,
                       normals: np.ndarray | None = None, tree: cKDTree | None = None,
                       at: np.ndarray | None = None, point_weights: np.ndarray | None = None) -> LocalQuadrics:
    """(N, 3) points -> one quadric patch per point over its k nearest neighbours (itself included).
    at: optional (M,) indices of the points to fit patches at (default: every point); the result
    then has M patches.

    normals: optional (N, 3) consistently oriented normals; a patch is `one_sided` when all its
    neighbours' normals have a positive dot product with its point's (no sample from the far side
    of a thin structure is in it); `facing` keeps the fraction that do.

    Weights exp(-(u^2 + v^2) / r^2), r the distance to the k-th neighbour, favour the near samples
    (times point_weights (N,) of the neighbours when given: how much each sample says about the
    height of the surface, e.g. `refine.terrace_weights`); a tiny ridge keeps degenerate neighbourhoods (collinear samples) solvable.
    tree: a kd-tree of `points` to reuse."""
    pts = np.ascontiguousarray(points, dtype=np.float64)
    at = np.arange(len(pts)) if at is None else np.asarray(at)
    n = len(at)
    k = int(min(max(k, HEIGHT_FIELD_TERMS), len(pts)))
    dist, nn = (tree if tree is not None else cKDTree(pts)).query(pts[at], k=k, workers=-1)
    dist, nn = dist.reshape(n, k), np.ascontiguousarray(nn.reshape(n, k), dtype=np.int64)
    weights = np.ones(0) if point_weights is None else np.ascontiguousarray(point_weights, dtype=np.float64)
    centre, frame, coef, residual = _height_fields(pts, nn, np.ascontiguousarray(dist[:, -1]), weights)
    one_sided, facing = np.ones(n, bool), np.ones(n)
    if normals is not None:
        nrm = np.asarray(normals, dtype=np.float64)
        facing = (np.matmul(nrm[nn], nrm[at][..., None])[..., 0] > 0.0).mean(axis=1)
        one_sided = facing >= 1.0
    return LocalQuadrics(centre, frame, coef, dist[:, -1].copy(), residual, one_sided, facing)


@njit(parallel=True, cache=True)
def _height_fields(pts, nn, radius, point_weights):  # pragma: no cover - compiled
    """`fit_local_quadrics`' fit, one neighbourhood (pts[nn[i]], (N, k) int64) at a time: the
    centroid, the frame (rows e1, e2, n: the covariance's eigenvectors by descending eigenvalue,
    LAPACK's as np.linalg.eigh), the weighted height-field coefficients (weights exp(-(u^2 + v^2)
    / radius^2) x point_weights of the neighbours when that (N,) array is not empty, ridge 1e-10
    radius^2) and the weighted RMS residual. Replaced the batched numpy fit and its (chunk, k, 6)
    temporaries (the same patches to ~1e-12 relative: sums in another order): a label map's 105k
    boundary points at k = 32 ~1.6 -> ~0.3 s."""
    n, k = nn.shape
    centre = np.empty((n, 3))
    frame = np.empty((n, 3, 3))
    coef = np.empty((n, 6))
    residual = np.empty(n)
    weighted = point_weights.shape[0] > 0
    for i in prange(n):
        c, cov = _centroid_and_scatter(pts, nn[i])
        vecs = np.linalg.eigh(cov)[1]
        rot = np.empty((3, 3))
        for a in range(3):  # rows: largest (e1), middle (e2), least (n)
            rot[0, a], rot[1, a], rot[2, a] = vecs[a, 2], vecs[a, 1], vecs[a, 0]
        r2 = max(radius[i] * radius[i], 1e-18)
        ata = np.zeros((6, 6))
        atb = np.zeros(6)
        row = np.empty(6)
        u = np.empty(k)
        v = np.empty(k)
        w = np.empty(k)
        wt = np.empty(k)
        for t in range(k):
            x = pts[nn[i, t]] - c
            u[t] = x[0] * rot[0, 0] + x[1] * rot[0, 1] + x[2] * rot[0, 2]
            v[t] = x[0] * rot[1, 0] + x[1] * rot[1, 1] + x[2] * rot[1, 2]
            w[t] = x[0] * rot[2, 0] + x[1] * rot[2, 1] + x[2] * rot[2, 2]
            wt[t] = np.exp(-(u[t] * u[t] + v[t] * v[t]) / r2)
            if weighted:
                wt[t] *= point_weights[nn[i, t]]
            row[0], row[1], row[2], row[3], row[4], row[5] = 1.0, u[t], v[t], u[t] * u[t], u[t] * v[t], v[t] * v[t]
            for a in range(6):
                atb[a] += wt[t] * row[a] * w[t]
                for b in range(6):
                    ata[a, b] += wt[t] * row[a] * row[b]
        for a in range(6):
            ata[a, a] += 1e-10 * r2
        sol = np.linalg.solve(ata, atb)
        num = 0.0
        den = 0.0
        for t in range(k):
            h = sol[0] + sol[1] * u[t] + sol[2] * v[t] + sol[3] * u[t] * u[t] + sol[4] * u[t] * v[t] + sol[5] * v[t] * v[t]
            e = w[t] - h
            num += wt[t] * e * e
            den += wt[t]
        centre[i], frame[i], coef[i], residual[i] = c, rot, sol, np.sqrt(num / den)
    return centre, frame, coef, residual


def project_onto_quadrics(queries: np.ndarray, nearest: np.ndarray, quadrics: LocalQuadrics,
                          fallback: np.ndarray | None = None, max_shift: float | None = None,
                          max_relative_residual: float | None = None) -> np.ndarray:
    """(Q, 3) queries, (Q,) index of each query's nearest input point -> (Q, 3) the point of that
    point's patch above or below the query (along the patch normal).

    With `fallback` (Q, 3) (e.g. the nearest samples themselves) and `max_shift`, a projection that
    lands farther than max_shift from its fallback point, comes from a patch that is not one-sided,
    or from a patch whose residual
    exceeds max_relative_residual x its radius (a patch that does not describe the surface there:
    two sheets in one neighbourhood, a tube thinner than the patch), is replaced by the fallback."""
    q = np.asarray(queries, dtype=np.float64)
    c, rot, a = quadrics.centre[nearest], quadrics.frame[nearest], quadrics.coef[nearest]
    loc = np.einsum("nj,nij->ni", q - c, rot)
    u, v = loc[:, 0], loc[:, 1]
    w = np.einsum("ni,ni->n", _monomials(u, v), a)
    out = c + u[:, None] * rot[:, 0] + v[:, None] * rot[:, 1] + w[:, None] * rot[:, 2]
    if fallback is not None:
        bad = ~quadrics.one_sided[nearest]
        if max_shift is not None:
            bad |= np.linalg.norm(out - fallback, axis=1) > max_shift
        if max_relative_residual is not None:
            bad |= quadrics.residual[nearest] > max_relative_residual * quadrics.radius[nearest]
        out[bad] = np.asarray(fallback, dtype=np.float64)[bad]
    return out


def project_onto_blended_quadrics(queries: np.ndarray, quadrics: LocalQuadrics, tree: cKDTree,
                                  blend: int = 8, chunk: int = 65_536) -> np.ndarray:
    """(Q, 3) queries -> (Q, 3) moving-least-squares points: each query is projected onto the patches
    of its `blend` nearest input points (along each patch's normal) and the projections are averaged
    with weights exp(-(d / r)^2) (d: the query's distance to that point, r: its patch radius).

    Blending several patches makes the result continuous as a query moves from one nearest point
    to the next (a single patch per query would leave steps one sampling gap apart). tree: the
    kd-tree of the points the patches were fitted to. `chunk` queries at a time bound the memory.
    Units are those of the points."""
    q = np.ascontiguousarray(queries, dtype=np.float64)
    blend = int(max(1, min(blend, len(quadrics.centre))))
    frame = np.ascontiguousarray(quadrics.frame, dtype=np.float64)
    centre = np.ascontiguousarray(quadrics.centre, dtype=np.float64)
    coef = np.ascontiguousarray(quadrics.coef, dtype=np.float64)
    radius = np.asarray(quadrics.radius, dtype=np.float64)
    out = np.empty_like(q)
    for s in range(0, len(q), chunk):
        qc = q[s:s + chunk]
        dist, nn = tree.query(qc, k=blend, workers=-1)
        dist, nn = dist.reshape(len(qc), blend), np.ascontiguousarray(nn.reshape(len(qc), blend))
        # numpy's exp (its own vectorised one: the kernel's would differ in the last bit)
        weight = np.exp(-(dist / np.maximum(radius[nn], 1e-12)) ** 2)
        out[s:s + chunk] = _blend_projections(qc, weight, nn, centre, frame, coef)
    return out


@njit(parallel=True, cache=True)
def _blend_projections(queries, weight, nn, centre, frame, coef):  # pragma: no cover - compiled
    """`project_onto_blended_quadrics` for one chunk: (c, 3) queries, the (c, b) weights of and
    indices of their b nearest points -> (c, 3) blended projections. One pass per query instead of
    numpy's (c, b, 6) temporaries (the sternum map's 210k-vertex mesh: 0.49 -> 0.23 s with the kd
    query), each sum in the order numpy's reductions and einsum take here (`_numpy_order_sum` for
    the weights): the numpy formula's numbers bit for bit on this machine, within 1e-13 anywhere."""
    n_query, n_blend = nn.shape
    out = np.empty((n_query, 3))
    for i in prange(n_query):
        acc0, acc1, acc2 = 0.0, 0.0, 0.0
        for j in range(n_blend):
            p = nn[i, j]
            dx = queries[i, 0] - centre[p, 0]
            dy = queries[i, 1] - centre[p, 1]
            dz = queries[i, 2] - centre[p, 2]
            u = dx * frame[p, 0, 0] + dy * frame[p, 0, 1] + dz * frame[p, 0, 2]
            v = dx * frame[p, 1, 0] + dy * frame[p, 1, 1] + dz * frame[p, 1, 2]
            nx, ny, nz = frame[p, 2, 0], frame[p, 2, 1], frame[p, 2, 2]
            # numpy's einsum over the 6 terms sums the even and the odd ones apart, then adds them
            height = ((coef[p, 0] + v * coef[p, 2]) + (u * v) * coef[p, 4]) \
                + ((u * coef[p, 1] + (u * u) * coef[p, 3]) + (v * v) * coef[p, 5])
            step = height - (dx * nx + dy * ny + dz * nz)  # along the patch's normal, to the patch
            w = weight[i, j]
            acc0 += w * step * nx
            acc1 += w * step * ny
            acc2 += w * step * nz
        wsum = max(_numpy_order_sum(weight[i]), 1e-300)
        out[i, 0] = queries[i, 0] + acc0 / wsum
        out[i, 1] = queries[i, 1] + acc1 / wsum
        out[i, 2] = queries[i, 2] + acc2 / wsum
    return out


@njit(inline="always")
def _numpy_order_sum(a):  # pragma: no cover - compiled
    """The sum of a 1-d float64 array of at most 128 values in the order numpy's sum takes: in
    order below 8 values, else eight running sums combined pairwise, then the rest in order."""
    n = a.shape[0]
    if n < 8:
        res = 0.0
        for i in range(n):
            res += a[i]
        return res
    r0, r1, r2, r3, r4, r5, r6, r7 = a[0], a[1], a[2], a[3], a[4], a[5], a[6], a[7]
    i = 8
    while i + 8 <= n:
        r0 += a[i]
        r1 += a[i + 1]
        r2 += a[i + 2]
        r3 += a[i + 3]
        r4 += a[i + 4]
        r5 += a[i + 5]
        r6 += a[i + 6]
        r7 += a[i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[i]
        i += 1
    return res
