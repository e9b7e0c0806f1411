"""Loaders, writers and validation of ribpull_core.io on good and bad files of every format."""

from __future__ import annotations

import pickle
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
import shareddata

from ribpull_core.errors import RibPullInputError
from ribpull_core.io import (
    SUPPORTED_EXTENSIONS,
    load_point_cloud,
    validate_points,
    write_point_cloud,
)
from ribpull_core.pointcloud import PointCloud

TOTALSEG_EXAMPLE = shareddata.TOTALSEG_EXAMPLE


# ----------------------------------------------------------------------------------------------
# fixtures and helpers
# ----------------------------------------------------------------------------------------------


@pytest.fixture
def cloud() -> PointCloud:
    """300 points on an ellipsoid (semi-axes 120, 90, 60 mm, centre (10, -20, 300) mm), outward
    unit normals, labels 1..3."""
    rng = np.random.default_rng(0)
    d = rng.normal(size=(300, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    axes = np.array([120.0, 90.0, 60.0])
    pts = d * axes + np.array([10.0, -20.0, 300.0])
    nrm = d / axes**2
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    return PointCloud(points=pts, normals=nrm, labels=rng.integers(1, 4, size=300))


def expect_error(code: str, path, **kw) -> RibPullInputError:
    """Load `path` and assert a RibPullInputError with `code`; returns it for message checks."""
    with pytest.raises(RibPullInputError) as ei:
        load_point_cloud(path, **kw)
    assert ei.value.code == code, f"expected {code}, got {ei.value.code}: {ei.value.message}"
    assert ei.value.message
    return ei.value


def ply_header(n: int, fmt: str, props: list[str], extra: list[str] = ()) -> bytes:
    """Hand-written PLY header with a vertex element of `n` and property lines `props`."""
    lines = ["ply", f"format {fmt} 1.0", "comment hand written", f"element vertex {n}"]
    lines += [f"property {p}" for p in props] + list(extra) + ["end_header"]
    return ("\n".join(lines) + "\n").encode()


def pcd_header(fields, sizes, types, counts, width, height, points, data) -> bytes:
    """Hand-written PCD v0.7 header."""
    return (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n"
        f"FIELDS {' '.join(fields)}\nSIZE {' '.join(map(str, sizes))}\n"
        f"TYPE {' '.join(types)}\nCOUNT {' '.join(map(str, counts))}\n"
        f"WIDTH {width}\nHEIGHT {height}\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {points}\nDATA {data}\n"
    ).encode()


def save_nifti(path: Path, vol: np.ndarray, affine: np.ndarray | None = None) -> Path:
    """Write `vol` with a 2 x 1.5 x 3 mm affine (or `affine`) as NIfTI-1."""
    if affine is None:
        affine = np.diag([2.0, 1.5, 3.0, 1.0])
        affine[:3, 3] = [-100.0, 50.0, 20.0]
    nib.save(nib.Nifti1Image(vol, affine), str(path))
    return path


# ----------------------------------------------------------------------------------------------
# round trips through write_point_cloud
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "name,binary,has_normals,has_labels,atol",
    [
        ("c.ply", True, True, True, 1e-4),  # float32 coordinates: ~1e-5 mm at 300 mm
        ("c.ply", False, True, True, 1e-6),
        ("c.xyz", True, True, False, 1e-6),
        ("c.txt", True, True, False, 1e-6),
        ("c.csv", True, True, False, 1e-6),
        ("c.npy", True, True, False, 0.0),
        ("c.npz", True, True, True, 0.0),
    ],
)
def test_round_trip(tmp_path, cloud, name, binary, has_normals, has_labels, atol):
    path = write_point_cloud(tmp_path / name, cloud, binary=binary)
    got = load_point_cloud(path)
    assert got.points.shape == (300, 3) and got.points.dtype == np.float64
    np.testing.assert_allclose(got.points, cloud.points, atol=atol, rtol=0)
    if has_normals:
        np.testing.assert_allclose(got.normals, cloud.normals, atol=1e-6)
        np.testing.assert_allclose(np.linalg.norm(got.normals, axis=1), 1.0, atol=1e-12)
    if has_labels:
        np.testing.assert_array_equal(got.labels, cloud.labels)
    else:
        assert got.labels is None
    assert got.source_format == Path(name).suffix[1:]
    assert got.source_bytes == path.stat().st_size
    assert got.nifti_affine is None


def test_round_trip_points_only(tmp_path, cloud):
    plain = PointCloud(points=cloud.points)
    for name in ("p.ply", "p.xyz", "p.npy", "p.npz"):
        got = load_point_cloud(write_point_cloud(tmp_path / name, plain))
        assert got.normals is None and got.labels is None
        np.testing.assert_allclose(got.points, plain.points, atol=1e-4)


def test_write_unknown_extension(tmp_path, cloud):
    with pytest.raises(RibPullInputError) as ei:
        write_point_cloud(tmp_path / "c.obj", cloud)
    assert ei.value.code == "unknown_format"


# ----------------------------------------------------------------------------------------------
# PLY variants with hand-written headers
# ----------------------------------------------------------------------------------------------


def test_ply_ascii_mesh_with_faces_crlf_and_comments(tmp_path, cloud):
    pts = cloud.points[:120]
    head = ply_header(120, "ascii", ["float x", "float y", "float z"],
                      ["obj_info made by hand", "element face 2", "property list uchar int vertex_indices"])
    body = "".join(f"{x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in pts) + "3 0 1 2\n3 1 2 3\n"
    (tmp_path / "m.ply").write_bytes((head.decode() + body).replace("\n", "\r\n").encode())
    got = load_point_cloud(tmp_path / "m.ply")
    np.testing.assert_allclose(got.points, pts, atol=1e-6)
    assert got.normals is None and got.labels is None


def test_ply_binary_big_endian_double_with_int_label_and_faces(tmp_path, cloud):
    n = 150
    dt = np.dtype([("x", ">f8"), ("y", ">f8"), ("z", ">f8"), ("quality", ">i2"), ("label", ">u1")])
    rec = np.zeros(n, dtype=dt)
    rec["x"], rec["y"], rec["z"] = cloud.points[:n].T
    rec["label"] = np.arange(n) % 7
    faces = np.zeros(2, dtype=[("k", "u1"), ("i", ">i4", (3,))])
    faces["k"] = 3
    head = ply_header(n, "binary_big_endian", ["double x", "double y", "double z", "short quality",
                                                "uchar label"],
                      ["element face 2", "property list uchar int vertex_indices"])
    (tmp_path / "b.ply").write_bytes(head + rec.tobytes() + faces.tobytes())
    got = load_point_cloud(tmp_path / "b.ply")
    np.testing.assert_array_equal(got.points, cloud.points[:n])  # doubles: exact
    np.testing.assert_array_equal(got.labels, np.arange(n) % 7)
    assert got.labels.dtype == np.int32


def test_ply_binary_little_endian_int_coords_and_unnormalised_normals(tmp_path):
    rng = np.random.default_rng(1)
    pts = rng.integers(-500, 500, size=(200, 3)).astype("<i4")
    nrm = rng.normal(size=(200, 3)).astype("<f4") * 5.0
    dt = np.dtype([("x", "<i4"), ("y", "<i4"), ("z", "<i4"), ("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")])
    rec = np.zeros(200, dtype=dt)
    rec["x"], rec["y"], rec["z"] = pts.T
    rec["nx"], rec["ny"], rec["nz"] = nrm.T
    head = ply_header(200, "binary_little_endian", ["int x", "int y", "int z", "float nx", "float ny",
                                                    "float nz"])
    (tmp_path / "i.ply").write_bytes(head + rec.tobytes())
    got = load_point_cloud(tmp_path / "i.ply")
    np.testing.assert_array_equal(got.points, pts.astype(np.float64))
    np.testing.assert_allclose(got.normals, nrm / np.linalg.norm(nrm, axis=1, keepdims=True), atol=1e-6)


def test_ply_binary_lying_header(tmp_path, cloud):
    good = tmp_path / "good.ply"
    write_point_cloud(good, PointCloud(points=cloud.points))
    raw = good.read_bytes()
    more = raw.replace(b"element vertex 300", b"element vertex 301")  # declares more than present
    (tmp_path / "more.ply").write_bytes(more)
    err = expect_error("header_mismatch", tmp_path / "more.ply")
    assert "301" in err.message
    fewer = raw.replace(b"element vertex 300", b"element vertex 299")  # 12 surplus bytes
    (tmp_path / "fewer.ply").write_bytes(fewer)
    expect_error("header_mismatch", tmp_path / "fewer.ply")
    (tmp_path / "trunc.ply").write_bytes(raw[:-7])  # truncated mid-record
    expect_error("header_mismatch", tmp_path / "trunc.ply")


def test_ply_ascii_lying_header(tmp_path, cloud):
    good = tmp_path / "good.ply"
    write_point_cloud(good, PointCloud(points=cloud.points), binary=False)
    raw = good.read_bytes()
    (tmp_path / "more.ply").write_bytes(raw.replace(b"element vertex 300", b"element vertex 400"))
    expect_error("header_mismatch", tmp_path / "more.ply")
    (tmp_path / "fewer.ply").write_bytes(raw.replace(b"element vertex 300", b"element vertex 200"))
    expect_error("header_mismatch", tmp_path / "fewer.ply")


def test_ply_header_count_above_max_points_is_refused_before_reading(tmp_path):
    head = ply_header(10**9, "binary_little_endian", ["float x", "float y", "float z"])
    (tmp_path / "huge.ply").write_bytes(head + b"\0" * 120)
    err = expect_error("too_large", tmp_path / "huge.ply")
    assert "1000000000" in err.message


def test_ply_garbage_and_bad_headers(tmp_path):
    (tmp_path / "g.ply").write_bytes(np.random.default_rng(2).bytes(4000))
    expect_error("parse_error", tmp_path / "g.ply")
    (tmp_path / "noend.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\n")
    expect_error("parse_error", tmp_path / "noend.ply")
    (tmp_path / "noxyz.ply").write_bytes(ply_header(1, "ascii", ["float a", "float b"]) + b"1 2\n")
    expect_error("parse_error", tmp_path / "noxyz.ply")
    (tmp_path / "fmt.ply").write_bytes(ply_header(1, "binary_middle_endian", ["float x"]))
    expect_error("parse_error", tmp_path / "fmt.ply")
    bad_row = ply_header(2, "ascii", ["float x", "float y", "float z"]) + b"1 2 3\n1 2 abc\n"
    (tmp_path / "row.ply").write_bytes(bad_row)
    expect_error("parse_error", tmp_path / "row.ply")


# ----------------------------------------------------------------------------------------------
# XYZ / TXT / CSV
# ----------------------------------------------------------------------------------------------


def test_csv_with_header_and_spaces(tmp_path, cloud):
    rows = "\n".join(f"{x}, {y}, {z}" for x, y, z in cloud.points)
    (tmp_path / "h.csv").write_text("x,y,z\n" + rows + "\n")
    np.testing.assert_allclose(load_point_cloud(tmp_path / "h.csv").points, cloud.points, atol=1e-9)


def test_semicolon_and_comments_and_whitespace(tmp_path, cloud):
    rows = "\n".join(f"{x};{y};{z}" for x, y, z in cloud.points)
    (tmp_path / "s.txt").write_text("# exported by hand\n\n" + rows + "  # last\n")
    np.testing.assert_allclose(load_point_cloud(tmp_path / "s.txt").points, cloud.points, atol=1e-9)
    rows = "\n".join(f"{x}\t {y}   {z}" for x, y, z in cloud.points)
    (tmp_path / "w.xyz").write_text(rows)
    np.testing.assert_allclose(load_point_cloud(tmp_path / "w.xyz").points, cloud.points, atol=1e-9)


def test_xyz_six_columns_normals_are_normalised(tmp_path, cloud):
    arr = np.hstack([cloud.points, cloud.normals * 3.0])
    np.savetxt(tmp_path / "n.xyz", arr)
    got = load_point_cloud(tmp_path / "n.xyz")
    np.testing.assert_allclose(got.normals, cloud.normals, atol=1e-9)


def test_text_bad_inputs(tmp_path, cloud):
    np.savetxt(tmp_path / "four.xyz", np.hstack([cloud.points, cloud.points[:, :1]]))
    err = expect_error("parse_error", tmp_path / "four.xyz")
    assert "3 columns" in err.message
    (tmp_path / "ragged.xyz").write_text("1 2 3\n4 5 6\n7 8\n" * 50)
    expect_error("parse_error", tmp_path / "ragged.xyz")
    (tmp_path / "bin.xyz").write_bytes(b"\xff\xfe\x00\x81" * 100)
    expect_error("parse_error", tmp_path / "bin.xyz")
    (tmp_path / "comments.xyz").write_text("# nothing here\n\n   \n")
    expect_error("empty_file", tmp_path / "comments.xyz")


def test_nan_points_are_counted(tmp_path, cloud):
    pts = cloud.points.copy()
    pts[[5, 17, 200], 1] = [np.nan, np.inf, -np.inf]
    np.savetxt(tmp_path / "nan.xyz", pts)
    err = expect_error("non_finite", tmp_path / "nan.xyz")
    assert "3 of 300" in err.message and "index 5" in err.message


def test_nan_normals_rejected_and_zero_normals_dropped(tmp_path, cloud):
    nrm = cloud.normals.copy()
    nrm[3] = np.nan
    write_point_cloud(tmp_path / "nn.npz", PointCloud(points=cloud.points, normals=nrm))
    expect_error("non_finite", tmp_path / "nn.npz")
    nrm = cloud.normals.copy()
    nrm[3] = 0.0
    write_point_cloud(tmp_path / "zn.npz", PointCloud(points=cloud.points, normals=nrm))
    assert load_point_cloud(tmp_path / "zn.npz").normals is None


# ----------------------------------------------------------------------------------------------
# NPY / NPZ
# ----------------------------------------------------------------------------------------------


def test_npz_single_unnamed_array_and_float_labels(tmp_path, cloud):
    np.savez(tmp_path / "u.npz", cloud.points.astype(np.float32))  # key "arr_0"
    got = load_point_cloud(tmp_path / "u.npz")
    np.testing.assert_allclose(got.points, cloud.points, atol=1e-4)
    np.savez_compressed(tmp_path / "l.npz", points=cloud.points, labels=cloud.labels.astype(float))
    np.testing.assert_array_equal(load_point_cloud(tmp_path / "l.npz").labels, cloud.labels)
    np.savez(tmp_path / "two.npz", a=cloud.points, b=cloud.points)
    expect_error("parse_error", tmp_path / "two.npz")
    np.savez(tmp_path / "short.npz", points=cloud.points, labels=cloud.labels[:10])
    expect_error("header_mismatch", tmp_path / "short.npz")


def test_npy_object_and_pickle_rejected_without_unpickling(tmp_path, cloud):
    obj = np.empty(300, dtype=object)
    obj[:] = [tuple(p) for p in cloud.points]
    np.save(tmp_path / "obj.npy", obj, allow_pickle=True)
    err = expect_error("parse_error", tmp_path / "obj.npy")
    assert "object" in err.message.lower()
    np.savez(tmp_path / "obj.npz", points=obj)
    assert "object" in expect_error("parse_error", tmp_path / "obj.npz").message.lower()
    (tmp_path / "pickled.npy").write_bytes(pickle.dumps(cloud.points))
    assert "pickled" in expect_error("parse_error", tmp_path / "pickled.npy").message


def test_npy_bad_shapes_and_truncation(tmp_path, cloud):
    np.save(tmp_path / "flat.npy", cloud.points.ravel())
    expect_error("parse_error", tmp_path / "flat.npy")
    np.save(tmp_path / "four.npy", np.hstack([cloud.points, cloud.points[:, :1]]))
    expect_error("parse_error", tmp_path / "four.npy")
    np.save(tmp_path / "t.npy", cloud.points)
    raw = (tmp_path / "t.npy").read_bytes()
    (tmp_path / "t.npy").write_bytes(raw[:-100])
    expect_error("header_mismatch", tmp_path / "t.npy")
    np.save(tmp_path / "fortran.npy", np.asfortranarray(cloud.points))
    np.testing.assert_array_equal(load_point_cloud(tmp_path / "fortran.npy").points, cloud.points)
    (tmp_path / "g.npz").write_bytes(b"PK\x03\x04" + np.random.default_rng(3).bytes(500))
    expect_error("parse_error", tmp_path / "g.npz")


# ----------------------------------------------------------------------------------------------
# PCD
# ----------------------------------------------------------------------------------------------


def test_pcd_ascii_with_normals_and_label(tmp_path, cloud):
    fields = ["x", "y", "z", "normal_x", "normal_y", "normal_z", "curvature", "label"]
    head = pcd_header(fields, [4] * 8, list("FFFFFFFU"), [1] * 8, 300, 1, 300, "ascii")
    rows = np.hstack([cloud.points, cloud.normals, np.zeros((300, 1)), cloud.labels[:, None]])
    body = "\n".join(" ".join(f"{v:.9g}" for v in r) for r in rows) + "\n"
    (tmp_path / "a.pcd").write_bytes(head + body.encode())
    got = load_point_cloud(tmp_path / "a.pcd")
    np.testing.assert_allclose(got.points, cloud.points, atol=1e-6)
    np.testing.assert_allclose(got.normals, cloud.normals, atol=1e-6)
    np.testing.assert_array_equal(got.labels, cloud.labels)
    assert got.source_format == "pcd"


def test_pcd_binary_with_padding_and_multi_count_field(tmp_path, cloud):
    # x y z, a padding field "_", rgb, a 3-float "hist" field (COUNT 3), another "_"
    dt = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("_a", "<u4"), ("rgb", "<f4"),
                   ("hist", "<f4", (3,)), ("_b", "<u1")])
    rec = np.zeros(300, dtype=dt)
    rec["x"], rec["y"], rec["z"] = cloud.points.T
    head = pcd_header(["x", "y", "z", "_", "rgb", "hist", "_"], [4, 4, 4, 4, 4, 4, 1],
                      list("FFFUFFU"), [1, 1, 1, 1, 1, 3, 1], 30, 10, 300, "binary")
    (tmp_path / "b.pcd").write_bytes(head + rec.tobytes())
    got = load_point_cloud(tmp_path / "b.pcd")
    np.testing.assert_allclose(got.points, cloud.points.astype(np.float32), atol=0)
    assert got.normals is None and got.labels is None
    # lying headers: data short, data long, POINTS != WIDTH*HEIGHT
    (tmp_path / "short.pcd").write_bytes(head + rec.tobytes()[:-5])
    expect_error("header_mismatch", tmp_path / "short.pcd")
    (tmp_path / "long.pcd").write_bytes(head + rec.tobytes() + rec.tobytes()[:40])
    expect_error("header_mismatch", tmp_path / "long.pcd")
    bad = head.replace(b"POINTS 300", b"POINTS 299")
    (tmp_path / "wh.pcd").write_bytes(bad + rec.tobytes())
    err = expect_error("header_mismatch", tmp_path / "wh.pcd")
    assert "WIDTH" in err.message


