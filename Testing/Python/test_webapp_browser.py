"""The web app in a real headless Chromium (Debian's ``chromium``, driven by
Playwright with ``executable_path``): the whole FluoTomo workflow by clicks,
the overlay checked in the screenshot's pixels, UI latency measured while the
reconstruction runs, and the single-user session rule with several browser
contexts.  Screenshots are kept in ``test-artifacts/browser/``."""

import json
import os
import re
import shutil
import socket
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytestmark = [pytest.mark.browser, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]
ARTIFACTS = ROOT / "test-artifacts" / "browser"


def _chromium():
    path = os.environ.get("FLUO_CHROMIUM") or shutil.which("chromium") or shutil.which("chromium-browser")
    if not path:
        if os.environ.get("CI"):
            pytest.fail("Debian's chromium is not installed (`make system-deps` installs it)")
        pytest.skip("chromium not installed: apt-get install chromium")
    return path


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# the app's workspace: the UI takes paths inside it (issue #21)
WORKSPACE = {}


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """The app's address with this launch's secret (``fluo app`` prints it)."""
    port = _free_port()
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    log = open(ARTIFACTS / "server.log", "w")
    workspace = tmp_path_factory.mktemp("workspace")
    WORKSPACE["root"] = workspace
    proc = subprocess.Popen([sys.executable, "-m", "fluoapp", "app", "--port", str(port),
                             "--workspace", str(workspace)],
                            cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
    t0 = time.time()
    url = None
    while time.time() - t0 < 180 and url is None:
        if proc.poll() is not None:
            pytest.fail(f"app exited ({proc.returncode}); see {ARTIFACTS / 'server.log'}")
        m = re.search(r"FluoGuide app: (http://\S+/\?secret=\S+)", (ARTIFACTS / "server.log").read_text())
        url = m.group(1) if m else None
        time.sleep(0.5)
    if url is None:
        proc.kill()
        pytest.fail("app did not start in 180 s")
    yield url
    proc.terminate()
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        proc.kill()
    log.close()


@pytest.fixture(scope="module")
def page(server):
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=_chromium(), headless=True,
                                    args=["--no-sandbox"])
        pg = browser.new_page(viewport={"width": 1500, "height": 950})
        pg.goto(server)
        pg.wait_for_selector("#tomo-load", timeout=60000)
        yield pg
        browser.close()


def _text(pg, sel):
    return pg.inner_text(sel)


def _wait_text(pg, sel, needle, timeout_ms=60000):
    from playwright.sync_api import TimeoutError as PlaywrightTimeout

    try:
        pg.wait_for_function(
            f"document.querySelector({sel!r}) && "
            f"document.querySelector({sel!r}).innerText.includes({needle!r})",
            timeout=timeout_ms)
    except PlaywrightTimeout:
        # say what the page showed instead: a timeout alone cannot be diagnosed
        shown = pg.evaluate(f"(document.querySelector({sel!r}) || {{}}).innerText")
        message = pg.evaluate("(document.querySelector('#fluo-message') || {}).innerText")
        log = (ARTIFACTS / "server.log").read_text(errors="replace").splitlines()[-15:]
        raise AssertionError(f"{sel} never showed {needle!r} in {timeout_ms / 1000:.0f} s; "
                             f"it showed {shown!r}; the message bar: {message!r}; "
                             "the server's log ends:\n" + "\n".join(log)) from None


def _ping_ms(pg):
    before = _text(pg, "#fluo-ping-count")
    t = time.perf_counter()
    pg.click("#fluo-ping")
    pg.wait_for_function(f"document.querySelector('#fluo-ping-count').innerText !== {before!r}",
                         timeout=20000)
    return 1000 * (time.perf_counter() - t)


def _views(pg, name):
    """Screenshots of the rendered views (remote-rendered <img> elements) as arrays."""
    from io import BytesIO

    from PIL import Image

    out = []
    for k, el in enumerate(pg.query_selector_all("img.image-display-area")):
        png = el.screenshot(path=str(ARTIFACTS / f"{name}-view{k}.png"))
        out.append(np.asarray(Image.open(BytesIO(png)).convert("RGB")).astype(int))
    return out


