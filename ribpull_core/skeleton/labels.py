"""Rib names for skeleton curves: from input labels when there are any, else from geometry.

Frame assumption for geometric naming: NIfTI/nibabel RAS+ mm by default (+x = patient's right,
+y = anterior, +z = superior), as real label maps read through their affine and the phantom;
`left_is_positive_x=True` flips the side rule. Names are "L1".."L12" / "R1".."R12".
"""

from __future__ import annotations

import re

import numpy as np

#: TotalSegmentator rib ids: 92..103 = left ribs 1..12, 104..115 = right ribs 1..12
TOTALSEG_LEFT_FIRST = 92
TOTALSEG_RIGHT_FIRST = 104


def totalseg_rib_name(label_id: int) -> str | None:
    """TotalSegmentator id -> "L7" style name (98 -> "L7", 110 -> "R7"), None outside 92..115."""
    i = int(label_id)
    if TOTALSEG_LEFT_FIRST <= i < TOTALSEG_LEFT_FIRST + 12:
        return f"L{i - TOTALSEG_LEFT_FIRST + 1}"
    if TOTALSEG_RIGHT_FIRST <= i < TOTALSEG_RIGHT_FIRST + 12:
        return f"R{i - TOTALSEG_RIGHT_FIRST + 1}"
    return None


def normalise_rib_name(name: str) -> str | None:
    """A rib class name -> "L7" style, or None if it names no rib side and number.

    Accepts "rib_left_7", "rib_right_12", "left rib 7", "L7", "r12" (case-insensitive).
    """
    s = name.strip().lower()
    m = re.fullmatch(r"([lr])\s*0*(\d{1,2})", s)
    if m:
        return f"{m.group(1).upper()}{int(m.group(2))}"
    side = "L" if re.search(r"left", s) else "R" if re.search(r"right", s) else None
    num = re.search(r"(\d{1,2})", s)
    if side and num and ("rib" in s or re.fullmatch(r"(left|right)[\s_-]*\d{1,2}", s)):
        return f"{side}{int(num.group(1))}"
    return None


def label_name(label_id: int, label_names: dict[int, str] | None) -> str:
    """Curve name for an input label value: the label's own name normalised to "L7" when it names a
    rib (else the raw name), TotalSegmentator's convention when no name is given, else "label_<id>"."""
    if label_names and int(label_id) in label_names:
        raw = str(label_names[int(label_id)])
        return normalise_rib_name(raw) or raw
    return totalseg_rib_name(label_id) or f"label_{int(label_id)}"


def majority_label(values: np.ndarray) -> tuple[int | None, float]:
    """(most frequent label value, its fraction) of an int array; (None, 0) when empty."""
    v = np.asarray(values).astype(np.int64).ravel()
    if len(v) == 0:
        return None, 0.0
    ids, counts = np.unique(v, return_counts=True)
    k = int(np.argmax(counts))
    return int(ids[k]), float(counts[k] / len(v))


def head_end_score(point_mm: np.ndarray, mid_x_mm: float) -> float:
    """Lower = more likely a rib head: posterior (small y) and medial (small |x - mid|), mm."""
    return float(point_mm[1] + abs(point_mm[0] - mid_x_mm))


def orient_head_first(poly_mm: np.ndarray, mid_x_mm: float) -> bool:
    """True when the polyline (m, 3) should be reversed so that it runs head -> tip."""
    return head_end_score(poly_mm[-1], mid_x_mm) < head_end_score(poly_mm[0], mid_x_mm)


def number_by_height(head_z_mm: np.ndarray, spacing_mm: float, max_skip: int = 2) -> np.ndarray:
    """(n,) rib numbers for one side's heads z (any order): 1 for the highest head; a gap between
    consecutive heads of about k x spacing_mm skips k - 1 numbers (a missing rib in between), at
    most `max_skip` numbers per gap."""
    z = np.asarray(head_z_mm, dtype=np.float64)
    order = np.argsort(-z)
    nums = np.empty(len(z), dtype=np.int64)
    if len(z) == 0:
        return nums
    gaps = -np.diff(z[order])
    steps = np.clip(np.rint(gaps / max(spacing_mm, 1e-6)).astype(np.int64), 1, 1 + max_skip)
    nums[order] = 1 + np.concatenate([[0], np.cumsum(steps)])
    return nums


def geometric_labels(
    polys_mm: list[np.ndarray], mid_x_mm: float, left_is_positive_x: bool = False,
    min_spacing_mm: float = 12.0,
) -> list[str]:
    """Names for head-first curves from geometry alone.

    Side: mean x of the curve vs the mid-sagittal x; the patient's left is at -x (NIfTI RAS+, the
    default) or at +x when left_is_positive_x.
    Number: rank of the head (first node) height per side, top = 1, where a head gap of about k
    typical spacings skips k - 1 numbers (a missing rib), and a side whose top head sits about k
    spacings below the other side's top head starts at k + 1 (a missing first rib on one side).
    The typical spacing is the median gap between consecutive heads of a side (at least
    min_spacing_mm). If that would number past 12, plain ranks are used.

    Limitations: ribs missing at the top of BOTH sides (or a crop that starts below rib 1) shift
    every number; several ribs missing in a row next to irregular spacing can be miscounted;
    curves whose head is cut off (crops) rank by their highest remaining end. Use labels then.
    """
    if not polys_mm:
        return []
    left = np.array([(p[:, 0].mean() > mid_x_mm) == left_is_positive_x for p in polys_mm])
    side = np.where(left, "L", "R")
    head_z = np.array([p[0, 2] for p in polys_mm])
    gaps = []
    for sd in ("L", "R"):
        z = np.sort(head_z[side == sd])[::-1]
        gaps.extend((-np.diff(z)).tolist())
    gaps = np.asarray(gaps)
    spacing = max(float(np.median(gaps)) if len(gaps) else 20.0, min_spacing_mm)
    numbers = np.zeros(len(polys_mm), dtype=np.int64)
    ranks = np.zeros(len(polys_mm), dtype=np.int64)
    tops = {}
    for sd in ("L", "R"):
        idx = np.flatnonzero(side == sd)
        if len(idx):
            numbers[idx] = number_by_height(head_z[idx], spacing)
            ranks[idx] = number_by_height(head_z[idx], np.inf)
            tops[sd] = head_z[idx].max()
    if len(tops) == 2:
        top = max(tops.values())
        for sd, zt in tops.items():
            k = int(np.rint((top - zt) / spacing))
            if k > 0:
                numbers[side == sd] += k
    if numbers.max() > 12:
        numbers = ranks
    return [f"{s}{int(n)}" for s, n in zip(side, numbers)]