def test_pcd_binary_compressed_and_ascii_line_mismatch(tmp_path, cloud):
    head = pcd_header(["x", "y", "z"], [4, 4, 4], list("FFF"), [1, 1, 1], 300, 1, 300,
                      "binary_compressed")
    (tmp_path / "c.pcd").write_bytes(head + b"\x10\x00\x00\x00" * 20)
    err = expect_error("unknown_format", tmp_path / "c.pcd")
    assert "binary_compressed" in err.message and "re-save" in err.message
    head = pcd_header(["x", "y", "z"], [4, 4, 4], list("FFF"), [1, 1, 1], 301, 1, 301, "ascii")
    body = "\n".join(f"{x} {y} {z}" for x, y, z in cloud.points)
    (tmp_path / "l.pcd").write_bytes(head + body.encode())
    expect_error("header_mismatch", tmp_path / "l.pcd")


# ----------------------------------------------------------------------------------------------
# generic file problems, detection and validation
# ----------------------------------------------------------------------------------------------


def test_missing_empty_unknown_and_too_large(tmp_path, cloud):
    expect_error("bad_parameter", tmp_path / "nope.ply")
    (tmp_path / "e.ply").write_bytes(b"")
    expect_error("empty_file", tmp_path / "e.ply")
    np.savetxt(tmp_path / "c.dat", cloud.points)
    err = expect_error("unknown_format", tmp_path / "c.dat")
    assert all(ext in err.message for ext in SUPPORTED_EXTENSIONS)
    big = write_point_cloud(tmp_path / "big.ply", cloud)
    err = expect_error("too_large", big, max_file_bytes=1000)
    assert "1000" in err.message
    expect_error("too_large", big, max_points=200)