def _hot_pixels(img):
    """Pixels of the yield colour map (red/orange/yellow), not grey CT or green outline."""
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    return int(np.count_nonzero((r > 140) & (r - b > 80) & (r >= g)))


# the tube phantom reconstructed by the app: 7.0 GB measured on the uniform grid; the
# job alone is now 1.2 GB on the graded mesh (test_webapp.py), not re-measured here
@pytest.mark.heavy(gb=8)
def test_fluotomo_workflow_in_the_browser(page):
    pg = page
    idle = [_ping_ms(pg) for _ in range(5)]
    pg.click("#tomo-load")
    _wait_text(pg, "#fluo-message", "Loaded")
    pg.screenshot(path=str(ARTIFACTS / "01-loaded.png"))
    pg.click("#tomo-threshold")
    _wait_text(pg, "#tomo-segments", "liquid")
    pg.click("#tomo-threshold")
    _wait_text(pg, "#tomo-segments", "tube")
    pg.screenshot(path=str(ARTIFACTS / "02-segmented.png"))
    pg.click("#tomo-labels")
    _wait_text(pg, "#tomo-regions", "tube")
    pg.click("#tomo-mesh")
    _wait_text(pg, "#tomo-mesh-info", "nodes", 180000)
    pg.wait_for_timeout(1500)
    pg.screenshot(path=str(ARTIFACTS / "03-mesh.png"))
    before = _views(pg, "03-mesh")
    pg.click("#tomo-recon")
    pg.wait_for_timeout(300)
    busy = []
    while len(busy) < 8:
        busy.append(_ping_ms(pg))
        pg.wait_for_timeout(250)
    assert "reconstruction" in _text(pg, "#tomo-job")  # still running while we pinged
    pg.wait_for_selector("#tomo-result", timeout=300000)
    pg.wait_for_timeout(3000)  # the views re-render after the overlay is added
    pg.screenshot(path=str(ARTIFACTS / "04-reconstruction.png"))
    after = _views(pg, "04-reconstruction")
    result = _text(pg, "#tomo-result")
    hot_before = [_hot_pixels(v) for v in before]
    hot_after = [_hot_pixels(v) for v in after]
    report = {"idle_ping_ms": idle, "busy_ping_ms": busy,
              "busy_ping_median_ms": statistics.median(busy), "result": result,
              "hot_pixels_before": hot_before, "hot_pixels_after": hot_after}
    (ARTIFACTS / "workflow.json").write_text(json.dumps(report, indent=2))
    print(json.dumps(report, indent=2))
    # the overlay is in the pixels of the slice views (views 0, 2, 3; view 1 is 3D)
    slice_views = [0, 2, 3]
    assert all(hot_before[k] < 20 for k in slice_views), hot_before
    assert sum(hot_after[k] >= 30 for k in slice_views) >= 2, hot_after
    # and the 3D view shows the iso-surface / sources
    assert hot_after[1] > hot_before[1] + 50
    # a frozen UI would take seconds per round trip; target 200 ms (reported above)
    assert statistics.median(busy) < 1000
    # the threshold slider changes the overlay without a reload
    assert "HP" in result


