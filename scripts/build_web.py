"""Vendor the web page's front-end parts (three.js + GLTFLoader + OrbitControls) into the app package.

`make install` runs this after pip. It installs the exact versions of web/package-lock.json with
`npm ci` (the lock's integrity hashes check every tarball) and copies only the files the page loads
into app/web/static/vendor/ (git-ignored: the lock file is the source of truth, not a 3 MB copy).
A stamp (the lock file's sha256) makes later runs a no-op while the lock and the files are unchanged.

Where npm is missing it is installed with apt-get when running as root; where that is impossible the
script says so loudly and exits 0: the API still works and the page says the 3D view is unavailable.
`--check` only reports (exit 1 when the vendored files are missing or stale).
"""

from __future__ import annotations

import argparse
import hashlib
import os
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
WEB_DIR = ROOT / "web"  # package.json + package-lock.json; node_modules/ lands here (git-ignored)
LOCK = WEB_DIR / "package-lock.json"
VENDOR_DIR = ROOT / "app" / "web" / "static" / "vendor"
STAMP = VENDOR_DIR / ".stamp"

#: node_modules-relative files the page imports (GLTFLoader imports the two utils), and the licence
VENDOR_FILES = (
    "three/LICENSE",
    "three/build/three.module.js",
    "three/build/three.core.js",
    "three/examples/jsm/loaders/GLTFLoader.js",
    "three/examples/jsm/controls/OrbitControls.js",
    "three/examples/jsm/utils/BufferGeometryUtils.js",
    "three/examples/jsm/utils/SkeletonUtils.js",
)


def lock_digest() -> str:
    return hashlib.sha256(LOCK.read_bytes()).hexdigest()


def is_current() -> bool:
    """True when every vendored file exists and was copied from the current lock file."""
    try:
        stamped = STAMP.read_text().strip()
    except OSError:
        return False
    return stamped == lock_digest() and all((VENDOR_DIR / f).is_file() for f in VENDOR_FILES)


def debian_binary(binary: str, package: str, quiet: bool = False) -> str | None:
    """`binary` on PATH, else installed from Debian's `package` with apt-get when we are root; None
    when it is missing and cannot be installed. (The web page's browser tests get chromium so too.)"""
    found = shutil.which(binary)
    if found or os.geteuid() != 0 or not shutil.which("apt-get"):
        return found
    print(f"{binary} is missing; installing Debian's {package} with apt-get", file=sys.stderr)
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    out = subprocess.DEVNULL if quiet else None
    subprocess.run(["apt-get", "update"], env=env, check=False, stdout=out, stderr=out)
    subprocess.run(["apt-get", "install", "-y", "--no-install-recommends", package], env=env, check=False,
                   stdout=out, stderr=out)
    return shutil.which(binary)


def build(node_modules: Path | None = None) -> bool:
    """npm ci (unless `node_modules` is given) and copy VENDOR_FILES; False with a warning on failure."""
    if node_modules is None:
        npm = debian_binary("npm", "npm")
        if npm is None:
            warn("npm is not installed and cannot be installed here")
            return False
        cmd = [npm, "ci", "--ignore-scripts", "--no-audit", "--no-fund", "--loglevel=error"]
        proc = subprocess.run(cmd, cwd=WEB_DIR, check=False)
        if proc.returncode != 0:
            warn(f"`{' '.join(cmd[:2])}` in web/ failed (exit {proc.returncode}); is the npm registry reachable?")
            return False
        node_modules = WEB_DIR / "node_modules"
    missing = [f for f in VENDOR_FILES if not (node_modules / f).is_file()]
    if missing:
        warn(f"node_modules lacks {', '.join(missing)}")
        return False
    if VENDOR_DIR.exists():
        shutil.rmtree(VENDOR_DIR)
    for rel in VENDOR_FILES:
        dest = VENDOR_DIR / rel
        dest.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(node_modules / rel, dest)
    STAMP.write_text(lock_digest() + "\n")
    print(f"build_web: vendored {len(VENDOR_FILES)} files into {VENDOR_DIR.relative_to(ROOT)}")
    return True


def warn(why: str) -> None:
    bar = "!" * 78
    print(f"{bar}\nbuild_web: {why}.\nThe API works, but the web page's 3D view is unavailable until "
          f"`make web` succeeds.\n{bar}", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="only report whether the vendored files are current")
    ap.add_argument("--force", action="store_true", help="rebuild even when the stamp is current")
    ap.add_argument("--node-modules", type=Path, default=None,
                    help="copy from this node_modules (already installed, e.g. by a Docker stage) instead of npm ci")
    args = ap.parse_args(argv)
    if args.check:
        ok = is_current()
        print("build_web: vendored files are " + ("current" if ok else "missing or stale: run `make web`"))
        return 0 if ok else 1
    if is_current() and not args.force:
        return 0
    build(args.node_modules)
    return 0


if __name__ == "__main__":
    sys.exit(main())
