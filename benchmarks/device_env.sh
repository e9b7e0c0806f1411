# Sourced by the device scripts: installs the wheels the GPU machine's image lacks (carried in .whl/:
# trimesh, robust-laplacian, nibabel, pygltflib and its needs, pydicom, and pymeshlab trimmed to the
# screened-Poisson filter with the GL / X libraries it loads; benchmarks/device_wheels.sh builds .whl/)
# into /tmp/site and sets the paths.
SITE=/tmp/site
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$SITE" .whl/*.whl || exit 3
tar xzf .whl/pymeshlab312.tgz -C "$SITE" || exit 3
export PYTHONPATH="$SITE:$PWD" PYTHONUNBUFFERED=1 LD_LIBRARY_PATH="$SITE/pymeshlab/lib/sys:${LD_LIBRARY_PATH:-}"
ribpull() { python3 -m ribpull_core.cli "$@"; }