@pytest.mark.heavy(gb=10)     # HP and SP on issue #17's scene: 9.1 GB measured
def test_own_label_map_from_files_in_the_browser(page, issue_acquisition):
    """Issue #17's scene through the web app: a label map file unlike the tube
    (ellipsoidal body, 6 mm inclusion 4 mm under the curved top, anisotropic
    voxels, direction diag(-1, -1, 1), origin far from zero), optics.json and an
    acquisition folder simulated by ``fluo tomo simulate`` (its own whole-map
    mesh at 'fine': the acquisition the CLI and logic tests grade, conftest.py);
    loaded, meshed and reconstructed by clicks: HP within 15 %, SP within 30 %,
    the half-maximum centroid within 1 mm of the inclusion's centre and the peak
    inside it, in RAS."""
    d = WORKSPACE["root"] / "own"      # the UI takes paths inside its workspace
    d.mkdir(exist_ok=True)
    for f in ("labels.nrrd", "optics.json"):
        shutil.copy(issue_acquisition.dir / f, d / f)
    shutil.copytree(issue_acquisition.acq, d / "acq", dirs_exist_ok=True)
    sc = issue_acquisition.sc
    pg = page
    pg.click("#tool-FluoTomo") if not pg.is_visible("#tomo-own-load") else None
    pg.fill("#tomo-own-labels", "own/labels.nrrd")
    pg.fill("#tomo-own-optics", "own/optics.json")
    pg.fill("#tomo-own-acquisition", "own/acq")
    pg.click("#tomo-own-load")
    _wait_text(pg, "#tomo-own-info", "labels [3, 7]", 120000)
    # issue #33: the user's scene is shown like a phantom from the start: the label
    # map in grey tones (not saturated white) with each label outlined, and its
    # surfaces in the 3D view before any reconstruction
    pg.wait_for_timeout(2000)
    pg.screenshot(path=str(ARTIFACTS / "07-own-scene-loaded.png"))
    loaded = _views(pg, "07-own-scene-loaded")
    for k, img in enumerate(loaded):
        lit = img.max(axis=-1) > 40
        white = np.all(img > 235, axis=-1)
        assert lit.mean() > 0.02, (k, lit.mean())             # every view shows something
        assert white.sum() < 0.5 * lit.sum(), (k, white.sum(), lit.sum())   # not white
    assert not pg.is_visible("#tomo-colorbar")                 # no result yet
    pg.fill("#tomo-mesh-size", "0.8")
    pg.click("#tomo-mesh")
    _wait_text(pg, "#tomo-mesh-info", "reconstruction uses this mesh", 600000)
    assert "region 7:" in _text(pg, "#tomo-mesh-info")
    centre = np.asarray(sc["inclusion_centre_ras_mm"])
    report = {}
    for method, tol in (("HP", 0.15), ("SP", 0.30)):
        if method != "HP":
            # Vuetify's select: its field (not the hidden input) opens the menu
            pg.locator(".v-field:has(#tomo-method)").click()
            pg.get_by_role("option", name=method, exact=True).click()
        pg.click("#tomo-recon")
        _wait_text(pg, "#tomo-own-result", f"{method} (FluoTomoYield{method}", 900000)
        pg.wait_for_timeout(2000)
        pg.screenshot(path=str(ARTIFACTS / f"07-own-scene-{method}.png"))
        # the colour bar and the threshold slider, as for a phantom's result
        assert pg.is_visible("#tomo-colorbar")
        assert pg.is_enabled("#tomo-threshold-slider input") if pg.locator(
            "#tomo-threshold-slider input").count() else pg.is_visible("#tomo-threshold-slider")
        after = _views(pg, f"07-own-scene-{method}")
        assert sum(_hot_pixels(v) >= 30 for v in after) >= 2, [_hot_pixels(v) for v in after]
        text = _text(pg, "#tomo-own-result")
        # the 95 % interval, not a bare SD (issue #31)
        assert "95 % interval" in text, text
        report[method] = text
        value = float(text.split("yield ")[1].split(" /mm")[0])
        assert abs(value - 2.6e-3) / 2.6e-3 < tol, (method, text)
        assert "(label 7)" in text, text
        cen = np.array([float(v) for v in text.split("centroid RAS ")[1].split(";")[0].split(",")])
        assert np.linalg.norm(cen - centre) < 1.0, (method, cen, centre)
        peak = np.array([float(v) for v in text.split(" at RAS ")[1].split(" (")[0].split(",")])
        assert np.linalg.norm(peak - centre) <= sc["inclusion_radius_mm"] + 0.1, (peak, centre)
    (ARTIFACTS / "own-scene.json").write_text(json.dumps(report, indent=2))


def test_an_error_is_a_message_not_a_dead_page(page):
    pg = page
    pg.fill("#tomo-lambda", "-3")
    pg.click("#tomo-recon")
    _wait_text(pg, "#fluo-message", "lambda")
    pg.screenshot(path=str(ARTIFACTS / "05-error-message.png"))
    assert _ping_ms(pg) < 5000  # the page still talks to the server


