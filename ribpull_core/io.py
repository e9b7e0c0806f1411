"""Read and write point clouds (mm) in the formats users bring; validate them.

Readers: PLY (ascii / binary little or big endian), XYZ / TXT / CSV, NPY, NPZ, PCD (ascii / binary)
and NIfTI label maps (.nii / .nii.gz, rib labels -> voxel centres in mm through the header affine).
Every problem with the user's file is raised as `RibPullInputError(code, message)`; no numpy,
struct, zip, gzip or decoding error escapes `load_point_cloud`.

Writers: PLY (binary little endian float32 or ascii), XYZ / TXT / CSV, NPY, NPZ.
Nothing is ever unpickled (`allow_pickle=False` everywhere).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ribpull_core.errors import RibPullInputError
from ribpull_core.pointcloud import PointCloud

SUPPORTED_EXTENSIONS: tuple[str, ...] = (
    ".ply", ".xyz", ".txt", ".csv", ".npy", ".npz", ".pcd", ".nii", ".nii.gz", ".dcm",
)
WRITABLE_EXTENSIONS: tuple[str, ...] = (".ply", ".xyz", ".txt", ".csv", ".npy", ".npz")


def _extension(path: str | os.PathLike) -> str:
    """Lower-case extension of `path`, with ".nii.gz" kept as one extension."""
    name = Path(path).name.lower()
    if name.endswith(".nii.gz"):
        return ".nii.gz"
    return Path(name).suffix


# ----------------------------------------------------------------------------------------------
# writers
# ----------------------------------------------------------------------------------------------


def write_point_cloud(path: str | os.PathLike, cloud: PointCloud, binary: bool = True) -> Path:
    """Write `cloud` (points in mm) to `path`; the format follows the extension.

    .ply: binary little endian (float32 x y z, float32 nx ny nz when normals exist, int32 label
        when labels exist), or ascii when `binary` is False.
    .xyz / .txt: whitespace separated "x y z" or "x y z nx ny nz" (labels are not written).
    .csv: the same, comma separated.
    .npy: (N, 3) or (N, 6) float64 array (points, then normals when present; labels dropped).
    .npz: arrays `points` (N, 3) float64, and `normals` (N, 3) / `labels` (N,) int32 when present.
    Returns the path written.
    """
    path = Path(path)
    ext = _extension(path)
    if ext == ".ply":
        _write_ply(path, cloud, binary)
    elif ext in (".xyz", ".txt", ".csv"):
        _write_text(path, cloud, "," if ext == ".csv" else " ")
    elif ext == ".npy":
        arr = cloud.points if cloud.normals is None else np.hstack([cloud.points, cloud.normals])
        with open(path, "wb") as f:
            np.save(f, np.ascontiguousarray(arr, dtype=np.float64), allow_pickle=False)
    elif ext == ".npz":
        arrays = {"points": cloud.points}
        if cloud.normals is not None:
            arrays["normals"] = cloud.normals
        if cloud.labels is not None:
            arrays["labels"] = cloud.labels.astype(np.int32)
        with open(path, "wb") as f:
            np.savez(f, **arrays)
    else:
        raise RibPullInputError(
            "unknown_format",
            f"cannot write '{path.name}': use one of the extensions {', '.join(WRITABLE_EXTENSIONS)}",
        )
    return path


def _write_ply(path: Path, cloud: PointCloud, binary: bool) -> None:
    """PLY writer: vertex element only (x y z [nx ny nz] [label])."""
    n = len(cloud.points)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if cloud.normals is not None:
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
    if cloud.labels is not None:
        fields += [("label", "<i4")]
    header = ["ply", f"format {'binary_little_endian' if binary else 'ascii'} 1.0",
              "comment written by ribpull (units: mm)", f"element vertex {n}"]
    header += [f"property {'int' if t == '<i4' else 'float'} {name}" for name, t in fields]
    header += ["end_header"]
    head = ("\n".join(header) + "\n").encode("ascii")
    with open(path, "wb") as f:
        f.write(head)
        if binary:
            rec = np.empty(n, dtype=np.dtype(fields))
            rec["x"], rec["y"], rec["z"] = cloud.points.T
            if cloud.normals is not None:
                rec["nx"], rec["ny"], rec["nz"] = cloud.normals.T
            if cloud.labels is not None:
                rec["label"] = cloud.labels
            f.write(rec.tobytes())
        else:
            cols = [cloud.points]
            fmt = ["%.9g"] * 3
            if cloud.normals is not None:
                cols.append(cloud.normals)
                fmt += ["%.9g"] * 3
            if cloud.labels is not None:
                cols.append(cloud.labels.reshape(-1, 1).astype(np.float64))
                fmt += ["%d"]
            np.savetxt(f, np.hstack(cols), fmt=" ".join(fmt))


def _write_text(path: Path, cloud: PointCloud, sep: str) -> None:
    """XYZ/TXT/CSV writer: N lines of x y z [nx ny nz], full float64 precision."""
    arr = cloud.points if cloud.normals is None else np.hstack([cloud.points, cloud.normals])
    np.savetxt(path, arr, fmt="%.10g", delimiter=sep)


# ----------------------------------------------------------------------------------------------
# validation shared by every loader (and by the service for in-memory arrays)
# ----------------------------------------------------------------------------------------------

DEGENERATE_RELATIVE_SV = 1e-6  # smallest / largest singular value of centred points below this
_NORMAL_EPS = 1e-12  # normals shorter than this count as zero-length


def validate_points(points: np.ndarray, min_points: int = 100, max_points: int = 2_000_000) -> None:
    """Raise `RibPullInputError` unless `points` is a usable (N, 3) cloud in mm.

    Checks, in order: shape (N, 3) numeric ("parse_error"), N <= max_points ("too_large"),
    every coordinate finite ("non_finite", with the count), N >= min_points ("too_few_points"),
    not all identical and not (nearly) on one line or plane ("degenerate": smallest singular value
    of the centred points < 1e-6 x the largest). Duplicate points are allowed.
    """
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3 or pts.dtype.kind not in "fiu":
        raise RibPullInputError(
            "parse_error",
            f"points must be a numeric (N, 3) array of x y z in mm, got shape {pts.shape} "
            f"dtype {pts.dtype}",
        )
    n = len(pts)
    if n > max_points:
        raise RibPullInputError(
            "too_large",
            f"the cloud has {n} points, more than the limit of {max_points}; subsample it first",
        )
    bad = ~np.isfinite(pts).all(axis=1)
    n_bad = int(bad.sum())
    if n_bad:
        first = int(np.flatnonzero(bad)[0])
        raise RibPullInputError(
            "non_finite",
            f"{n_bad} of {n} points have NaN or infinite coordinates (first at index {first}); "
            "remove them before uploading",
        )
    if n < min_points:
        raise RibPullInputError(
            "too_few_points",
            f"the cloud has {n} points; at least {min_points} are needed to fit a surface",
        )
    _check_not_degenerate(pts.astype(np.float64, copy=False))


def _check_not_degenerate(pts: np.ndarray) -> None:
    """Raise "degenerate" when (N, 3) mm points are identical or lie on a line or a plane."""
    centred = pts - pts.mean(axis=0)
    sv = np.linalg.svd(centred, compute_uv=False)  # (3,), descending
    if not sv[0] > 0:
        raise RibPullInputError(
            "degenerate", "all points are identical; a surface needs points spread in 3-D"
        )
    rel = sv / sv[0]
    if rel[1] < DEGENERATE_RELATIVE_SV:
        raise RibPullInputError(
            "degenerate",
            "all points lie on a straight line; a surface needs points spread in 3-D "
            "(is this a single scan line or a wrongly parsed file?)",
        )
    if rel[2] < DEGENERATE_RELATIVE_SV:
        raise RibPullInputError(
            "degenerate",
            "all points lie in one plane (e.g. a single CT slice); a surface needs points spread "
            "in 3-D",
        )


def _clean_normals(normals: np.ndarray | None, n: int) -> np.ndarray | None:
    """(N, 3) normals -> unit float64 normals, or None when absent or any is zero-length.

    Non-finite normals raise "non_finite"; a normal count different from the point count raises
    "header_mismatch".
    """
    if normals is None:
        return None
    nrm = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    if len(nrm) != n:
        raise RibPullInputError(
            "header_mismatch", f"{len(nrm)} normals for {n} points; give one normal per point"
        )
    bad = int((~np.isfinite(nrm).all(axis=1)).sum())
    if bad:
        raise RibPullInputError(
            "non_finite",
            f"{bad} of {n} normals are NaN or infinite; fix them or drop the normal columns",
        )
    length = np.linalg.norm(nrm, axis=1)
    if n == 0 or (length < _NORMAL_EPS).any():
        return None  # zero-length normals carry no orientation: treat normals as absent
    return nrm / length[:, None]


def _as_int_labels(values: np.ndarray, what: str) -> np.ndarray:
    """(N,) numeric label values -> int32; non-integral or out-of-range values -> "parse_error"."""
    v = np.asarray(values).reshape(-1)
    if v.dtype.kind not in "fiub":
        raise RibPullInputError("parse_error", f"{what} must be integers, got dtype {v.dtype}")
    if v.dtype.kind == "f" and (not np.isfinite(v).all() or (v != np.round(v)).any()):
        raise RibPullInputError("parse_error", f"{what} must be whole numbers")
    if len(v) and (v.min() < np.iinfo(np.int32).min or v.max() > np.iinfo(np.int32).max):
        raise RibPullInputError("parse_error", f"{what} do not fit in 32-bit integers")
    return v.astype(np.int32)


# ----------------------------------------------------------------------------------------------
# entry point
# ----------------------------------------------------------------------------------------------

_FORMAT_ALIASES = {
    "ply": "ply", "xyz": "xyz", "txt": "txt", "csv": "csv", "text": "txt", "npy": "npy",
    "npz": "npz", "pcd": "pcd", "nifti": "nifti", "nii": "nifti", "nii.gz": "nifti",
    "dicom": "dicom", "dcm": "dicom",
}
_EXT_FORMAT = {
    ".ply": "ply", ".xyz": "xyz", ".txt": "txt", ".csv": "csv", ".npy": "npy", ".npz": "npz",
    ".pcd": "pcd", ".nii": "nifti", ".nii.gz": "nifti", ".dcm": "dicom",
}


def load_point_cloud(
    path: str | os.PathLike,
    *,
    labels: list[int] | None = None,
    max_points: int = 2_000_000,
    max_file_bytes: int = 512 * 1024 * 1024,
    min_points: int = 100,
    format: str | None = None,
    units: str = "mm",
    max_nifti_bytes: int | None = None,
) -> PointCloud:
    """Load a point cloud (coordinates in mm) from a file and validate it.

    path: PLY, XYZ/TXT/CSV, NPY, NPZ, PCD or NIfTI label map (see SUPPORTED_EXTENSIONS).
    labels: NIfTI only - the label values to turn into points; by default the rib labels are found
        automatically (TotalSegmentator 92-115, else RibSeg 1-24, else a single-valued mask).
    max_points / min_points: accepted point count range. max_file_bytes: checked with os.stat
        before anything is read.
    format: overrides detection (one of ply, xyz, txt, csv, npy, npz, pcd, nifti). Otherwise an
        unambiguous magic number (PLY, NPY, NPZ/zip, PCD, NIfTI) wins, then the extension.
    units: unit of the file's coordinates (NIfTI: of its affine), "mm" (default), "cm" or "m";
        points (and the NIfTI affine) are converted to mm.
    max_nifti_bytes: NIfTI only - most bytes of voxel data (header dims x dtype), checked before any
        voxel is read (default MAX_NIFTI_BYTES).
    Returns a PointCloud with points (N, 3) float64 mm, unit normals or None, int32 labels or
    None, source_format and source_bytes (and the NIfTI affine/shape/label names for label maps).
    Raises RibPullInputError (codes: see ribpull_core.errors) for anything wrong with the input.
    """
    if min_points < 1 or max_points < min_points or max_file_bytes < 1:
        raise RibPullInputError(
            "bad_parameter",
            f"need 1 <= min_points <= max_points and max_file_bytes >= 1, got min_points="
            f"{min_points}, max_points={max_points}, max_file_bytes={max_file_bytes}",
        )
    if units not in UNIT_SCALE:
        raise RibPullInputError("bad_parameter", f"units must be one of {', '.join(UNIT_SCALE)}, got {units!r}")
    path = Path(path)
    try:
        st = os.stat(path)
    except OSError:
        raise RibPullInputError("bad_parameter", f"no such file: '{path}'") from None
    if not path.is_file():
        raise RibPullInputError("bad_parameter", f"'{path}' is not a regular file")
    size = int(st.st_size)
    if size > max_file_bytes:
        raise RibPullInputError(
            "too_large",
            f"'{path.name}' is {size} bytes, more than the limit of {max_file_bytes} bytes; "
            "subsample the cloud or use a binary format",
        )
    if size == 0:
        raise RibPullInputError("empty_file", f"'{path.name}' is empty (0 bytes); upload the file again")
    fmt = _detect_format(path, format)
    try:
        if fmt == "nifti":
            check_nifti_header(path, MAX_NIFTI_BYTES if max_nifti_bytes is None else max_nifti_bytes)
            cloud = _load_nifti(path, labels, max_points)
        elif fmt == "dicom":  # a DICOM SEG: a label map in the LPS patient frame (ribpull_core.dicom)
            from ribpull_core.dicom.seg_read import load_seg

            cloud = load_seg(path, labels, max_points,
                             MAX_NIFTI_BYTES if max_nifti_bytes is None else max_nifti_bytes)
        else:
            cloud = _LOADERS[fmt](path, max_points)
    except (RibPullInputError, MemoryError):
        raise
    except Exception as exc:  # noqa: BLE001 - any parser failure is the file's fault
        raise RibPullInputError(
            "parse_error",
            f"could not read '{path.name}' as {fmt.upper()}: {type(exc).__name__}: {exc}. "
            "Check that the file is complete and really is in this format.",
        ) from None
    validate_points(cloud.points, min_points, max_points)
    if UNIT_SCALE[units] != 1.0:
        cloud.points = cloud.points * UNIT_SCALE[units]
        if cloud.nifti_affine is not None:
            cloud.nifti_affine = cloud.nifti_affine.copy()
            cloud.nifti_affine[:3, :] *= UNIT_SCALE[units]
    cloud.normals = _clean_normals(cloud.normals, len(cloud.points))
    if cloud.labels is not None and len(cloud.labels) != len(cloud.points):
        raise RibPullInputError(
            "header_mismatch", f"{len(cloud.labels)} labels for {len(cloud.points)} points"
        )
    cloud.source_format = fmt
    cloud.source_bytes = size
    return cloud


def _detect_format(path: Path, override: str | None) -> str:
    """Format name from `override`, else magic bytes, else the extension; else "unknown_format"."""
    supported = ", ".join(SUPPORTED_EXTENSIONS)
    if override is not None:
        key = str(override).lower().lstrip(".")
        if key not in _FORMAT_ALIASES:
            raise RibPullInputError(
                "unknown_format",
                f"unknown format '{override}'; use one of {', '.join(sorted(set(_FORMAT_ALIASES.values())))}",
            )
        return _FORMAT_ALIASES[key]
    ext = _extension(path)
    sniffed = _sniff(path)
    if sniffed is not None and not (sniffed == "gzip" and ext != ".nii.gz" and ext in _EXT_FORMAT):
        return "nifti" if sniffed == "gzip" else sniffed
    if ext in _EXT_FORMAT:
        return _EXT_FORMAT[ext]
    raise RibPullInputError(
        "unknown_format",
        f"cannot tell the format of '{path.name}' (extension '{ext or '(none)'}'); supported: "
        f"{supported}",
    )


def _sniff(path: Path) -> str | None:
    """Cheap magic-number check of the first 560 bytes; "gzip" for any gzip stream."""
    with open(path, "rb") as f:
        head = f.read(560)
    if head.startswith(b"ply") and head[3:4] in (b"\n", b"\r"):
        return "ply"
    if head.startswith(b"\x93NUMPY"):
        return "npy"
    if head.startswith((b"PK\x03\x04", b"PK\x05\x06")):
        return "npz"
    if head.startswith(b"\x1f\x8b"):
        return "gzip"
    if head[344:348] in (b"n+1\x00", b"ni1\x00") or head[4:8] in (b"n+2\x00", b"ni2\x00"):
        return "nifti"
    if head.startswith((b"# .PCD", b"VERSION", b"FIELDS")):
        return "pcd"
    if head[128:132] == b"DICM":  # DICOM Part 10 preamble
        return "dicom"
    return None


def _too_many(n: int, max_points: int, what: str) -> None:
    """Raise "too_large" early (before reading the data) when a header declares > max_points."""
    if n > max_points:
        raise RibPullInputError(
            "too_large",
            f"the file declares {n} {what}, more than the limit of {max_points}; subsample it first",
        )


# ----------------------------------------------------------------------------------------------
# PLY
# ----------------------------------------------------------------------------------------------

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def _split_header(data: bytes, end_marker: bytes, what: str) -> tuple[list[str], int]:
    """Header lines (ascii) up to and including the line that starts with `end_marker`.

    Returns (lines, byte offset of the data after that line).
    """
    pos = 0
    lines: list[str] = []
    while True:
        nl = data.find(b"\n", pos)
        if nl < 0 or len(lines) > 10_000:
            raise RibPullInputError(
                "parse_error",
                f"the {what} header never ends (no '{end_marker.decode()}' line); the file is "
                f"truncated or not a {what} file",
            )
        raw = data[pos:nl].rstrip(b"\r")
        try:
            line = raw.decode("ascii").strip()
        except UnicodeDecodeError:
            raise RibPullInputError(
                "parse_error", f"the {what} header contains non-ASCII bytes; is this really {what}?"
            ) from None
        lines.append(line)
        pos = nl + 1
        if line.split()[:1] == [end_marker.decode()]:
            return lines, pos


def _parse_ply_header(lines: list[str]) -> tuple[str, list[dict]]:
    """PLY header lines -> (format, elements); element = {name, count, props: [(name, type|None)]}.

    A list property is recorded with type None (its size varies per element).
    """
    if not lines or lines[0] != "ply":
        raise RibPullInputError("parse_error", "not a PLY file: the first line must be 'ply'")
    fmt = None
    elements: list[dict] = []
    for line in lines[1:-1]:
        tok = line.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        if tok[0] == "format" and len(tok) >= 2:
            fmt = tok[1]
        elif tok[0] == "element" and len(tok) == 3:
            count = int(tok[2])
            if count < 0:
                raise ValueError(f"negative element count in '{line}'")
            elements.append({"name": tok[1], "count": count, "props": []})
        elif tok[0] == "property" and elements:
            if tok[1] == "list" and len(tok) == 5:
                elements[-1]["props"].append((tok[4], None, tok[2], tok[3]))
            elif len(tok) == 3 and tok[1] in _PLY_TYPES:
                elements[-1]["props"].append((tok[2], _PLY_TYPES[tok[1]]))
            else:
                raise ValueError(f"unsupported PLY property line '{line}'")
        else:
            raise ValueError(f"unexpected PLY header line '{line}'")
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise RibPullInputError(
            "parse_error",
            f"unsupported PLY format '{fmt}'; use ascii, binary_little_endian or binary_big_endian",
        )
    return fmt, elements


def _load_ply(path: Path, max_points: int) -> PointCloud:
    """PLY vertex element -> PointCloud (x y z, optional nx ny nz and integer label)."""
    data = path.read_bytes()
    lines, offset = _split_header(data, b"end_header", "PLY")
    fmt, elements = _parse_ply_header(lines)
    idx = next((i for i, e in enumerate(elements) if e["name"] == "vertex"), None)
    if idx is None:
        raise RibPullInputError("parse_error", "the PLY file has no 'element vertex'")
    vertex = elements[idx]
    n = vertex["count"]
    _too_many(n, max_points, "vertices")
    names = [p[0] for p in vertex["props"]]
    if any(p[1] is None for p in vertex["props"]):
        raise RibPullInputError("parse_error", "PLY vertex element with list properties is not supported")
    if not {"x", "y", "z"} <= set(names):
        raise RibPullInputError("parse_error", f"PLY vertex has no x, y, z properties (has {names})")
    if fmt == "ascii":
        table = _ply_ascii_vertices(data[offset:], elements, idx)
        cols = {name: table[:, i] for i, name in enumerate(names)}
    else:
        rec = _ply_binary_vertices(data, offset, elements, idx, "<" if "little" in fmt else ">")
        cols = {name: rec[name] for name in names}
    return _cloud_from_columns(cols, ("x", "y", "z"), ("nx", "ny", "nz"), "label", "PLY")


def _cloud_from_columns(cols: dict, xyz, nxyz, label_key: str, what: str) -> PointCloud:
    """Named (N,) columns -> PointCloud; normals only when all three normal columns exist."""
    points = np.stack([np.asarray(cols[k], dtype=np.float64) for k in xyz], axis=1)
    normals = None
    if all(k in cols for k in nxyz):
        normals = np.stack([np.asarray(cols[k], dtype=np.float64) for k in nxyz], axis=1)
    lab = _as_int_labels(cols[label_key], f"{what} '{label_key}' values") if label_key in cols else None
    return PointCloud(points=points, normals=normals, labels=lab)


def _ply_ascii_vertices(body: bytes, elements: list[dict], idx: int) -> np.ndarray:
    """(N, n_props) float64 table of the ascii vertex lines; line counts checked against the header."""
    text = body.decode("ascii")
    lines = [ln for ln in text.splitlines() if ln.strip()]
    skip = sum(e["count"] for e in elements[:idx])
    n = elements[idx]["count"]
    later = sum(e["count"] for e in elements[idx + 1:])
    nprops = len(elements[idx]["props"])
    if len(lines) < skip + n + later:
        raise RibPullInputError(
            "header_mismatch",
            f"the PLY header declares {n} vertices but the file has only "
            f"{max(len(lines) - skip, 0)} data lines for them; the file is truncated or the header "
            "count is wrong",
        )
    if len(lines) > skip + n + later:
        raise RibPullInputError(
            "header_mismatch",
            f"the PLY header declares {skip + n + later} data lines ({n} vertices) but the file has "
            f"{len(lines)}; fix the 'element vertex' count",
        )
    if n == 0:
        return np.zeros((0, nprops))
    table = np.loadtxt(lines[skip:skip + n], dtype=np.float64, ndmin=2, comments=None)
    if table.shape[1] != nprops:
        raise RibPullInputError(
            "parse_error", f"PLY vertex lines have {table.shape[1]} values, the header declares {nprops}"
        )
    return table


def _ply_binary_vertices(data: bytes, offset: int, elements: list[dict], idx: int, endian: str):
    """Structured (N,) array of binary vertices; byte counts checked against the header."""
    for e in elements[:idx]:
        if any(p[1] is None for p in e["props"]):
            raise RibPullInputError(
                "parse_error",
                f"binary PLY with a list element ('{e['name']}') before the vertices is not "
                "supported; write the vertex element first",
            )
        offset += e["count"] * np.dtype([(p[0], endian + p[1]) for p in e["props"]]).itemsize
    vertex = elements[idx]
    dtype = np.dtype([(p[0], endian + p[1]) for p in vertex["props"]])
    need = vertex["count"] * dtype.itemsize
    have = len(data) - offset
    if have < need:
        raise RibPullInputError(
            "header_mismatch",
            f"the PLY header declares {vertex['count']} vertices ({need} bytes) but only "
            f"{max(have, 0)} bytes follow; the file is truncated or the header count is wrong",
        )
    rest = elements[idx + 1:]
    if all(p[1] is not None for e in rest for p in e["props"]):
        expected_rest = sum(
            e["count"] * np.dtype([(p[0], endian + p[1]) for p in e["props"]]).itemsize for e in rest
        )
        if have - need != expected_rest:
            raise RibPullInputError(
                "header_mismatch",
                f"the PLY header declares {vertex['count']} vertices ({need} bytes"
                f"{' plus ' + str(expected_rest) + ' bytes of other elements' if rest else ''}) "
                f"but {have} bytes follow; fix the 'element vertex' count",
            )
    return np.frombuffer(data, dtype=dtype, count=vertex["count"], offset=offset)


# ----------------------------------------------------------------------------------------------
# XYZ / TXT / CSV
# ----------------------------------------------------------------------------------------------


def _load_text(path: Path, max_points: int) -> PointCloud:
    """Columns x y z or x y z nx ny nz; ',', ';' or whitespace separated; '#' comments; an
    optional single header line."""
    try:
        text = path.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError:
        raise RibPullInputError(
            "parse_error", f"'{path.name}' is not a text file (it is not valid UTF-8/ASCII)"
        ) from None
    lines = [ln.split("#", 1)[0].strip() for ln in text.splitlines()]
    lines = [ln for ln in lines if ln]
    if not lines:
        raise RibPullInputError("empty_file", f"'{path.name}' has no data lines (only comments or blanks)")
    delim = "," if "," in lines[0] else ";" if ";" in lines[0] else None
    if not _is_numeric_row(lines[0], delim):
        lines = lines[1:]  # a header line such as "x,y,z"
        if not lines:
            raise RibPullInputError("too_few_points", f"'{path.name}' has a header line but no data")
    _too_many(len(lines), max_points, "data lines")
    table = np.loadtxt(lines, dtype=np.float64, delimiter=delim, ndmin=2, comments=None)
    if table.shape[1] not in (3, 6):
        raise RibPullInputError(
            "parse_error",
            f"expected 3 columns (x y z) or 6 columns (x y z nx ny nz), found {table.shape[1]}",
        )
    return PointCloud(points=table[:, :3], normals=table[:, 3:6] if table.shape[1] == 6 else None)


def _is_numeric_row(line: str, delim: str | None) -> bool:
    """True when every field of `line` parses as a float."""
    try:
        [float(t) for t in line.split(delim)]
    except ValueError:
        return False
    return True


# ----------------------------------------------------------------------------------------------
# NPY / NPZ
# ----------------------------------------------------------------------------------------------


def _read_npy_checked(f, name: str, max_points: int, allowed_ndim: tuple[int, ...]) -> np.ndarray:
    """Read one .npy stream after checking its header (dtype, shape, size) - never unpickles."""
    fmt = np.lib.format
    try:
        version = fmt.read_magic(f)
    except ValueError:
        raise RibPullInputError(
            "parse_error",
            f"'{name}' is not a .npy array file (no NUMPY magic bytes); pickled or other data is "
            "never loaded - save the points with np.save",
        ) from None
    if version == (1, 0):
        shape, fortran, dtype = fmt.read_array_header_1_0(f)
    elif version == (2, 0):
        shape, fortran, dtype = fmt.read_array_header_2_0(f)
    else:
        raise RibPullInputError(
            "parse_error", f"'{name}' uses .npy format version {version}; re-save it with np.save"
        )
    if dtype.hasobject:
        raise RibPullInputError(
            "parse_error",
            f"'{name}' holds Python objects (a pickled/object array), which are never loaded; "
            "save a plain float array, e.g. np.save(path, points.astype(np.float64))",
        )
    if dtype.kind not in "fiub":
        raise RibPullInputError("parse_error", f"'{name}' has non-numeric dtype {dtype}")
    if len(shape) not in allowed_ndim:
        raise RibPullInputError("parse_error", f"'{name}' has shape {shape}; expected (N, 3) or (N, 6)")
    if shape:
        _too_many(int(shape[0]), max_points, f"rows in '{name}'")
    count = int(np.prod(shape, dtype=np.int64))
    _too_many(count, 6 * max_points, f"values in '{name}'")
    raw = f.read(count * dtype.itemsize)
    if len(raw) < count * dtype.itemsize:
        raise RibPullInputError(
            "header_mismatch",
            f"'{name}' declares shape {shape} ({count * dtype.itemsize} bytes) but only "
            f"{len(raw)} bytes of data follow; the file is truncated",
        )
    arr = np.frombuffer(raw, dtype=dtype, count=count)
    return arr.reshape(shape, order="F" if fortran else "C")


def _points_normals_from_array(arr: np.ndarray, name: str):
    """(N, 3) or (N, 6) array -> (points (N, 3), normals (N, 3) or None)."""
    if arr.ndim != 2 or arr.shape[1] not in (3, 6):
        raise RibPullInputError(
            "parse_error", f"'{name}' has shape {arr.shape}; expected (N, 3) points or (N, 6) points+normals"
        )
    arr = arr.astype(np.float64)
    return arr[:, :3], (arr[:, 3:6] if arr.shape[1] == 6 else None)


def _load_npy(path: Path, max_points: int) -> PointCloud:
    """NPY (N, 3) or (N, 6) numeric array."""
    with open(path, "rb") as f:
        arr = _read_npy_checked(f, path.name, max_points, (2,))
    points, normals = _points_normals_from_array(arr, path.name)
    return PointCloud(points=points, normals=normals)


def _load_npz(path: Path, max_points: int) -> PointCloud:
    """NPZ with `points` (or its only array) (N, 3)/(N, 6), optional `normals` (N, 3), `labels` (N,)."""
    import zipfile

    with zipfile.ZipFile(path) as zf:
        members = {n[:-4]: n for n in zf.namelist() if n.endswith(".npy")}
        if "points" in members:
            key = "points"
        elif len(members) == 1:
            key = next(iter(members))
        else:
            raise RibPullInputError(
                "parse_error",
                f"the NPZ file has arrays {sorted(members)}; name the point array 'points'",
            )

        def read(k: str, ndims: tuple[int, ...]) -> np.ndarray:
            with zf.open(members[k]) as f:
                return _read_npy_checked(f, f"{path.name}:{k}", max_points, ndims)

        points, normals = _points_normals_from_array(read(key, (2,)), f"{path.name}:{key}")
        if "normals" in members and key != "normals":
            normals = read("normals", (2,)).astype(np.float64)
        labels = None
        if "labels" in members and key != "labels":
            labels = _as_int_labels(read("labels", (1,)), "NPZ 'labels'")
    return PointCloud(points=points, normals=normals, labels=labels)


# ----------------------------------------------------------------------------------------------
# PCD
# ----------------------------------------------------------------------------------------------


def _load_pcd(path: Path, max_points: int) -> PointCloud:
    """PCD ascii/binary: x y z, optional normal_x normal_y normal_z, optional label."""
    data = path.read_bytes()
    lines, offset = _split_header(data, b"DATA", "PCD")
    head: dict[str, list[str]] = {}
    for line in lines:
        tok = line.split()
        if tok and not tok[0].startswith("#"):
            head[tok[0].upper()] = tok[1:]
    fields = head.get("FIELDS")
    if not fields:
        raise RibPullInputError("parse_error", "the PCD header has no FIELDS line")
    nf = len(fields)
    sizes = [int(s) for s in head.get("SIZE", ["4"] * nf)]
    types = [t.upper() for t in head.get("TYPE", ["F"] * nf)]
    counts = [int(c) for c in head.get("COUNT", ["1"] * nf)]
    if not (len(sizes) == len(types) == len(counts) == nf):
        raise RibPullInputError("parse_error", "PCD FIELDS, SIZE, TYPE and COUNT have different lengths")
    width, height = int(head.get("WIDTH", ["-1"])[0]), int(head.get("HEIGHT", ["1"])[0])
    n = int(head["POINTS"][0]) if "POINTS" in head else width * height
    if n < 0:
        raise RibPullInputError("parse_error", "the PCD header has neither POINTS nor WIDTH")
    if width >= 0 and n != width * height:
        raise RibPullInputError(
            "header_mismatch",
            f"the PCD header says POINTS {n} but WIDTH x HEIGHT = {width} x {height} = "
            f"{width * height}; make them agree",
        )
    _too_many(n, max_points, "points")
    mode = head["DATA"][0].lower() if head.get("DATA") else ""
    if mode == "binary_compressed":
        raise RibPullInputError(
            "unknown_format",
            "PCD 'DATA binary_compressed' is not supported; re-save the cloud as binary or ascii "
            "PCD (e.g. pcl_convert_pcd_ascii_binary in.pcd out.pcd 1)",
        )
    if not {"x", "y", "z"} <= set(fields):
        raise RibPullInputError("parse_error", f"PCD has no x, y, z fields (has {fields})")
    unique = [f if f not in fields[:i] else f"_dup{i}" for i, f in enumerate(fields)]
    if mode == "binary":
        codes = {"F": "f", "I": "i", "U": "u"}
        dtype = np.dtype([
            (name, f"<{codes[t]}{s}", (c,)) if c > 1 else (name, f"<{codes[t]}{s}")
            for name, t, s, c in zip(unique, types, sizes, counts)
        ])
        need, have = n * dtype.itemsize, len(data) - offset
        if have != need:
            raise RibPullInputError(
                "header_mismatch",
                f"the PCD header declares {n} points ({need} bytes) but {have} bytes follow; "
                f"the file is {'truncated' if have < need else 'longer than declared'}",
            )
        rec = np.frombuffer(data, dtype=dtype, count=n, offset=offset)
        cols = {name: rec[name] for name, c in zip(unique, counts) if c == 1}
    elif mode == "ascii":
        rows = [ln for ln in data[offset:].decode("ascii").splitlines() if ln.strip()]
        if len(rows) != n:
            raise RibPullInputError(
                "header_mismatch",
                f"the PCD header declares {n} points but the file has {len(rows)} data lines",
            )
        table = np.loadtxt(rows, dtype=np.float64, ndmin=2, comments=None) if n else np.zeros((0, sum(counts)))
        if table.shape[1] != sum(counts):
            raise RibPullInputError(
                "parse_error", f"PCD data lines have {table.shape[1]} values, header declares {sum(counts)}"
            )
        starts = np.cumsum([0] + counts[:-1])
        cols = {name: table[:, s] for name, s, c in zip(unique, starts, counts) if c == 1}
    else:
        raise RibPullInputError("parse_error", f"unknown PCD DATA mode '{mode}'; use ascii or binary")
    return _cloud_from_columns(cols, ("x", "y", "z"), ("normal_x", "normal_y", "normal_z"), "label", "PCD")


# ----------------------------------------------------------------------------------------------
# NIfTI label maps
# ----------------------------------------------------------------------------------------------

TOTALSEG_RIB_LABELS: tuple[int, ...] = tuple(range(92, 116))  # rib_left_1..12, rib_right_1..12
RIBSEG_RIB_LABELS: tuple[int, ...] = tuple(range(1, 25))
MAX_NIFTI_VOXELS = 1024**3  # larger volumes are refused before their data is read
MAX_NIFTI_BYTES = 1024**3  # voxel data (dims x dtype) of a label map, checked from the header
#: factor from a unit to mm (load_point_cloud(units=...))
UNIT_SCALE = {"mm": 1.0, "cm": 10.0, "m": 1000.0}


def check_nifti_header(path: Path, max_bytes: int) -> None:
    """Refuse a NIfTI whose header says its voxel data (dims x bitpix) is over `max_bytes`, before
    any voxel is read or decompressed (only the first 540 bytes of the stream are inflated)."""
    import gzip
    import struct

    with open(path, "rb") as f:
        gz = f.read(2) == b"\x1f\x8b"
    try:
        with gzip.open(path, "rb") if gz else open(path, "rb") as f:
            head = f.read(540)
    except (OSError, EOFError, ValueError):
        raise RibPullInputError("parse_error", f"'{path.name}' is not a readable (gzipped) NIfTI file") from None
    if len(head) < 348:
        raise RibPullInputError("parse_error", f"'{path.name}' is shorter than a NIfTI header (348 bytes)")
    for endian in ("<", ">"):
        n = struct.unpack(endian + "i", head[:4])[0]
        if n == 348:
            dims = struct.unpack(endian + "8h", head[40:56])
            bitpix = struct.unpack(endian + "h", head[72:74])[0]
            break
        if n == 540 and len(head) >= 540:
            dims = struct.unpack(endian + "8q", head[16:80])
            bitpix = struct.unpack(endian + "h", head[14:16])[0]
            break
    else:
        raise RibPullInputError("parse_error", f"'{path.name}' has no NIfTI-1/-2 header (sizeof_hdr is not 348/540)")
    ndim = int(dims[0])
    if not 1 <= ndim <= 7 or any(int(d) < 1 for d in dims[1:ndim + 1]) or bitpix not in (1, 8, 16, 24, 32, 64, 128, 256):
        raise RibPullInputError(
            "parse_error", f"the NIfTI header of '{path.name}' has invalid dims {tuple(dims[:ndim + 1])} or bitpix {bitpix}")
    nbytes = int(np.prod([int(d) for d in dims[1:ndim + 1]], dtype=object)) * bitpix // 8
    if nbytes > max_bytes:
        raise RibPullInputError(
            "too_large",
            f"the NIfTI header says {tuple(int(d) for d in dims[1:ndim + 1])} voxels of {bitpix} bits "
            f"({nbytes / 2**20:.0f} MiB); the limit is {max_bytes / 2**20:.0f} MiB of voxel data",
        )
_MAX_MASK_DISTINCT = 1000  # integral volumes with more distinct values look like images


def totalseg_rib_names() -> dict[int, str]:
    """TotalSegmentator v2 rib ids: 92..103 -> rib_left_1..12, 104..115 -> rib_right_1..12."""
    return {92 + i: f"rib_left_{i + 1}" for i in range(12)} | {
        104 + i: f"rib_right_{i + 1}" for i in range(12)
    }


def ribseg_rib_names() -> dict[int, str]:
    """RibSeg v2 ids: 1..12 -> rib_left_1..12, 13..24 -> rib_right_1..12.

    ASSUMPTION: RibSeg documents labels 1-24 as the 24 ribs; that 1-12 are the left side and
    13-24 the right side (top to bottom) is our assumption, not verified against the dataset.
    """
    return {1 + i: f"rib_left_{i + 1}" for i in range(12)} | {
        13 + i: f"rib_right_{i + 1}" for i in range(12)
    }


def _load_nifti(path: Path, labels: list[int] | None, max_points: int) -> PointCloud:
    """NIfTI label map -> voxel centres (mm, through img.affine) of the selected labels."""
    import nibabel as nib

    if path.name.lower().endswith((".nii", ".nii.gz")):
        return _nifti_to_cloud(nib.load(str(path)), labels, max_points)
    # a neutral upload name: open the (gzipped) stream ourselves; data is still read lazily
    import gzip

    with open(path, "rb") as f:
        gz = f.read(2) == b"\x1f\x8b"
    with gzip.open(path, "rb") if gz else open(path, "rb") as stream:
        holder = nib.FileHolder(fileobj=stream)
        img = nib.Nifti1Image.from_file_map({"header": holder, "image": holder})
        return _nifti_to_cloud(img, labels, max_points)


def _nifti_to_cloud(img, labels: list[int] | None, max_points: int) -> PointCloud:
    """nibabel image (header read, data lazy) -> PointCloud of the selected label voxels."""
    shape = tuple(int(s) for s in img.shape)
    while len(shape) > 3 and shape[-1] == 1:
        shape = shape[:-1]
    if len(shape) != 3:
        raise RibPullInputError(
            "parse_error",
            f"the NIfTI volume has shape {tuple(img.shape)}; a 3-D label map is needed "
            "(4-D / time series volumes are not supported)",
        )
    if int(np.prod(shape, dtype=np.int64)) > MAX_NIFTI_VOXELS:
        raise RibPullInputError(
            "too_large", f"the NIfTI volume {shape} has more than {MAX_NIFTI_VOXELS} voxels"
        )
    affine = np.asarray(img.affine, dtype=np.float64)
    if not np.isfinite(affine).all():
        raise RibPullInputError(
            "bad_affine", "the NIfTI affine (sform/qform) contains NaN or infinite values; fix the header's "
                          "voxel-to-world transform")
    if abs(float(np.linalg.det(affine[:3, :3]))) < 1e-12:
        raise RibPullInputError(
            "bad_affine", "the NIfTI affine (sform/qform) is singular (zero voxel size or collapsed axes); "
                          "fix the header's voxel-to-world transform / pixdim")
    vol = np.asanyarray(img.dataobj)
    while vol.ndim > 3:  # drop trailing singleton axes (a view, no copy)
        vol = vol[..., 0]
    vol = _integral_label_volume(vol)
    present = _present_labels(vol)
    selected, names = _select_labels(present, labels)
    return label_volume_cloud(vol, affine, selected, names, max_points, all_present=len(selected) == len(present))


def label_volume_cloud(vol: np.ndarray, affine: np.ndarray, selected: list[int], names: dict[int, str],
                       max_points: int, all_present: bool = False) -> PointCloud:
    """An integer label volume -> PointCloud of the voxel centres (mm, through `affine`: voxel index
    -> mm) holding one of the `selected` values, labelled with their value and named by `names`.
    Shared by the NIfTI loader and the DICOM SEG reader (ribpull_core.dicom.seg_read).
    all_present: every non-zero value is selected (a plain `vol != 0` mask, no lookup)."""
    shape = tuple(int(s) for s in vol.shape)
    mask = vol != 0 if all_present else _label_mask(vol, selected)
    count = int(np.count_nonzero(mask))
    _too_many(count, max_points, "selected label voxels")
    if mask.flags.f_contiguous and not mask.flags.c_contiguous:  # nibabel arrays: walk in memory order
        ijk = np.argwhere(mask.T)[:, ::-1]  # (N, 3) voxel indices i, j, k
    else:
        ijk = np.argwhere(mask)
    points = ijk @ affine[:3, :3].T + affine[:3, 3]
    values = vol[tuple(ijk.T)].astype(np.int32)
    return PointCloud(
        points=points, labels=values, nifti_affine=affine, nifti_shape=shape,
        label_names={k: v for k, v in names.items() if k in set(selected)},
    )


def _integral_label_volume(vol: np.ndarray) -> np.ndarray:
    """Label volume as integers; non-integral float volumes (CT images) -> "no_labels"."""
    if vol.dtype.kind in "iub":
        return vol
    if vol.dtype.kind != "f":
        raise RibPullInputError("parse_error", f"unsupported NIfTI data type {vol.dtype}")
    if not np.isfinite(vol).all() or (vol != np.round(vol)).any():
        raise RibPullInputError(
            "no_labels",
            "this looks like a CT image, not a label map (its voxel values are not whole "
            "numbers); upload the rib segmentation (label map) instead",
        )
    lo, hi = float(vol.min()), float(vol.max())
    if lo < np.iinfo(np.int32).min or hi > np.iinfo(np.int32).max:
        raise RibPullInputError("no_labels", "the NIfTI values are too large to be labels")
    return np.round(vol).astype(np.int32)


def _present_labels(vol: np.ndarray) -> list[int]:
    """Sorted non-zero values in an integer volume; rejects image-like volumes."""
    lo, hi = int(vol.min()), int(vol.max())
    if lo >= 0 and hi <= 65535:
        counts = np.zeros(hi + 1, dtype=np.int64)
        flat = vol.ravel(order="K")  # memory order: no copy for nibabel's Fortran-ordered arrays
        for start in range(0, flat.size, 1 << 24):  # bounded memory for large volumes
            counts += np.bincount(flat[start:start + (1 << 24)].astype(np.intp), minlength=hi + 1)
        present = np.flatnonzero(counts)
    else:
        present = np.unique(vol)
    present = [int(v) for v in present if v != 0]
    if lo < 0 or len(present) > _MAX_MASK_DISTINCT:
        raise RibPullInputError(
            "no_labels",
            f"this looks like a CT image, not a label map ({len(present)} distinct values from "
            f"{lo} to {hi}); upload the rib segmentation (label map) instead",
        )
    return present


def _label_mask(vol: np.ndarray, selected: list[int]) -> np.ndarray:
    """Boolean volume: True where the integer `vol` holds one of `selected` (lookup table)."""
    lo, hi = int(vol.min()), int(vol.max())
    if lo >= 0 and hi <= 65535:
        lut = np.zeros(hi + 1, dtype=bool)
        lut[[v for v in selected if v <= hi]] = True
        return lut[vol]
    return np.isin(vol, np.asarray(selected, dtype=vol.dtype))


def _select_labels(present: list[int], labels: list[int] | None) -> tuple[list[int], dict[int, str]]:
    """Which label values become points, and their anatomical names.

    Rules: explicit `labels` -> those values; any TotalSegmentator rib (92-115) present -> 92-115;
    a single non-zero value -> binary mask; all values within 1-24 -> RibSeg ribs; otherwise
    "no_labels" (a multi-label map without rib labels: pass `labels` explicitly).
    """
    if not present:
        raise RibPullInputError("no_labels", "the label map is empty (every voxel is 0)")
    pset = set(present)
    ts = [v for v in present if v in TOTALSEG_RIB_LABELS]
    if labels is not None:
        try:
            want = sorted({int(v) for v in labels})
        except (TypeError, ValueError):
            raise RibPullInputError(
                "bad_parameter", f"labels must be a list of integers, got {labels!r}"
            ) from None
        chosen = [v for v in want if v in pset]
        if not chosen:
            raise RibPullInputError(
                "no_labels",
                f"none of the requested labels {want} occur in the volume; labels present: "
                f"{_fmt_labels(present)}",
            )
        if set(chosen) <= set(TOTALSEG_RIB_LABELS):
            return chosen, totalseg_rib_names()
        if pset <= set(RIBSEG_RIB_LABELS) and len(pset) > 1:
            return chosen, ribseg_rib_names()
        return chosen, {}
    if ts:
        return ts, totalseg_rib_names()
    if len(present) == 1:
        return present, {}
    if pset <= set(RIBSEG_RIB_LABELS):
        return present, ribseg_rib_names()
    raise RibPullInputError(
        "no_labels",
        f"no rib labels found: the volume has labels {_fmt_labels(present)} but neither "
        "TotalSegmentator ribs (92-115) nor only RibSeg ribs (1-24); pass labels=[...] to choose "
        "which values are ribs",
    )


def _fmt_labels(values: list[int], limit: int = 60) -> str:
    """Short printable list of label values."""
    s = ", ".join(str(v) for v in values[:limit])
    return f"[{s}{', ...' if len(values) > limit else ''}]"


_LOADERS = {
    "ply": _load_ply, "xyz": _load_text, "txt": _load_text, "csv": _load_text,
    "npy": _load_npy, "npz": _load_npz, "pcd": _load_pcd,
}
