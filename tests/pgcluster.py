"""A throw-away PostgreSQL cluster for the service tests: Debian's `postgresql` server binaries,
`initdb` into a temp directory and `postgres` on a free loopback port, both as an unprivileged user
(PostgreSQL refuses to run as root), trust authentication on 127.0.0.1 only, no fsync (test data).

    bindir, why = ensure_postgres()         # installs the `postgresql` package as root when missing
    pg = PgCluster(bindir).start()
    url = pg.create_database("jobs")       # postgresql+psycopg2://ribpull@127.0.0.1:<port>/jobs
    pg.stop()                              # stops the server and removes the cluster directory
"""

from __future__ import annotations

import glob
import os
import pwd
import shutil
import signal
import subprocess
import tempfile
import time
from pathlib import Path

from app import launcher

SUPERUSER = "ribpull"
_install_attempted = {"done": False, "log": ""}


def find_pg_bindir() -> Path | None:
    """The directory holding initdb and postgres: $RIBPULL_PG_BINDIR, Debian's newest
    /usr/lib/postgresql/<major>/bin, or wherever `initdb` on PATH points."""
    cands = [os.environ.get("RIBPULL_PG_BINDIR")]
    cands += sorted(glob.glob("/usr/lib/postgresql/*/bin"), key=lambda p: int(Path(p).parent.name)
                    if Path(p).parent.name.isdigit() else 0, reverse=True)
    found = shutil.which("initdb")
    if found:
        cands.append(str(Path(found).resolve().parent))
    for c in cands:
        if c and (Path(c) / "initdb").is_file() and (Path(c) / "postgres").is_file():
            return Path(c)
    return None


def ensure_postgres() -> tuple[Path | None, str]:
    """(bindir, "") when the server binaries exist, installing Debian's `postgresql` as root when they
    do not (once per test session); else (None, why not)."""
    bindir = find_pg_bindir()
    if bindir is not None:
        return bindir, ""
    if os.geteuid() != 0:
        return None, "PostgreSQL server binaries are missing and the tests are not root: apt-get install postgresql"
    if shutil.which("apt-get") is None:
        return None, "PostgreSQL server binaries are missing and there is no apt-get to install them"
    if not _install_attempted["done"]:
        _install_attempted["done"] = True
        env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
        cmd = ["apt-get", "install", "-y", "--no-install-recommends", "postgresql"]
        out = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=900, check=False)
        if out.returncode != 0:  # stale package lists: refresh once and retry
            subprocess.run(["apt-get", "update"], env=env, capture_output=True, timeout=600, check=False)
            out = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=900, check=False)
        _install_attempted["log"] = (out.stdout + out.stderr)[-2000:]
    bindir = find_pg_bindir()
    if bindir is None:
        return None, "apt-get install postgresql did not provide initdb/postgres:\n" + _install_attempted["log"]
    return bindir, ""


def _unprivileged_user() -> str | None:
    """Who runs initdb/postgres: ourselves unless we are root, then `postgres` (Debian's) or `nobody`."""
    if os.geteuid() != 0:
        return None
    for name in ("postgres", "nobody"):
        try:
            pwd.getpwnam(name)
            return name
        except KeyError:
            continue
    raise RuntimeError("running as root and neither a `postgres` nor a `nobody` user exists")


class PgCluster:
    """One initdb'd cluster in a fresh temp directory, served on 127.0.0.1:<free port>."""

    def __init__(self, bindir: Path, log_dir: Path | None = None):
        self.bindir = Path(bindir)
        self.user = _unprivileged_user()
        # not under pytest's tmp dir: that one is private to root and the server user must enter it
        self.root = Path(tempfile.mkdtemp(prefix="ribpull-pg-"))
        self.data = self.root / "data"
        self.log = (log_dir or self.root) / "postgres.log"
        self.port = launcher.free_port()
        self.proc: subprocess.Popen | None = None

    def _as_server_user(self, path: Path) -> None:
        if self.user is not None:
            pw = pwd.getpwnam(self.user)
            os.chown(path, pw.pw_uid, pw.pw_gid)

    def start(self, timeout: float = 60) -> PgCluster:
        self._as_server_user(self.root)
        out = subprocess.run(
            [str(self.bindir / "initdb"), "-D", str(self.data), "-U", SUPERUSER, "--auth=trust", "-E", "UTF8",
             "--no-sync", "--no-instructions"],
            user=self.user, capture_output=True, text=True, timeout=120, check=False, cwd=self.root)
        if out.returncode != 0:
            raise RuntimeError(f"initdb failed ({out.returncode}):\n{out.stdout}\n{out.stderr}")
        self.log.parent.mkdir(parents=True, exist_ok=True)
        logf = open(self.log, "ab", buffering=0)  # noqa: SIM115 - handed to the child, closed below
        try:
            self.proc = subprocess.Popen(
                [str(self.bindir / "postgres"), "-D", str(self.data), "-p", str(self.port), "-k", str(self.root),
                 "-c", "listen_addresses=127.0.0.1", "-c", "fsync=off", "-c", "synchronous_commit=off",
                 "-c", "full_page_writes=off", "-c", "max_connections=300", "-c", "shared_buffers=64MB"],
                user=self.user, stdin=subprocess.DEVNULL, stdout=logf, stderr=subprocess.STDOUT, cwd=self.root,
                start_new_session=True)
        finally:
            logf.close()
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"postgres exited with {self.proc.returncode}:\n{self.tail()}")
            try:
                self.connect("postgres").close()
                return self
            except Exception:  # noqa: BLE001 - not accepting connections yet
                time.sleep(0.1)
        raise TimeoutError(f"postgres did not accept connections within {timeout} s:\n{self.tail()}")

    def connect(self, dbname: str):
        import psycopg2

        conn = psycopg2.connect(host="127.0.0.1", port=self.port, user=SUPERUSER, dbname=dbname, connect_timeout=3)
        conn.autocommit = True
        return conn

    def create_database(self, name: str, driver: str = "postgresql+psycopg2") -> str:
        """CREATE DATABASE `name`; its SQLAlchemy URL (`driver` postgresql or postgresql+psycopg2)."""
        conn = self.connect("postgres")
        try:
            with conn.cursor() as cur:
                cur.execute(f'CREATE DATABASE "{name}"')
        finally:
            conn.close()
        return self.url(name, driver)

    def url(self, name: str, driver: str = "postgresql+psycopg2") -> str:
        return f"{driver}://{SUPERUSER}@127.0.0.1:{self.port}/{name}"

    def tail(self, n: int = 40) -> str:
        try:
            return "\n".join(self.log.read_text(errors="replace").splitlines()[-n:])
        except OSError:
            return ""

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)  # fast shutdown (SIGTERM would wait for clients)
            try:
                self.proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=10)
        shutil.rmtree(self.root, ignore_errors=True)