def test_nav_panel_streams_tracked_frames(page):
    pg = page
    pg.click("#tool-FluoNav")
    pg.wait_for_selector("#nav-stream", timeout=10000)
    pg.fill("#nav-seconds", "4")
    pg.click("#nav-stream")
    pg.wait_for_selector("#nav-corrected", timeout=60000)
    first = pg.inner_text("#nav-count")
    pg.wait_for_function(f"document.querySelector('#nav-count').innerText !== {first!r}",
                         timeout=30000)               # frames keep coming
    pg.screenshot(path=str(ARTIFACTS / "06-nav-stream.png"))
    text = pg.inner_text("#nav-images")
    assert "corrected" in text and "tracker frame" in text
    src = pg.get_attribute("#nav-raw", "src")
    assert src and src.startswith("data:image/png;base64,")


# Markup and a Vue template in names the app shows (issue #34, item 9): each sets
# window.__xss if the page runs it (a handler's bare assignment makes a global);
# the page must show each as text. No "." in them: a node is named by its file's
# name up to the first dot.
XSS = {
    "node": "<img src=x onerror=__xss=1>",                        # a label map file -> its node
    "region": "<svg onload=__xss=2>",                             # optics.json's region names
    "template": "{{constructor.constructor('__xss=3')()}}",       # Vue would evaluate it
    "segment": "<b onmouseover=__xss=4 id=xss-seg>bold</b>",      # a segment's name
    "file": "<img src=y onerror=__xss=5>",                        # a file name in a message
}


def _no_script_ran(pg, where):
    pg.wait_for_timeout(800)          # an <img onerror> fires after its failed load
    assert pg.evaluate("window.__xss") is None, where
    assert pg.query_selector("#xss-seg") is None, where        # no element made of a name


def test_hostile_names_show_as_text_in_every_panel(page, own_scene):
    """Names from files (a label map file and so its node, optics.json's region
    names, a segment typed in the panel, file names in messages) hold markup and a
    Vue template: shown as text in every panel (FluoTomo's own-scene info, regions,
    segments and messages, the segment editor's list, FluoCalib's messages, FluoNav),
    never run: ``window.__xss`` stays undefined and the literal text is on the page.
    Screenshots: 10-hostile-names-*.png."""
    pg = page
    d = WORKSPACE["root"] / "xss"
    d.mkdir(exist_ok=True)
    shutil.copy(own_scene.labels, d / f"{XSS['node']}.nrrd")
    optics = json.loads(own_scene.optics.read_text())
    optics["names"] = {"3": XSS["region"], "7": XSS["template"]}
    (d / "optics.json").write_text(json.dumps(optics))
    shutil.copytree(own_scene.acq, d / "acq", dirs_exist_ok=True)

    pg.click("#tool-FluoTomo") if not pg.is_visible("#tomo-own-load") else None
    # a message naming a file the user typed (not found), then the scene itself
    pg.fill("#tomo-own-labels", f"xss/{XSS['file']}.nrrd")
    pg.fill("#tomo-own-optics", "xss/optics.json")
    pg.fill("#tomo-own-acquisition", "xss/acq")
    pg.click("#tomo-own-load")
    _wait_text(pg, "#fluo-message", XSS["file"])
    _no_script_ran(pg, "FluoTomo: a message naming a file")
    pg.fill("#tomo-own-labels", f"xss/{XSS['node']}.nrrd")
    pg.click("#tomo-own-load")
    _wait_text(pg, "#tomo-own-info", XSS["node"], 120000)
    _wait_text(pg, "#fluo-message", "Loaded your scene: " + XSS["node"])
    regions = _text(pg, "#tomo-regions")
    assert XSS["region"] in regions and XSS["template"] in regions, regions
    # a segment named by markup, by threshold on the label map (labels 3 and 7)
    pg.fill("#tomo-seg-name", XSS["segment"])
    pg.fill("#tomo-seg-min", "0.5")
    pg.fill("#tomo-seg-max", "100")
    pg.click("#tomo-threshold")
    _wait_text(pg, "#tomo-segments", XSS["segment"])
    _wait_text(pg, "#fluo-message", f"Segment '{XSS['segment']}'")
    _no_script_ran(pg, "FluoTomo")
    pg.screenshot(path=str(ARTIFACTS / "10-hostile-names-tomo.png"))
    # the segment editor lists the segment by its name
    pg.click("#tool-segment-editor")
    pg.wait_for_function("document.body.innerText.includes(%s)" % json.dumps(XSS["segment"]),
                         timeout=20000)
    _no_script_ran(pg, "segment editor")
    pg.screenshot(path=str(ARTIFACTS / "10-hostile-names-segment-editor.png"))
    # FluoCalib: a glob and a scene file named by markup, in its messages
    pg.click("#tool-FluoCalib")
    pg.fill("#calib-images", f"xss/{XSS['file']}*.png")
    pg.click("#calib-run")
    _wait_text(pg, "#fluo-message", XSS["file"])
    _no_script_ran(pg, "FluoCalib: images")
    pg.fill("#calib-save-path", f"xss/{XSS['node']}.mrml")
    pg.click("#calib-save")
    _wait_text(pg, "#fluo-message", f"Scene saved to xss/{XSS['node']}.mrml", 60000)
    assert (d / f"{XSS['node']}.mrml").is_file()
    _no_script_ran(pg, "FluoCalib: save")
    pg.screenshot(path=str(ARTIFACTS / "10-hostile-names-calib.png"))
    # FluoNav: the surface of the scene's label map, named in its info and message
    # (the phantom's CBCTLabels where the workflow test made one, else the node above)
    pg.click("#tool-FluoNav")
    pg.click("#nav-surface")
    _wait_text(pg, "#nav-surface-info", "TissueSurface of ", 120000)
    info = _text(pg, "#nav-surface-info")
    assert XSS["node"] in info or "TissueSurface of CBCTLabels" in info, info
    _no_script_ran(pg, "FluoNav")
    pg.screenshot(path=str(ARTIFACTS / "10-hostile-names-nav.png"))
    # leave the phantom's CBCT shown, as the earlier tests left the page
    pg.click("#tool-FluoTomo")
    pg.click("#tomo-load")
    _wait_text(pg, "#fluo-message", "Loaded the")


