#!/usr/bin/env bash
# Where a `ribpull fit --device cuda` spends its time on a lent GPU machine: checks FusedAdam on
# CUDA against torch.optim.Adam (tests/test_optimizer.py), fits a 60k-point phantom once (compiles
# and caches the numba kernels), then again under cProfile. Writes to $OUT: log.txt, profile.txt
# (cumulative and own time), metrics.json of the profiled fit.
set -uo pipefail
OUT=${OUT:-/tmp/ribpull-device-out}
mkdir -p "$OUT"
exec > >(tee "$OUT/log.txt") 2>&1
source benchmarks/device_env.sh
# --noconftest: the tests' conftest starts the service, whose packages (Celery, ...) the image lacks
python3 -m pytest -q -p no:cacheprovider --noconftest tests/test_optimizer.py
ribpull phantom /tmp/ph60 --points 60000 --noise 0.3
time ribpull fit /tmp/ph60/points.ply -o /tmp/fit60a --device cuda -q
time python3 - <<'PY' > "$OUT/profile.txt"
import cProfile, pstats, time
from ribpull_core.pipeline import PipelineOptions, run_pipeline
t = time.perf_counter()
prof = cProfile.Profile()
prof.enable()
run_pipeline("/tmp/ph60/points.ply", "/tmp/fit60b", PipelineOptions(device="cuda"))
prof.disable()
print(f"run_pipeline {time.perf_counter() - t:.2f} s")
stats = pstats.Stats(prof)
stats.sort_stats("cumulative").print_stats(70)
stats.sort_stats("tottime").print_stats(40)
PY
cp /tmp/fit60b/metrics.json "$OUT/" 2>/dev/null
python3 -c "import json; m = json.load(open('/tmp/fit60b/metrics.json')); print(m['timings_s'], m['fit_seconds'])"
echo "device profile done"
