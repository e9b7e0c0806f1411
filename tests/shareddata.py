"""The project's shared real data (../shared/data, see its README) for the tests that use it.

It sits next to the checkout on the dev machine (<checkout>/../shared/data); a clean clone made
elsewhere (CI clones into a temporary directory) finds it at /work/shared/data; RIBPULL_SHARED_DATA
names another folder. Tests skip, naming the path, when the file is in none of them.
"""

from __future__ import annotations

import os
from pathlib import Path


def shared_data_file(name: str) -> Path:
    """The first existing <folder>/<name> of: $RIBPULL_SHARED_DATA, <checkout>/../shared/data,
    /work/shared/data; the first candidate when none exists (for the skip reason)."""
    folders = [Path(os.environ["RIBPULL_SHARED_DATA"])] if os.environ.get("RIBPULL_SHARED_DATA") else []
    folders += [Path(__file__).resolve().parents[2] / "shared" / "data", Path("/work/shared/data")]
    candidates = [f / name for f in folders]
    return next((c for c in candidates if c.exists()), candidates[0])


#: the real TotalSegmentator label map (a rib crop, 3 mm voxels)
TOTALSEG_EXAMPLE = shared_data_file("totalseg_example_seg.nii.gz")
