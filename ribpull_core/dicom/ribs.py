"""Rib names and their coded concepts (SNOMED CT), shared by the SEG reader and the writers.

A rib is named "L1".."L12" / "R1".."R12" (the skeleton's names). Its SEG segment carries category
Anatomical Structure (SCT 91723000), type Rib (SCT 113197003) and its side, Left (SCT 7771000) or
Right (SCT 24028007), as the segment's anatomic region; the segment label is the name and the
tracking id TotalSegmentator's class name ("rib_left_7"), so other tools map it back.
"""

from __future__ import annotations

import re

from pydicom.sr.codedict import codes

from ..skeleton.labels import normalise_rib_name

RIB_CODE = codes.SCT.Rib
CATEGORY_CODE = codes.SCT.AnatomicalStructure
LEFT_CODE = codes.SCT.Left
RIGHT_CODE = codes.SCT.Right

#: "L1".."L12", "R1".."R12" in segment-number order (segment n = RIB_NAMES[n - 1])
RIB_NAMES: tuple[str, ...] = tuple(f"L{i}" for i in range(1, 13)) + tuple(f"R{i}" for i in range(1, 13))

_NAME_RE = re.compile(r"^([LR])(\d{1,2})$")


def rib_side_number(name: str) -> tuple[str, int] | None:
    """("L", 7) for "L7" (or any name normalise_rib_name understands, e.g. "rib_left_7"); else None."""
    norm = normalise_rib_name(str(name))
    m = _NAME_RE.match(norm or "")
    if not m or not 1 <= int(m.group(2)) <= 12:
        return None
    return m.group(1), int(m.group(2))


def rib_name(name: str) -> str:
    """"rib_left_7" (or "L7", "left rib 7") -> "L7"; names that are no rib come back as is."""
    sn = rib_side_number(name)
    return str(name) if sn is None else f"{sn[0]}{sn[1]}"


def totalseg_class_name(name: str) -> str:
    """"L7" -> "rib_left_7" (TotalSegmentator's class name); names that are no rib come back as is."""
    sn = rib_side_number(name)
    if sn is None:
        return str(name)
    return f"rib_{'left' if sn[0] == 'L' else 'right'}_{sn[1]}"


def rib_segment_number(name: str) -> int | None:
    """Segment number of a rib in RibPull's SEG: L1..L12 -> 1..12, R1..R12 -> 13..24."""
    sn = rib_side_number(name)
    if sn is None:
        return None
    return sn[1] + (0 if sn[0] == "L" else 12)


def laterality_code(name: str):
    """The SNOMED CT Left / Right code of a rib name, or None."""
    sn = rib_side_number(name)
    if sn is None:
        return None
    return LEFT_CODE if sn[0] == "L" else RIGHT_CODE
