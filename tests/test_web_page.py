"""The web page (app/routers/web.py, app/web/static/) in a real browser against the real service.

Debian's `chromium` (installed with apt-get when missing and we are root) driven by Playwright for
Python through its executable path (Playwright's own browser download cannot work offline), headless,
with SwiftShader as the software WebGL. The service is the session `service` stack (Redis + Celery
worker + uvicorn, API keys on). Where the browser, Playwright or the vendored three.js cannot be had,
the browser tests are skipped with a loud reason; the HTTP checks of the page run regardless.

RIBPULL_WEB_SCREENSHOT=<path.png> also saves a screenshot of the finished job's page there (the one
in docs/ was made so).
"""

from __future__ import annotations

import base64
import hashlib
import io
import os
import re
import shutil
import sys
import time
import warnings
from pathlib import Path

import pytest
import servicekit

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "scripts"))

import build_web

pytestmark = pytest.mark.service

#: headless Chromium with software WebGL (no GPU here); --no-sandbox because the tests run as root
CHROMIUM_ARGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--no-sandbox",
                 "--disable-dev-shm-usage"]
FINISHED = ("succeeded", "failed", "canceled")
#: how long a smoke job may take to start and finish: ~1 min on a quiet 2-core machine, several when the
#: machine is busy or the shared worker still has an earlier test's job
JOB_WAIT_S = 420


def skip_loudly(why: str):
    msg = f"web page browser tests SKIPPED: {why}"
    warnings.warn(msg, stacklevel=2)
    print("\n" + "!" * 78 + "\n" + msg + "\n" + "!" * 78, file=sys.stderr)
    pytest.skip(msg)


def chromium_executable() -> str | None:
    """Debian's chromium, installed with apt-get when missing and we are root (once: then it is there)."""
    return shutil.which("chromium-browser") or build_web.debian_binary("chromium", "chromium", quiet=True)


@pytest.fixture(scope="module")
def launch_chromium():
    """launch(extra_args=()) -> a headless Debian chromium under Playwright; all closed at the end."""
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        skip_loudly("Playwright for Python is not installed (it is in the dev extra: `make install`)")
    exe = chromium_executable()
    if exe is None:
        skip_loudly("no chromium here and apt-get could not install it (needs root and Debian's repositories)")
    if not build_web.is_current() and not build_web.build():
        skip_loudly("three.js could not be vendored (scripts/build_web.py: npm ci failed or npm is missing)")
    launched = []
    with sync_playwright() as pw:
        def launch(extra_args=()):
            launched.append(pw.chromium.launch(executable_path=exe, args=[*CHROMIUM_ARGS, *extra_args],
                                               headless=True))
            return launched[-1]

        yield launch
        for b in launched:
            b.close()


@pytest.fixture(scope="module")
def browser(launch_chromium):
    return launch_chromium()


@pytest.fixture
def page(browser, service):
    ctx = browser.new_context(viewport={"width": 1280, "height": 900}, accept_downloads=True)
    pg = ctx.new_page()
    pg.set_default_timeout(30_000)
    errors: list[str] = []
    pg.on("pageerror", lambda exc: errors.append(str(exc)))
    yield pg
    ctx.close()
    assert not errors, f"uncaught errors in the page: {errors}"


def enter_key(pg, url: str, key: str = servicekit.KEY_A) -> None:
    pg.goto(url + "/")
    pg.fill("#api-key", key)
    pg.click("#key-form button[type=submit]")
    pg.wait_for_function("() => document.getElementById('key-state').textContent.includes('API key set')")
    # the key's job list has answered (rows, or 'No jobs yet'): a submit before that could take an
    # older job of the session's service, shown late, for the new one
    pg.wait_for_function("() => document.querySelector('#jobs tbody tr') !== null"
                         " || !document.getElementById('jobs-empty').hidden")


def row(pg, job_id: str):
    return pg.locator(f'#jobs tbody tr[data-job-id="{job_id}"]')