@pytest.mark.parametrize("ext", SUPPORTED_EXTENSIONS)
def test_garbage_bytes_are_parse_errors(tmp_path, ext):
    raw = np.random.default_rng(10).bytes(5000)
    assert not raw.startswith((b"ply", b"\x93NUMPY", b"PK", b"\x1f\x8b", b"VERSION", b"#"))
    (tmp_path / f"junk{ext}").write_bytes(raw)
    expect_error("parse_error", tmp_path / f"junk{ext}")


def test_format_override_and_magic_sniffing(tmp_path, cloud):
    np.savetxt(tmp_path / "c.dat", cloud.points)
    got = load_point_cloud(tmp_path / "c.dat", format="xyz")
    np.testing.assert_allclose(got.points, cloud.points, atol=1e-9)
    assert got.source_format == "xyz"
    ply = write_point_cloud(tmp_path / "c.ply", cloud)
    upload = tmp_path / "upload.bin"  # the service may store uploads under a neutral name
    upload.write_bytes(ply.read_bytes())
    assert load_point_cloud(upload).source_format == "ply"
    expect_error("unknown_format", tmp_path / "c.dat", format="obj")


def test_validate_points_directly():
    rng = np.random.default_rng(4)
    ok = rng.normal(size=(500, 3)) * [100.0, 50.0, 1.0]  # a thin (1 mm) slab is still 3-D
    validate_points(ok, 100, 1000)

    def code(points, **kw):
        with pytest.raises(RibPullInputError) as ei:
            validate_points(points, kw.get("min_points", 100), kw.get("max_points", 10_000))
        return ei.value.code

    assert code(ok, min_points=501) == "too_few_points"
    assert code(ok, max_points=499) == "too_large"
    assert code(np.tile([1.0, 2.0, 3.0], (200, 1))) == "degenerate"
    t = rng.uniform(-50, 50, size=(300, 1))
    line = np.array([5.0, 6.0, 7.0]) + t * np.array([0.3, -0.5, 0.8])
    assert code(line) == "degenerate"
    basis = np.linalg.qr(rng.normal(size=(3, 3)))[0]  # rotated plane through (10, 20, 30)
    plane = rng.uniform(-100, 100, size=(400, 2)) @ basis[:, :2].T + [10.0, 20.0, 30.0]
    assert code(plane) == "degenerate"
    assert code(ok.reshape(-1, 3)[:, :2]) == "parse_error"
    dup = np.vstack([ok, ok[:50]])  # duplicates are allowed
    validate_points(dup, 100, 1000)


