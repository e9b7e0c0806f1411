"""preview.png: the mesh and the skeleton from the front and the side (Pillow, no display).

Views assume the input's frame is patient RAS (x left->right, y posterior->anterior, z up), which is
how nibabel reads NIfTI inputs; for other inputs they are simply the +y and +x views with z up.

The mesh is drawn into each view by a z-buffer (`rasterize_triangles`), the skeleton's curves over
it as lines, and the titles with Pillow's default font. Why: matplotlib's 3D polygons cost ~0.6-1.2
s per preview (per-polygon projection, depth sorting and paths for 2 x 60k decimated faces) and
~0.6 s to import, on the pipeline's main thread beside the SDF; this draws every face of both
views in ~0.2 s.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh
from numba import njit
from PIL import Image, ImageDraw, ImageFont

MESH_RGB = np.array([0.86, 0.82, 0.74])  # bone
SKELETON_RGB = (217, 26, 26)
#: (title, (horizontal, vertical, depth) axes) of the two orthographic views, each a signed world
#: axis (0 x, 1 y, 2 z; -1 - k: minus axis k), depth growing towards the camera: anterior (camera on
#: +y, the front in RAS: the patient's right on the viewer's left) and lateral (camera on +x,
#: anterior to the right); z up in both
VIEWS = (("anterior", (-1, 2, 1)), ("lateral", (1, 2, 0)))
#: the PNG's size (pixels): two square views side by side under the titles
WIDTH, HEIGHT = 1200, 600
#: pixels per side of each view's square image, and its top edge
VIEW_PX, VIEW_TOP = 550, 48


def _shade(normals: np.ndarray, view_dir: np.ndarray, rgb: np.ndarray) -> np.ndarray:
    """(F, 3) unit normals -> (F, 3) colours: ambient + two-sided Lambert from the camera side."""
    lam = np.abs(normals @ view_dir)
    return np.clip(rgb[None, :] * (0.35 + 0.65 * lam[:, None]), 0, 1)


@njit(cache=True)
def rasterize_triangles(tri_px, colors, height, width, background):  # pragma: no cover - compiled
    """(F, 3, 3) triangles in pixels (x right, y down, depth: larger is nearer the camera) and (F, 3)
    colours -> (height, width, 3) image (float, background (3,) where no triangle is): each pixel
    whose centre a triangle covers takes the nearest such triangle's colour (depth interpolated)."""
    image = np.empty((height, width, 3))
    for c in range(3):
        image[:, :, c] = background[c]
    zbuf = np.full((height, width), -np.inf)
    for f in range(tri_px.shape[0]):
        x0, y0, z0 = tri_px[f, 0, 0], tri_px[f, 0, 1], tri_px[f, 0, 2]
        x1, y1, z1 = tri_px[f, 1, 0], tri_px[f, 1, 1], tri_px[f, 1, 2]
        x2, y2, z2 = tri_px[f, 2, 0], tri_px[f, 2, 1], tri_px[f, 2, 2]
        area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
        if area == 0.0:
            continue
        i_lo = max(int(np.floor(min(x0, x1, x2))), 0)
        i_hi = min(int(np.ceil(max(x0, x1, x2))), width - 1)
        j_lo = max(int(np.floor(min(y0, y1, y2))), 0)
        j_hi = min(int(np.ceil(max(y0, y1, y2))), height - 1)
        for j in range(j_lo, j_hi + 1):
            py = j + 0.5
            for i in range(i_lo, i_hi + 1):
                px = i + 0.5
                # barycentric weights from the edge functions (either winding)
                w0 = ((x1 - px) * (y2 - py) - (x2 - px) * (y1 - py)) / area
                w1 = ((x2 - px) * (y0 - py) - (x0 - px) * (y2 - py)) / area
                w2 = 1.0 - w0 - w1
                if w0 < 0.0 or w1 < 0.0 or w2 < 0.0:
                    continue
                z = w0 * z0 + w1 * z1 + w2 * z2
                if z > zbuf[j, i]:
                    zbuf[j, i] = z
                    for c in range(3):
                        image[j, i, c] = colors[f, c]
    return image


