"""Compiled CPU kernel (numba) for `sdf.SurfaceDistance`'s closest-point grid: one relaxation step.

A step along one axis and direction lets every node take its neighbour's stored closest point
when that point is nearer to the node, each node reading its neighbour's point from before the
step (float32 arithmetic). One loop instead of the whole-array numpy step's dozen full-volume
temporaries it replaced (the same grid bit for bit): the 1.5 mm label map's 5.1M-node grid's 12
steps ~1 s -> ~0.1 s.
"""

from __future__ import annotations

from numba import njit, prange


@njit(inline="always")
def _take_if_nearer(cp, best, ax0, ax1, ax2, i, j, k, si, sj, sk):  # pragma: no cover - compiled
    """Node (i, j, k) takes the closest point stored at (si, sj, sk) when that is nearer to it."""
    c0, c1, c2 = cp[0, si, sj, sk], cp[1, si, sj, sk], cp[2, si, sj, sk]
    d = (ax0[i] - c0) ** 2
    d += (ax1[j] - c1) ** 2
    d += (ax2[k] - c2) ** 2
    if d < best[i, j, k]:
        best[i, j, k] = d
        cp[0, i, j, k], cp[1, i, j, k], cp[2, i, j, k] = c0, c1, c2


@njit(parallel=True, cache=True)
def relax_step(cp, best, ax0, ax1, ax2, axis, step):  # pragma: no cover - compiled
    """One relaxation step in place: every node n takes the point of node n + step along `axis`
    (0, 1, 2; step +1 or -1) when nearer. cp (3, n0, n1, n2) float32 closest points (mm), best
    (n0, n1, n2) float32 squared distances (mm^2), ax0..ax2 float32 node coordinates (mm). The
    nodes are visited against the step's direction along `axis`, so each reads its neighbour
    before that neighbour is updated (what a whole-array step does), and in parallel across
    another axis."""
    n0, n1, n2 = best.shape
    if axis == 0:
        for j in prange(n1):
            for t in range(n0 - 1):
                i = t if step > 0 else n0 - 1 - t
                for k in range(n2):
                    _take_if_nearer(cp, best, ax0, ax1, ax2, i, j, k, i + step, j, k)
    else:
        for i in prange(n0):
            if axis == 1:
                for t in range(n1 - 1):
                    j = t if step > 0 else n1 - 1 - t
                    for k in range(n2):
                        _take_if_nearer(cp, best, ax0, ax1, ax2, i, j, k, i, j + step, k)
            else:
                for j in range(n1):
                    for t in range(n2 - 1):
                        k = t if step > 0 else n2 - 1 - t
                        _take_if_nearer(cp, best, ax0, ax1, ax2, i, j, k, i, j, k + step)