def submit_through_form(pg, path: Path, preset: str = "smoke", iterations: int | None = None) -> str:
    """Submit `path` with the form on `/` and return the new job's id (the newest row).
    `iterations`: typed into the form's iterations field (None leaves it empty: the preset's)."""
    before = set(pg.eval_on_selector_all("#jobs tbody tr", "rows => rows.map(r => r.dataset.jobId)"))
    pg.set_input_files("#file", str(path))
    pg.select_option("#preset", preset)
    pg.fill("#iterations", "" if iterations is None else str(iterations))
    pg.click("#submit")
    pg.wait_for_function(
        "before => [...document.querySelectorAll('#jobs tbody tr')].some(r => !before.includes(r.dataset.jobId))",
        arg=list(before))
    ids = pg.eval_on_selector_all("#jobs tbody tr", "rows => rows.map(r => r.dataset.jobId)")
    return next(i for i in ids if i not in before)


def wait_status(pg, selector_status: str, want: tuple[str, ...], timeout_s: float = 30) -> str:
    """Wait until the page shows one of `want` (`selector_status`: a JS expression giving the shown status).
    Predicates are functions: the page's CSP (no 'unsafe-eval') blocks Playwright's string predicates."""
    pg.wait_for_function(f"want => want.includes({selector_status})", arg=list(want), timeout=timeout_s * 1000)
    return pg.evaluate(selector_status)


# --- HTTP: the page's routes keep the API's hardening --------------------------------------------


def test_page_routes_are_open_hardened_and_outside_the_api_schema(service):
    with service.client(key=None) as c:
        for path in ("/", "/jobs/0123456789abcdef0123456789abcdef"):
            r = c.get(path)
            assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
            csp = r.headers["content-security-policy"]
            assert "default-src 'none'" in csp and "frame-ancestors 'none'" in csp and "unsafe" not in csp
            assert r.headers["x-content-type-options"] == "nosniff" and r.headers["x-frame-options"] == "DENY"
        # the inline import map is the one inline script, allowed by its hash (no 'unsafe-inline')
        import_map = re.search(r'<script type="importmap">(.*?)</script>', c.get("/jobs/x").text, re.DOTALL)
        digest = base64.b64encode(hashlib.sha256(import_map.group(1).encode()).digest()).decode()
        assert f"'sha256-{digest}'" in csp
        js = c.get("/ui/vendor/three/build/three.module.js")
        assert js.status_code == 200 and js.headers["content-type"].startswith("text/javascript"), js.text[:200]
        for bad in ("/ui/../app/main.py", "/ui/%2e%2e/routers/web.py", "/ui/vendor/.stamp", "/ui/nope.js"):
            servicekit.assert_problem(c.get(bad), 404)
        assert c.get("/v1/jobs").status_code == 401  # the data stays behind the key
        paths = c.get("/openapi.json").json()["paths"]
        assert "/" not in paths and not any(p.startswith(("/ui", "/jobs")) for p in paths)


# --- in the browser --------------------------------------------------------------------------------


def test_bad_upload_shows_the_problem_title_and_detail(page, service, tmp_path):
    page.goto(service.url + "/")
    # no key yet: the page says the service wants one, with the API's own words
    page.wait_for_selector("#jobs-error:not([hidden])")
    assert "Unauthorized" in page.inner_text("#jobs-error")
    assert "needs an API key" in page.inner_text("#key-state")
    enter_key(page, service.url)
    bad = tmp_path / "lying.ply"
    bad.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 5000\nproperty float x\nproperty float y\n"
                    b"property float z\nend_header\n1 2 3\n4 5 6\n")
    with service.client() as c:
        want = servicekit.assert_problem(servicekit.submit(c, bad, servicekit.SMOKE))
    before = page.locator("#jobs tbody tr").count()
    # dropped on the form, as a person would (a drop event carrying the file)
    page.evaluate("""([name, text]) => {
        const dt = new DataTransfer();
        dt.items.add(new File([text], name));
        document.getElementById('upload-section').dispatchEvent(
          new DragEvent('drop', {dataTransfer: dt, bubbles: true, cancelable: true}));
      }""", [bad.name, bad.read_text()])
    assert page.inner_text("#upload-state") == f"ready: {bad.name}"
    page.select_option("#preset", "smoke")
    page.fill("#labels", "1-x")  # refused by the page itself, with what to type instead
    page.click("#submit")
    page.wait_for_selector("#upload-error:not([hidden])")
    assert "labels: '1-x' is not a number or a range like 1-24" in page.inner_text("#upload-error")
    page.fill("#labels", "")
    page.fill("#iterations", "2.5")
    page.click("#submit")
    page.wait_for_function("() => document.getElementById('upload-error').textContent.includes('iterations')")
    assert "iterations: '2.5' is not a whole number of at least 1" in page.inner_text("#upload-error")
    page.fill("#iterations", "")
    page.click("#submit")
    page.wait_for_selector("#upload-error .problem-title:not(:text-is('Error'))")
    page.wait_for_selector("#upload-error:not([hidden])")
    assert page.inner_text("#upload-error .problem-title") == want["title"]
    assert page.inner_text("#upload-error .problem-detail") == want["detail"]
    assert page.locator("#jobs tbody tr").count() == before  # nothing was queued


