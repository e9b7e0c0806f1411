#!/usr/bin/env bash
# The GPU run of the sweep's speed cases (issue 9: "where a GPU machine is available, measure the
# same run on it"). Run on a lent device machine from the repository root, with the wheels the
# image lacks carried in .whl/ (how they were made: docs/benchmarks.md, "GPU run"). Writes to $OUT:
# device.txt (machine, versions), smoke.json (one `ribpull fit --device cuda`'s metrics), the
# bench's results.csv / results.md, and log.txt.
set -uo pipefail
OUT=${OUT:-/tmp/ribpull-device-out}
mkdir -p "$OUT"
exec > >(tee "$OUT/log.txt") 2>&1
source benchmarks/device_env.sh

{ nvidia-smi -L; nproc; python3 -c "import pymeshlab" || echo "pymeshlab does not load: the bench skips or fails its Poisson rows"
  python3 -c "import sys, torch, numpy, scipy, numba, skimage, trimesh
print(sys.version.split()[0], 'torch', torch.__version__, 'cuda', torch.cuda.is_available(), torch.cuda.get_device_name(0),
      'numpy', numpy.__version__, 'scipy', scipy.__version__, 'numba', numba.__version__, 'skimage', skimage.__version__)"
} | tee "$OUT/device.txt" || exit 4

# smoke: one fit on the GPU, all artifacts, before spending the lease on the bench
ribpull phantom /tmp/ph60 --points 60000 --noise 0.3 || exit 5
time ribpull fit /tmp/ph60/points.ply -o /tmp/fit60 --device cuda --reference /tmp/ph60/truth_mesh.ply || exit 6
python3 -c "import json; m = json.load(open('/tmp/fit60/metrics.json'))
print(json.dumps({k: m.get(k) for k in ('device', 'fit_seconds', 'timings_s', 'reference', 'mesh', 'loss_terms')}, indent=1, default=str))" \
    | tee "$OUT/smoke.json"

# the sweep's speed cases, default (cuda) against its baselines on this machine's CPUs
timeout "${BENCH_TIMEOUT_S:-420}" python3 -m ribpull_core.cli bench --plan sweep --device cuda -o /tmp/gpu \
    --variants n20000-noise0.3 n60000-noise0.3 n200000-noise0.3 mask1.5mm-pv mask0.75x0.75x2.5mm-pv \
    sternum-n60000-noise0.3 sternum-mask1.5mm-pv
# stopped by the limit: results.csv holds the runs that finished; report them
[ -f /tmp/gpu/results.md ] || python3 -m ribpull_core.cli bench --rewrite -o /tmp/gpu > /dev/null
cp /tmp/gpu/results.csv /tmp/gpu/results.md "$OUT/" 2>/dev/null
echo "device run done"
