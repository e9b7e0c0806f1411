"""DICOM in and out: rib segmentations (SEG) in, the reconstruction as SEG, SR and STL out.

Modules: `ribs` (rib names and coded concepts), `seg_read` (a DICOM SEG -> the label-map point cloud
the pipeline fits, in mm in the LPS patient frame), `seg_write` / `sr` / `stl` (the three result
objects), `export` (all three from a finished fit), `nifti_source` (a generated CT study for a NIfTI
input's DICOM outputs, converted from its RAS fit to LPS), `synthetic` (a CT series and a rib SEG of
a label map, for tests, demos and `nifti_source`). DICOM patient coordinates are LPS (+x left, +y posterior, +z head);
nibabel's NIfTI world is RAS: (x, y, z)_LPS = (-x, -y, z)_RAS.
"""

from __future__ import annotations

import numpy as np

#: 4x4 matrix taking RAS mm (NIfTI world) to LPS mm (DICOM patient) and back (its own inverse)
LPS_FROM_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])

SEG_SOP_CLASS_UID = "1.2.840.10008.5.1.4.1.1.66.4"
CT_SOP_CLASS_UID = "1.2.840.10008.5.1.4.1.1.2"
ENCAPSULATED_STL_SOP_CLASS_UID = "1.2.840.10008.5.1.4.1.1.104.3"
COMPREHENSIVE_3D_SR_SOP_CLASS_UID = "1.2.840.10008.5.1.4.1.1.88.34"

#: the software identity written into every object RibPull creates
MANUFACTURER = "RibPull"
MODEL_NAME = "ribpull"
SOFTWARE_VERSION = "0.1.0"