def test_coplanar_and_collinear_files(tmp_path):
    rng = np.random.default_rng(5)
    slice_pts = np.column_stack([rng.uniform(0, 300, 500), rng.uniform(0, 300, 500), np.full(500, 42.5)])
    write_point_cloud(tmp_path / "slice.ply", PointCloud(points=slice_pts))
    assert "plane" in expect_error("degenerate", tmp_path / "slice.ply").message
    line = np.outer(rng.uniform(0, 100, 200), [1.0, 2.0, 3.0])
    np.save(tmp_path / "line.npy", line)
    assert "line" in expect_error("degenerate", tmp_path / "line.npy").message
    np.savetxt(tmp_path / "few.xyz", rng.normal(size=(99, 3)))
    err = expect_error("too_few_points", tmp_path / "few.xyz")
    assert "99" in err.message
    load_point_cloud(tmp_path / "few.xyz", min_points=50)


def test_bad_parameters(tmp_path, cloud):
    path = write_point_cloud(tmp_path / "c.npy", cloud)
    expect_error("bad_parameter", path, min_points=0)
    expect_error("bad_parameter", path, min_points=10, max_points=5)
    expect_error("bad_parameter", tmp_path)  # a directory


# ----------------------------------------------------------------------------------------------
# NIfTI label maps (synthetic)
# ----------------------------------------------------------------------------------------------