def test_one_browser_session_at_a_time(page, server):
    """trame shares one state per server: a second browser context is refused while
    the first is open (a page that says so), and gets in by itself once the first
    closes; a page without the secret never gets a session."""
    browser = page.context.browser
    bare = server.split("?")[0]
    second = browser.new_context(viewport={"width": 1200, "height": 800})
    p2 = second.new_page()
    r = p2.goto(server)
    assert r.status == 409
    assert "open in another browser session" in p2.inner_text("#fluo-single-user")
    p2.screenshot(path=str(ARTIFACTS / "07-second-session-refused.png"))
    # the first session ends: the waiting page retries on its own and gets the app
    page.close()
    p2.wait_for_selector("#fluo-ping", timeout=90000)   # the app bar: any panel
    p2.screenshot(path=str(ARTIFACTS / "08-second-session-admitted.png"))
    third = browser.new_context()
    p3 = third.new_page()
    assert p3.goto(bare).status == 409              # the second one holds the app now
    second.close()
    # nobody holds it: a page without the secret loads the client but no session ...
    assert p3.goto(bare).status == 200
    p3.wait_for_timeout(8000)
    assert p3.query_selector("#fluo-ping") is None
    # ... and takes no slot: the next page with the secret gets in
    fourth = browser.new_context()
    p4 = fourth.new_page()
    assert p4.goto(server).status == 200
    p4.wait_for_selector("#fluo-ping", timeout=90000)
    # and sees the scene: the views render for it (the CBCT of the first session)
    p4.wait_for_timeout(5000)
    p4.screenshot(path=str(ARTIFACTS / "09-next-session.png"))
    lit = [int(np.count_nonzero(v.sum(axis=2) > 150)) for v in _views(p4, "09-next-session")]
    assert sum(n > 1000 for n in lit) >= 2, lit
    for ctx in (third, fourth):
        ctx.close()