#: the fit the page watches in test_submit_watch_view_pick_download_cancel (smoke preset)
WATCHED_ITERATIONS = 3 * servicekit.LONG["iterations"]


def test_submit_watch_view_pick_download_cancel(page, launch_chromium, service, sample_ply, tmp_path):
    url = service.url
    enter_key(page, url)

    # 1. two uploads through the form; the second waits behind the first (one worker) and is canceled
    #    from the list while queued, then its files are deleted from the list
    # the watched job runs 3x the long smoke schedule so that its fit outlasts several of the page's
    # 1 s polls (at 400 iterations a quiet machine ran it in ~3.5 s, and the page saw only 2)
    job_id = submit_through_form(page, sample_ply, iterations=WATCHED_ITERATIONS)
    queued_id = submit_through_form(page, sample_ply)
    row(page, queued_id).locator("button.cancel").click()
    wait_status(page, f"document.querySelector('#jobs tr[data-job-id=\"{queued_id}\"]').dataset.status",
                ("canceled",))
    row(page, queued_id).locator("button.delete").click()
    page.wait_for_function(
        f"() => document.querySelector('#jobs tr[data-job-id=\"{queued_id}\"]').textContent.includes('files deleted')")
    with service.client() as c:
        assert c.get(f"/v1/jobs/{queued_id}").json()["artifacts_deleted"] is True
        assert c.get(f"/v1/jobs/{job_id}").json()["params"]["iterations"] == WATCHED_ITERATIONS

    # 2. the list shows the running fit (stage, iteration, loss) and its loss curve; then the job's page
    #    while it runs: stage, iteration and the loss curve move
    page.wait_for_function(
        f"""() => {{
          const tr = document.querySelector('#jobs tr[data-job-id="{job_id}"]');
          return tr && /fit \\d+\\/\\d+ · loss/.test(tr.textContent)
            && Number(tr.querySelector('canvas.sparkline').dataset.points) >= 2;
        }}""", timeout=JOB_WAIT_S * 1000)
    row(page, job_id).locator("a").click()
    page.wait_for_url(f"**/jobs/{job_id}")
    seen_iterations: list[int] = []
    deadline = time.monotonic() + JOB_WAIT_S
    while time.monotonic() < deadline:
        status = page.get_attribute("body", "data-status")
        m = re.search(r"fit (\d+)/(\d+)", page.inner_text("#progress-text"))
        if m and (not seen_iterations or int(m.group(1)) != seen_iterations[-1]):
            seen_iterations.append(int(m.group(1)))
        if status in FINISHED:
            break
        time.sleep(0.3)
    assert status == "succeeded", page.inner_text("main")[:2000] + service.tail()
    assert len(seen_iterations) >= 3 and seen_iterations == sorted(seen_iterations), seen_iterations
    assert int(page.get_attribute("#loss-chart", "data-points")) >= 3

    # (the job canceled while running in step 7 starts now: its start-up overlaps steps 3-6)
    with service.client() as c:
        long_id = servicekit.submit(c, sample_ply, servicekit.LONG).json()["id"]

    # 3. the 3D view: a WebGL2 canvas that drew the surface and the ribs, and the 24 ribs listed
    page.wait_for_function("() => window.ribpullViewer !== undefined", timeout=60_000)
    with service.client() as c:
        metrics = c.get(f"/v1/jobs/{job_id}/artifacts/metrics.json").json()
        mesh_glb = c.get(f"/v1/jobs/{job_id}/artifacts/mesh.glb").content
        job = c.get(f"/v1/jobs/{job_id}").json()
    curves = {cv["label"]: cv for cv in metrics["skeleton"]["curves"]}
    assert len(curves) == 24
    state = page.evaluate("window.ribpullViewer.state()")
    assert state["webgl2"] is True and state["glRenderer"], state
    assert state["triangles"] > 10_000, state
    listed = page.eval_on_selector_all("#rib-list li", "lis => lis.map(li => li.dataset.rib)")
    assert sorted(set(listed) - {"other"}) == sorted(curves) and len(curves) == 24
    png = page.locator("#viewer-canvas").screenshot()
    assert_not_blank(png)

    # 4. pick a rib with the mouse: its label, length and radii from metrics.json
    label = "R6"
    point = page.evaluate(f"window.ribpullViewer.screenPoint('{label}')")
    page.mouse.click(point["x"], point["y"])
    page.wait_for_selector("#rib-info[data-rib]")
    picked = page.get_attribute("#rib-info", "data-rib")
    assert picked == label, f"clicked {label}'s middle node, picked {picked}"
    info = page.inner_text("#rib-info")
    assert f"{curves[label]['length_mm']:.1f} mm" in info and f"{curves[label]['mean_radius_mm']:.2f} mm" in info
    assert f"{curves[label]['min_radius_mm']:.2f} mm" in info

    # 5. per-rib visibility: hiding the rib removes its triangles from the next frame
    page.locator(f'#rib-list li[data-rib="{label}"] input[type=checkbox]').uncheck()
    hidden = page.evaluate("window.ribpullViewer.state()")
    assert hidden["visible"][label] is False and hidden["triangles"] < state["triangles"]
    page.locator(f'#rib-list li[data-rib="{label}"] input[type=checkbox]').check()

    # 6. surface metrics and a download link for every artifact (the key travels in a header)
    assert f"{metrics['surface']['cd_l1_mm']:.4g}" in page.inner_text("#surface-metrics")
    links = page.eval_on_selector_all("#downloads a", "as => as.map(a => a.textContent)")
    assert sorted(links) == sorted(a["name"] for a in job["artifacts"]) and len(links) >= 13
    with page.expect_download() as dl:
        page.click("#downloads a:text-is('mesh.glb')")
    assert dl.value.suggested_filename == "mesh.glb"
    assert Path(dl.value.path()).read_bytes() == mesh_glb
    if os.environ.get("RIBPULL_WEB_SCREENSHOT"):
        page.locator(f'#rib-list li[data-rib="{label}"] .rib-name').click()
        page.evaluate("() => window.scrollTo(0, 0)")
        page.screenshot(path=os.environ["RIBPULL_WEB_SCREENSHOT"], full_page=True,
                        clip={"x": 0, "y": 0, "width": 1280, "height": 1080})

    # 7. cancel a running job from its page
    page.goto(f"{url}/jobs/{long_id}")
    page.wait_for_function("() => /fit \\d+\\//.test(document.getElementById('progress-text').textContent)",
                           timeout=JOB_WAIT_S * 1000)
    page.click("#cancel")
    assert wait_status(page, "document.body.dataset.status", FINISHED, timeout_s=30) == "canceled"
    assert "Job canceled" in page.inner_text("#job-problem")

    # 8. a browser without WebGL: the page says the 3D view is unavailable; metrics and downloads stay
    pg = launch_chromium(["--disable-3d-apis"]).new_page()
    enter_key(pg, url)
    pg.goto(f"{url}/jobs/{job_id}")
    pg.wait_for_selector("#viewer .problem")
    assert "3D view unavailable: this browser gives no WebGL context" in pg.inner_text("#viewer")
    assert pg.locator("#downloads a").count() == len(job["artifacts"])
    assert pg.locator("#surface-metrics tr").count() > 10


def assert_not_blank(png: bytes) -> None:
    """The canvas shows a picture: many colours and a good share of pixels unlike the background."""
    import numpy as np
    from PIL import Image

    img = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)
    background = np.median(img.reshape(-1, 3), axis=0)
    drawn = np.abs(img - background).sum(axis=2) > 24
    colours = len(np.unique(img.reshape(-1, 3) // 8, axis=0))
    assert drawn.mean() > 0.03 and colours > 50, (drawn.mean(), colours)