def _blocks(vol: np.ndarray, values: list[int]) -> np.ndarray:
    """Fill one 3x4x5 block per value along the first axis; returns `vol`."""
    for n, v in enumerate(values):
        vol[1 + 4 * n:4 + 4 * n, 2:6, 3:8] = v
    return vol


def test_nifti_ribseg_labels_points_in_mm(tmp_path):
    vol = _blocks(np.zeros((20, 10, 12), np.uint8), [1, 13, 24])
    path = save_nifti(tmp_path / "case-rib-seg.nii.gz", vol)
    got = load_point_cloud(path, min_points=10)
    assert len(got) == 3 * 60 and got.source_format == "nifti"
    assert sorted(set(got.labels.tolist())) == [1, 13, 24]
    assert got.label_names == {1: "rib_left_1", 13: "rib_right_1", 24: "rib_right_12"}
    assert got.nifti_shape == (20, 10, 12)
    # voxel (1, 2, 3) holds label 1: its centre is affine @ [1, 2, 3, 1]
    expected = np.array([-100.0 + 2 * 1, 50.0 + 1.5 * 2, 20.0 + 3 * 3])
    assert np.min(np.linalg.norm(got.points - expected, axis=1)) == 0.0
    np.testing.assert_array_equal(got.nifti_affine, nib.load(str(path)).affine)


