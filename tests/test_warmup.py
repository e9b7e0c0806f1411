"""`ribpull warmup`: numba's kernels compiled once into its cache, and loaded, not compiled, after.

Each process runs the warm-up on a small 3 x 3 x 4 mm label map against its own empty numba cache
(NUMBA_CACHE_DIR), then counts cache hits and misses over every numba kernel the run used. The first
process compiles (misses). The second must load every kernel it calls from the cache: no miss at all.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

PROBE = r"""
import json, sys
from numba.core.registry import CPUDispatcher
from ribpull_core.warmup import WarmupInput, warm_up

runs = warm_up(inputs=(WarmupInput("map-3mm", spacing_mm=(3.0, 3.0, 4.0)),), log=lambda line: None)
kernels = []
for name, module in list(sys.modules.items()):
    if not name.startswith("ribpull_core"):
        continue
    for obj in vars(module).values():
        if isinstance(obj, CPUDispatcher) and obj.signatures:
            kernels.append(obj)
kernels = {obj.py_func.__module__ + "." + obj.__name__: obj for obj in kernels}  # by defining module
hits = sum(sum(obj.stats.cache_hits.values()) for obj in kernels.values())
misses = sum(sum(obj.stats.cache_misses.values()) for obj in kernels.values())
print(json.dumps({"kernels": sorted(kernels), "hits": hits, "misses": misses, "runs": runs}))
"""


def _probe(cache_dir) -> dict:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache_dir)}
    r = subprocess.run([sys.executable, "-c", PROBE], check=False, env=env, capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


def test_warm_up_fills_the_cache_and_a_new_process_compiles_nothing(tmp_path):
    cache = tmp_path / "numba-cache"
    first = _probe(cache)
    assert first["runs"][0]["input"] == "map-3mm" and first["runs"][0]["seconds"] > 0
    assert first["misses"] > 0, "an empty cache must have been compiled into"
    # kernels of the whole path: the hash grid, the SDF grid and closest points, a 3 mm map's section quadrics
    for kernel in ("ribpull_core.fields.grid_kernels._encode_forward2", "ribpull_core.sdf_kernels.relax_step",
                   "ribpull_core.triangle_distance.closest_points", "ribpull_core.section_quadrics.taubin_quadric"):
        assert kernel in first["kernels"], (kernel, first["kernels"])
    assert any(p.suffix == ".nbi" for p in cache.rglob("*")), "numba wrote no cache index"
    second = _probe(cache)
    # kernels called only from other kernels are inside their callers' cached code: a process that
    # loads the callers never compiles them, so the second process lists fewer
    assert set(second["kernels"]) <= set(first["kernels"])
    for kernel in ("ribpull_core.fields.grid_kernels._encode_forward2", "ribpull_core.sdf_kernels.relax_step",
                   "ribpull_core.triangle_distance.closest_points"):
        assert kernel in second["kernels"], (kernel, second["kernels"])
    assert second["misses"] == 0, f"{second['misses']} compiles after the warm-up"
    assert second["hits"] >= len(second["kernels"])
