"""Point queries against a finished job's stored field (weights + frame), cached per API process."""

from __future__ import annotations

import threading
from collections import OrderedDict
from pathlib import Path
from typing import Any

import numpy as np

from .schemas import finite_or_none


class FieldCache:
    """LRU of loaded fields: (job id, weights mtime) -> (field, frame, surface distance or None)."""

    def __init__(self, maxsize: int = 4):
        self.maxsize = maxsize
        self._items: OrderedDict[tuple, Any] = OrderedDict()
        self._lock = threading.Lock()
        self._load_lock = threading.Lock()

    def get(self, job_id: str, adir: Path):
        st = (adir / "model.safetensors").stat()
        key = (job_id, st.st_mtime_ns, st.st_size)
        with self._lock:
            if key in self._items:
                self._items.move_to_end(key)
                return self._items[key]
        with self._load_lock:  # one load at a time: each can take a few hundred MB
            with self._lock:
                if key in self._items:
                    return self._items[key]
            value = _load(adir)
            with self._lock:
                for k in [k for k in self._items if k[0] == job_id]:
                    del self._items[k]
                self._items[key] = value
                while len(self._items) > self.maxsize:
                    self._items.popitem(last=False)
            return value

    def drop(self, job_id: str) -> None:
        with self._lock:
            for k in [k for k in self._items if k[0] == job_id]:
                del self._items[k]


def _load(adir: Path):
    from ribpull_core.weights import load_field

    field, frame, _meta = load_field(adir, device="cpu")
    surface = None
    mesh_path = adir / "mesh.ply"
    if mesh_path.is_file():
        import trimesh

        from ribpull_core.sdf import SurfaceDistance

        mesh = trimesh.load(str(mesh_path), process=False, force="mesh")
        if len(getattr(mesh, "faces", ())) > 0:
            surface = SurfaceDistance(mesh, n_samples=200_000)
    return field, frame, surface


def run_query(cache: FieldCache, job_id: str, adir: Path, points_mm: list) -> dict:
    from ribpull_core.sdf import query_field

    field, frame, surface = cache.get(job_id, adir)
    pts = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    out = query_field(field, frame, pts, mesh_mm=surface)
    res = {
        "occupancy": [finite_or_none(v) for v in np.asarray(out["occupancy"]).reshape(-1).tolist()],
        "U": [finite_or_none(v) for v in np.asarray(out["U"]).reshape(-1).tolist()],
        "inside": [bool(v) for v in np.asarray(out["inside"]).reshape(-1).tolist()],
        "sdf_mm": None,
    }
    if out.get("sdf_mm") is not None:
        res["sdf_mm"] = [finite_or_none(v) for v in np.asarray(out["sdf_mm"]).reshape(-1).tolist()]
    return res