def test_nifti_totalseg_selection_binary_mask_and_explicit_labels(tmp_path):
    vol = _blocks(np.zeros((24, 10, 12), np.uint8), [5, 30, 92, 110, 117])  # organs + 2 ribs
    path = save_nifti(tmp_path / "ts.nii", vol)
    got = load_point_cloud(path, min_points=10)
    assert sorted(set(got.labels.tolist())) == [92, 110]
    assert got.label_names == {92: "rib_left_1", 110: "rib_right_7"}
    got = load_point_cloud(path, min_points=10, labels=[5, 30, 999])  # 999 absent: ignored
    assert sorted(set(got.labels.tolist())) == [5, 30] and got.label_names == {}
    err = expect_error("no_labels", path, min_points=10, labels=[7, 8])
    assert "[5, 30, 92, 110, 117]" in err.message
    mask = _blocks(np.zeros((20, 10, 12), np.uint8), [255, 255])
    got = load_point_cloud(save_nifti(tmp_path / "mask.nii.gz", mask), min_points=10)
    assert len(got) == 120 and set(got.labels.tolist()) == {255} and got.label_names == {}


def test_nifti_without_rib_labels_and_empty(tmp_path):
    vol = _blocks(np.zeros((20, 10, 12), np.uint8), [5, 30, 51])  # organs only, no ribs
    err = expect_error("no_labels", save_nifti(tmp_path / "organs.nii.gz", vol), min_points=10)
    assert "[5, 30, 51]" in err.message and "labels=" in err.message
    expect_error("no_labels", save_nifti(tmp_path / "zero.nii.gz", np.zeros((8, 8, 8), np.uint8)))


