#!/usr/bin/env bash
# Builds .whl/ (git-ignored through .git/info/exclude), the packages a lent GPU machine's image
# lacks, for its Python 3.12 (benchmarks/device_env.sh installs them there). Run here, from the
# repository root, with PyPI reachable:
# - wheels of the project's pins: trimesh, robust-laplacian, nibabel, pygltflib (+ dataclasses-json,
#   marshmallow, deprecated) and pydicom;
# - pymeshlab312.tgz: pymeshlab's 106 MB wheel cut to what the screened-Poisson baseline loads (the
#   screened-Poisson and base-I/O plugins and the libraries they link, found with ldd), plus the GL /
#   X libraries of this machine that the bare image lacks (lib/sys, put on LD_LIBRARY_PATH there):
#   ~29 MB, under the 64 MiB a device call carries.
set -euo pipefail
cd "$(git rev-parse --show-toplevel)"
grep -qx "/.whl/" .git/info/exclude || echo "/.whl/" >> .git/info/exclude
rm -rf .whl && mkdir .whl
fetch() {
    python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
        --platform manylinux_2_35_x86_64 --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 \
        --platform manylinux2014_x86_64 -d "$1" "${@:2}"
}
fetch .whl trimesh==5.2.0 robust-laplacian==1.1.0 nibabel==5.4.2 pygltflib==1.16.5 dataclasses-json \
    marshmallow deprecated pydicom==3.0.2

work=$(mktemp -d)
fetch "$work" pymeshlab==2025.7.post1
(cd "$work" && unzip -q pymeshlab-*.whl && mv pymeshlab-*.data/purelib/pymeshlab . \
    && rm -rf pymeshlab-*.data pymeshlab-*.dist-info pymeshlab-*.whl pymeshlab/tests)
lib="$work/pymeshlab/lib"
find "$lib/plugins" -type f ! -name 'libfilter_screened_poisson.so' ! -name 'libio_base.so' -delete
keep=$(ldd "$work"/pymeshlab/pmeshlab*.so "$lib"/plugins/*.so | awk -v d="$lib" 'index($3, d) == 1 {print $3}' \
       | xargs -n1 basename | sort -u)
for f in "$lib"/*; do
    [ -f "$f" ] && ! grep -qx "$(basename "$f")" <<< "$keep" && rm -f "$f"
done
mkdir -p "$lib/sys"
for l in libGL.so.1 libGLX.so.0 libGLdispatch.so.0 libOpenGL.so.0 libX11.so.6 libXau.so.6 libXdmcp.so.6 \
         libbsd.so.0 libmd.so.0 libxcb.so.1 libcom_err.so.2; do
    cp -L "/lib/x86_64-linux-gnu/$l" "$lib/sys/"
done
tar czf .whl/pymeshlab312.tgz -C "$work" pymeshlab
rm -rf "$work"
du -sh .whl