def _signed_axis(points: np.ndarray, axis: int) -> np.ndarray:
    """(..., 3) points -> (...) their coordinate along a signed axis of VIEWS (-1 - k: minus axis k).
    Of np.eye(3): the axis's unit vector (3,), e.g. a view's direction towards its camera."""
    return points[..., axis] if axis >= 0 else -points[..., -1 - axis]


def _view_pixels(points_mm: np.ndarray, axes: tuple[int, int, int], centre_mm: np.ndarray, half_mm: float,
                 px_per_mm: float) -> np.ndarray:
    """(..., 3) points (mm) -> (..., 3) [x right, y down (pixels of a view's square), depth (mm,
    larger nearer the camera)] in the view of a VIEWS entry's axes whose square spans centre_mm +-
    half_mm."""
    h_axis, v_axis, depth_axis = axes
    x = (_signed_axis(points_mm, h_axis) - _signed_axis(centre_mm, h_axis) + half_mm) * px_per_mm
    y = (half_mm - _signed_axis(points_mm, v_axis) + _signed_axis(centre_mm, v_axis)) * px_per_mm
    return np.stack([x, y, _signed_axis(points_mm, depth_axis)], axis=-1)


def render_preview(
    path,
    mesh_mm: trimesh.Trimesh | None,
    polylines_mm: list[np.ndarray] | None = None,
    title: str = "",
) -> Path:
    """Write a WIDTH x HEIGHT (1200×600) px PNG with anterior and lateral orthographic views, both
    at one scale; returns the path.

    mesh_mm: the surface (mm), every face drawn opaque and flat-shaded (a z-buffer needs no
    decimation: ~0.1 s for 1M faces). polylines_mm: skeleton curves, each (K, 3) mm, drawn over the
    mesh in red.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    polylines = [np.asarray(p, dtype=np.float64).reshape(-1, 3) for p in (polylines_mm or []) if len(p) >= 2]
    pts = []
    tri = fn = None
    if mesh_mm is not None and len(mesh_mm.faces):
        v = np.asarray(mesh_mm.vertices, dtype=np.float64)
        tri = v[np.asarray(mesh_mm.faces, dtype=np.int64)]
        fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-12)
        pts.append(v)
    pts.extend(polylines)

    canvas = Image.new("RGB", (WIDTH, HEIGHT), "white")
    draw = ImageDraw.Draw(canvas)
    font = ImageFont.load_default(size=15)
    if title:
        draw.text((WIDTH / 2, 4), title, fill="black", font=font, anchor="ma")
    if pts:
        allp = np.concatenate(pts)
        lo, hi = allp.min(0), allp.max(0)
        centre, half = (lo + hi) / 2, max(float((hi - lo).max()) / 2, 1e-6) * 1.02
        px_per_mm = VIEW_PX / (2 * half)
    view_width = WIDTH // len(VIEWS)
    for k, (name, axes) in enumerate(VIEWS):
        left = k * view_width + (view_width - VIEW_PX) // 2
        draw.text((k * view_width + view_width / 2, 26), name, fill="black", font=font, anchor="ma")
        if not pts:
            draw.text((k * view_width + view_width / 2, HEIGHT / 2), "nothing to show", fill="black", font=font, anchor="mm")
            continue
        if tri is not None:
            tri_px = _view_pixels(tri, axes, centre, half, px_per_mm)
            image = rasterize_triangles(np.ascontiguousarray(tri_px), _shade(fn, _signed_axis(np.eye(3), axes[2]), MESH_RGB),
                                        VIEW_PX, VIEW_PX, np.ones(3))
            canvas.paste(Image.fromarray(np.round(image * 255).astype(np.uint8)), (left, VIEW_TOP))
        for p in polylines:
            xy = _view_pixels(p, axes, centre, half, px_per_mm)[:, :2] + (left, VIEW_TOP)
            draw.line([tuple(q) for q in xy.tolist()], fill=SKELETON_RGB, width=2, joint="curve")
    canvas.save(path, compress_level=3)
    return path