def test_nifti_float_volumes(tmp_path):
    vol = _blocks(np.zeros((20, 10, 12), np.float32), [3, 4])
    got = load_point_cloud(save_nifti(tmp_path / "f.nii.gz", vol), min_points=10)
    assert sorted(set(got.labels.tolist())) == [3, 4]
    ct = np.random.default_rng(6).normal(40.0, 300.0, size=(16, 16, 8)).astype(np.float32)
    err = expect_error("no_labels", save_nifti(tmp_path / "ct.nii.gz", ct))
    assert "CT image" in err.message
    hu = np.random.default_rng(7).integers(-1024, 2000, size=(16, 16, 8)).astype(np.int16)
    assert "CT image" in expect_error("no_labels", save_nifti(tmp_path / "hu.nii.gz", hu)).message


def test_nifti_under_a_neutral_name(tmp_path):
    vol = _blocks(np.zeros((20, 10, 12), np.uint8), [2, 3])
    raw = save_nifti(tmp_path / "v.nii.gz", vol).read_bytes()
    (tmp_path / "upload.bin").write_bytes(raw)  # gzip magic, unknown extension -> NIfTI
    got = load_point_cloud(tmp_path / "upload.bin", min_points=10)
    assert got.source_format == "nifti" and len(got) == 120
    plain = save_nifti(tmp_path / "v.nii", vol).read_bytes()
    (tmp_path / "upload2.dat").write_bytes(plain)  # "n+1" magic at byte 344
    got = load_point_cloud(tmp_path / "upload2.dat", min_points=10, format="nifti")
    assert sorted(set(got.labels.tolist())) == [2, 3]


def test_nifti_4d_and_garbage(tmp_path):
    vol4 = np.zeros((10, 10, 10, 3), np.uint8)
    vol4[2:6, 2:6, 2:6, :] = 1
    expect_error("parse_error", save_nifti(tmp_path / "four.nii.gz", vol4))
    vol1 = _blocks(np.zeros((20, 10, 12, 1), np.uint8), [1, 2])  # trailing singleton is fine
    assert len(load_point_cloud(save_nifti(tmp_path / "one.nii.gz", vol1), min_points=10)) == 120
    (tmp_path / "g.nii.gz").write_bytes(b"\x1f\x8b" + np.random.default_rng(8).bytes(300))
    expect_error("parse_error", tmp_path / "g.nii.gz")
    (tmp_path / "g.nii").write_bytes(np.random.default_rng(9).bytes(300))
    expect_error("parse_error", tmp_path / "g.nii")


# ----------------------------------------------------------------------------------------------
# the real TotalSegmentator label map
# ----------------------------------------------------------------------------------------------


@pytest.mark.skipif(not TOTALSEG_EXAMPLE.exists(), reason="shared TotalSegmentator example missing")
def test_real_totalsegmentator_example():
    got = load_point_cloud(TOTALSEG_EXAMPLE)
    rib_values = sorted(set(got.labels.tolist()))
    assert rib_values == list(range(98, 104)) + list(range(110, 116))  # exactly 12 rib labels
    assert got.label_names[98] == "rib_left_7" and got.label_names[115] == "rib_right_12"
    assert got.nifti_shape == (122, 101, 30)

    # independent check: voxel counts and one voxel centre through the header's sform
    img = nib.load(str(TOTALSEG_EXAMPLE))
    data = np.asarray(img.dataobj)
    assert len(got) == int(np.isin(data, rib_values).sum())
    i, j, k = np.argwhere(data == 100)[0]
    sform = img.header.get_sform()
    centre = (sform @ np.array([i, j, k, 1.0]))[:3]
    assert np.min(np.linalg.norm(got.points - centre, axis=1)) < 1e-9
    lattice = (got.points - sform[:3, 3]) / 3.0  # isotropic 3 mm voxels
    np.testing.assert_allclose(lattice, np.round(lattice), atol=1e-9)

    # laterality. nibabel's world frame is RAS+: +x points to the patient's RIGHT (LPS/DICOM is
    # the opposite). In this file the left ribs lie at x ~ -125 mm and the right ribs at
    # x ~ +116 mm, i.e. left ribs have the SMALLER x, consistent with RAS+; the spleen (label 1,
    # left) and liver (label 5, right) agree.
    left_x = got.points[got.labels < 104, 0].mean()
    right_x = got.points[got.labels >= 104, 0].mean()
    assert left_x < -50.0 < 50.0 < right_x
    def mean_x(label: int) -> float:
        return float((np.argwhere(data == label) @ sform[:3, :3].T + sform[:3, 3])[:, 0].mean())

    assert mean_x(1) < 0 < mean_x(5)  # TotalSegmentator v2: 1 = spleen, 5 = liver


def test_mask_boundary_cloud_puts_points_on_the_voxel_faces():
    """A 3x3x3 block of label 7 (voxels 2 x 3 x 4 mm): 54 outer faces, on the block's mm boundary,
    labelled 7; interior voxels give none. Two labels keep their own faces apart."""
    from ribpull_core.pointcloud import PointCloud, mask_boundary_cloud, mask_voxel_indices

    aff = np.diag([2.0, 3.0, 4.0, 1.0])
    aff[:3, 3] = [10.0, 20.0, 30.0]
    ijk = np.argwhere(np.ones((3, 3, 3), bool)) + [5, 6, 7]
    labels = np.where(ijk[:, 0] == 5, 8, 7)
    cloud = PointCloud(points=ijk @ aff[:3, :3].T + aff[:3, 3], labels=labels, nifti_affine=aff, nifti_shape=(20, 20, 20),
                       source_format="nifti", label_names={7: "a", 8: "b"})
    assert (mask_voxel_indices(cloud) == ijk).all()
    b = mask_boundary_cloud(cloud)
    assert len(b) == 54  # the outer faces only: faces between two selected voxels are not boundary
    assert np.allclose(b.points.min(0), [19.0, 36.5, 56.0]) and np.allclose(b.points.max(0), [25.0, 45.5, 68.0])
    on_x_min = np.isclose(b.points[:, 0], 19.0)
    assert on_x_min.sum() == 9 and (b.labels[on_x_min] == 8).all()
    assert set(b.labels.tolist()) == {7, 8} and b.label_names == {7: "a", 8: "b"} and b.source_format == "nifti"
    assert np.allclose(b.nifti_affine, aff) and b.nifti_shape == (20, 20, 20)
    assert len(mask_boundary_cloud(cloud, max_points=10)) == 10
    # between labels: the 9 faces between the x = 5 layer (label 8) and the rest (7), once per side
    walls = mask_boundary_cloud(cloud, between_labels=True)
    shared = np.isclose(walls.points[:, 0], 21.0)
    assert len(walls) == 72 and shared.sum() == 18
    assert sorted(walls.labels[shared].tolist()) == [7] * 9 + [8] * 9
    with pytest.raises(ValueError):
        mask_boundary_cloud(PointCloud(points=np.zeros((3, 3))))


def test_mask_boundary_cloud_blurs_each_structure_on_its_own():
    """Two balls of different labels one voxel apart: with the sub-voxel blur, each ball's boundary
    points are where they are with the other ball absent; a blur of both together (one label) fills
    the gap between them and moves the points that face it into it (measured: up to 0.25 mm)."""
    from ribpull_core.pointcloud import PointCloud, mask_boundary_cloud

    aff = np.diag([1.5, 1.5, 1.5, 1.0])
    grid = np.argwhere(np.ones((32, 20, 20), bool))
    centre = np.array([9.5, 9.5, 9.5])
    ball_a = np.linalg.norm(grid - centre, axis=1) <= 5.9
    ball_b = np.linalg.norm(grid - centre - [13, 0, 0], axis=1) <= 5.9  # one empty voxel between them at x = 16
    ijk = np.concatenate([grid[ball_a], grid[ball_b]])
    labels = np.r_[np.full(ball_a.sum(), 1), np.full(ball_b.sum(), 2)]

    assert grid[ball_b][:, 0].min() - grid[ball_a][:, 0].max() == 2

    def cloud_of(keep, structure_labels=labels):
        return PointCloud(points=ijk[keep] @ aff[:3, :3].T, labels=structure_labels[keep], nifti_affine=aff,
                          nifti_shape=(32, 20, 20))

    both = mask_boundary_cloud(cloud_of(np.ones(len(ijk), bool)), subvoxel_sigma_mm=0.9)
    alone = mask_boundary_cloud(cloud_of(labels == 1), subvoxel_sigma_mm=0.9)
    a_with_b = both.points[both.labels == 1]
    order = np.lexsort(a_with_b.T), np.lexsort(alone.points.T)
    assert len(a_with_b) == len(alone.points)
    assert np.allclose(a_with_b[order[0]], alone.points[order[1]])
    assert both.boundary_smoothing_mm2 > 0 and not np.allclose(alone.points % 0.75, 0)  # they did move off the faces
    merged = mask_boundary_cloud(cloud_of(np.ones(len(ijk), bool), np.ones(len(ijk), int)), subvoxel_sigma_mm=0.9)
    a_merged = merged.points[merged.points[:, 0] < 16 * 1.5]
    assert np.abs(a_merged[np.lexsort(a_merged.T)] - alone.points[order[1]]).max() > 0.1
