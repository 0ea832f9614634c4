"""The viewer as a person sees it: headless Chromium (software WebGL) driven by Playwright.

Needs Debian's chromium at /usr/bin/chromium and the playwright Python package (never
`playwright install`). In CI::

    apt-get update && apt-get install -y chromium
    pip install -e .[dev]        # viser and playwright

What is drawn is read back with ``client.get_render(..., transport_format="png")``: RGBA
with a transparent background, so "drawn pixels" are pixels with alpha > 0. Every
positive check has a negative control in the same page (0 drawn pixels).
"""

from __future__ import annotations

import colorsys
import re
import time
from pathlib import Path

import numpy as np
import pytest

from ndtom_ti import NdtOmMap

CHROMIUM = Path("/usr/bin/chromium")
if not CHROMIUM.exists():
    pytest.skip(
        "browser tests need Debian's chromium at /usr/bin/chromium: apt-get update && apt-get install -y chromium",
        allow_module_level=True,
    )
pytest.importorskip("viser", reason="the viewer needs viser: pip install ndtom_ti[viewer]")
sync_api = pytest.importorskip("playwright.sync_api", reason="browser tests need playwright: pip install playwright")
viser = pytest.importorskip("viser")

from ndtom_ti.viewer import MapViewer
from ndtom_ti.viewer import geometry as geo

RES = 0.5
FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--enable-unsafe-swiftshader",
]
H, W = 240, 320  # rendered image (the page is 800 x 600)


@pytest.fixture(scope="module")
def room(room_scans):
    m = NdtOmMap(RES)
    for s in room_scans:
        m.insert_scan(s.points, s.T_world_sensor)
    return m


@pytest.fixture(scope="module")
def browser():
    # launch() gives the browser a fresh temporary profile (the fresh --user-data-dir)
    pw = sync_api.sync_playwright().start()
    try:
        b = pw.chromium.launch(executable_path=str(CHROMIUM), args=FLAGS, headless=True)
    except Exception:
        pw.stop()
        raise
    yield b
    b.close()
    pw.stop()


@pytest.fixture
def page(browser):
    ctx = browser.new_context(viewport={"width": 800, "height": 600})
    p = ctx.new_page()
    yield p
    ctx.close()


@pytest.fixture
def viewers():
    made = []
    yield made
    for v in made:
        v.close()


def _viewer(viewers, *args, **kwargs) -> MapViewer:
    v = MapViewer(*args, verbose=False, environment_map=False, **kwargs)
    viewers.append(v)
    return v


def _connect(page, v: MapViewer, timeout: float = 30.0):
    page.goto(v.url)
    t_end = time.monotonic() + timeout
    while not v.server.get_clients():
        assert time.monotonic() < t_end, "the page did not connect to the viewer"
        time.sleep(0.05)
    client = next(iter(v.server.get_clients().values()))
    v.frame()
    return client


def _render(client) -> np.ndarray:
    return client.get_render(H, W, transport_format="png", timeout=30.0)


def _drawn(img: np.ndarray) -> int:
    return int((img[..., 3] > 0).sum())


def _render_until(client, pred, timeout: float = 25.0) -> np.ndarray:
    """Render until ``pred(img)`` (geometry is decoded asynchronously after a change)."""
    t_end = time.monotonic() + timeout
    img = _render(client)
    while not pred(img) and time.monotonic() < t_end:
        time.sleep(0.3)
        img = _render(client)
    return img


def _wait(cond, timeout: float = 15.0) -> bool:
    t_end = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > t_end:
            return False
        time.sleep(0.05)
    return True


def _hues(rgb: np.ndarray) -> np.ndarray:
    """Hue (degrees) of (N, 3) uint8 colours."""
    return np.array([colorsys.rgb_to_hsv(*(c / 255.0))[0] * 360.0 for c in rgb.reshape(-1, 3)])


def _saturated_pixel_hues(img: np.ndarray) -> np.ndarray:
    px = img[img[..., 3] > 200][:, :3].astype(np.float64)
    mx, mn = px.max(axis=1), px.min(axis=1)
    keep = (mx > 40) & ((mx - mn) / np.maximum(mx, 1) > 0.3)  # clearly coloured, not shadow or highlight
    px = px[keep]
    r, g, b = px.T / 255.0
    mx, mn = px.max(axis=1) / 255.0, px.min(axis=1) / 255.0
    d = np.maximum(mx - mn, 1e-9)
    h = np.where(mx == r, ((g - b) / d) % 6, np.where(mx == g, (b - r) / d + 2, (r - g) / d + 4)) * 60.0
    return h


def _hue_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    d = np.abs(a[:, None] - b[None, :]) % 360.0
    return np.minimum(d, 360.0 - d).min(axis=1)


CANVAS_JS = """() => {
    const cs = [...document.querySelectorAll('canvas')];
    if (!cs.length) return null;
    cs.sort((a, b) => b.width * b.height - a.width * a.height);
    const c = cs[0]; const r = c.getBoundingClientRect();
    const W = Math.round(r.width), H = Math.round(r.height);
    const o = document.createElement('canvas'); o.width = W; o.height = H;
    const g = o.getContext('2d'); g.drawImage(c, 0, 0, W, H);
    const d = g.getImageData(0, 0, W, H).data; let n = 0, x0 = W, x1 = -1, y0 = H, y1 = -1;
    for (let y = 0; y < H; y++) for (let x = 0; x < W; x++) if (d[(y * W + x) * 4 + 3] > 0) {
        n++; x0 = Math.min(x0, x); x1 = Math.max(x1, x); y0 = Math.min(y0, y); y1 = Math.max(y1, y); }
    return {drawn: n, width: W, height: H, box: x1 < 0 ? 0 : (x1 - x0 + 1) * (y1 - y0 + 1),
            box_w: x1 < 0 ? 0 : x1 - x0 + 1, page: innerWidth * innerHeight}; }"""


def _canvas(page, pred=lambda c: True, timeout: float = 25.0, settled: bool = False) -> dict:
    """What the page's scene canvas shows (drawn pixels, their bounding box), once ``pred``
    (and, if ``settled``, once three reads in a row agree)."""
    t_end = time.monotonic() + timeout
    seen: list = [page.evaluate(CANVAS_JS)]
    while time.monotonic() < t_end:
        c = seen[-1]
        if c is not None and pred(c) and (not settled or (len(seen) >= 3 and seen[-3] == seen[-2] == c)):
            break
        time.sleep(0.3)
        seen.append(page.evaluate(CANVAS_JS))
    return seen[-1]


@pytest.fixture
def small_page(browser):
    ctx = browser.new_context(viewport={"width": 640, "height": 480})
    p = ctx.new_page()
    yield p
    ctx.close()


def test_map_fills_a_640x480_page_in_height_colours(small_page, room, viewers):
    page = small_page
    # negative control: an empty map draws nothing in the same page size
    empty = _viewer(viewers, NdtOmMap(RES))
    page.goto(empty.url)
    c = _canvas(page, lambda c: c["width"] > 0)
    time.sleep(1.5)
    assert page.evaluate(CANVAS_JS)["drawn"] == 0

    v = _viewer(viewers, room)
    page.goto(v.url)
    c = _canvas(page, lambda c: c["drawn"] > 5000, settled=True)
    # the map, framed at once, fills most of the scene's width beside the panel and a good
    # part of the page (with no camera moved by the test)
    assert c["box_w"] > 0.75 * c["width"], c
    assert c["box"] > 0.2 * c["page"] and c["drawn"] > 0.04 * c["page"], c
    assert c["width"] < 640  # the panel is docked beside the scene, not over it

    # coloured by height: the pixels carry the height colours of the map's Gaussians, several hues of them
    client = next(iter(v.server.get_clients().values()))
    img = _render_until(client, lambda im: _drawn(im) > 3000)
    g = room.gaussians(min_probability=0.5)
    expected = _hues(np.unique(geo.height_colors(g["mean"][:, 2], v.drawn["zrange"]), axis=0))
    hues = _saturated_pixel_hues(img)
    assert len(hues) > 1000
    near = _hue_distance(hues, expected) < 15.0
    assert near.mean() > 0.85, f"only {near.mean():.0%} of the pixels have a height colour"
    bins = np.histogram(hues, bins=6, range=(0, 360))[0]
    assert (bins > 0.03 * len(hues)).sum() >= 3, f"one colour for the whole map: hue histogram {bins}"
    sync_api.expect(page.get_by_text("Colour: height of the Gaussian's mean")).to_be_visible()


def test_controls_a_person_uses(small_page, room, viewers):
    page = small_page
    v = _viewer(viewers, room)
    page.goto(v.url)
    full = _canvas(page, lambda c: c["drawn"] > 5000, settled=True)
    # a map file has no trajectory, latest scan or comparison map: not offered; free cells off
    sync_api.expect(page.get_by_label("Gaussians", exact=True)).to_be_checked()
    assert page.get_by_label("Trajectory", exact=True).count() == 0
    assert page.get_by_label("Latest scan", exact=True).count() == 0
    assert page.get_by_label("Conflicting cells", exact=True).count() == 0
    assert not page.get_by_label("Free cells", exact=True).is_checked()

    # the camera taken far away, then "Frame the map" brings the whole map back
    client = next(iter(v.server.get_clients().values()))
    client.camera.position = (400.0, -400.0, 300.0)
    far = _canvas(page, lambda c: c["drawn"] < 0.2 * full["drawn"])
    assert far["drawn"] < 0.2 * full["drawn"]
    page.get_by_role("button", name="Frame the map").click()
    back = _canvas(page, lambda c: c["box_w"] > 0.75 * c["width"] and c["drawn"] > 0.5 * full["drawn"])
    assert back["box_w"] > 0.75 * back["width"] and back["drawn"] > 0.5 * full["drawn"], (full, back)

    # the height clip keeps the floor only: the walls go, so the drawn box loses their height
    # and fewer pixels are drawn (each count once the canvas has settled). Pixel counts alone
    # vary: when frames come slowly the page may render at a lower pixel ratio, and the
    # upscaled floor's blurred edges then cover ~45% more pixels
    whole = _canvas(page, lambda c: c["drawn"] > 0.5 * full["drawn"], settled=True)
    n_whole = v.drawn["gaussians"]
    lo, _ = v.controls.zlimits
    v.controls.zclip.value = (lo, 0.3)

    def floor_only(c):
        return 0 < c["drawn"] < 0.95 * whole["drawn"] and c["box"] < 0.85 * whole["box"]

    # (the clip redraws the cloud: a frame between the old cloud and the new one may be blank)
    clipped = _canvas(page, floor_only, settled=True, timeout=60.0)
    assert floor_only(clipped), (whole, clipped, v.drawn)
    assert v.drawn["clip"] == (lo, 0.3) and v.drawn["gaussians"] < 0.6 * n_whole, (n_whole, v.drawn)
    sync_api.expect(page.get_by_text(re.compile(r"Height clip: .* to 0\.30 m"))).to_be_visible()


def _outdoor_points(rng) -> np.ndarray:
    """A lidar 1.8 m above flat ground (48 rings out to ~50 m: line-thin Gaussians along the
    rings, as a real lidar's) and six small buildings 150-190 m away (far cells, ~8% of them)."""
    el = np.radians(np.linspace(-25.0, -2.0, 48))
    az = np.radians(np.arange(0.0, 360.0, 0.25))
    E, A = np.meshgrid(el, az, indexing="ij")
    r = 1.8 / np.tan(-E)
    parts = [np.c_[(r * np.cos(A)).ravel(), (r * np.sin(A)).ravel(), np.full(E.size, -1.8)]]
    for k, dist in enumerate((150.0, 160.0, 170.0, 180.0, 190.0, 175.0)):
        a = np.radians(60.0 * k + 10.0)
        n, t = np.array([np.cos(a), np.sin(a)]), np.array([-np.sin(a), np.cos(a)])
        u, z = rng.uniform(-2.0, 2.0, 400), rng.uniform(-1.8, 3.2, 400)
        parts.append(np.c_[dist * n[0] + u * t[0], dist * n[1] + u * t[1], z])
    return np.concatenate(parts)


def _hall_points(rng, n: int = 60000) -> np.ndarray:
    """Points seen from (10, 7, 1.5) (sensor frame) in a 20 x 14 x 4 m hall: floor, walls, flat ceiling."""
    o = np.array([10.0, 7.0, 1.5])
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d > 0, (np.array([20.0, 14.0, 4.0]) - o) / d, -o / d)
    t = np.nanmin(np.where(t > 0, t, np.inf), axis=1)
    return d * t[:, None]


def test_outdoor_map_first_view_and_frame_show_its_bulk(small_page, viewers):
    """norlab at 0.2 m was a white canvas at first sight: its 1-99% box reached far cells, and
    line-thin splats of the lidar's rings faded out from the distance that box needed."""
    rng = np.random.default_rng(5)
    m = NdtOmMap(RES, max_range=250.0)
    T = np.eye(4)
    T[2, 3] = 1.8
    m.insert_scan(_outdoor_points(rng), T)
    n = len(m.gaussians(min_probability=0.5)["n"])
    v = _viewer(viewers, m.snapshot())
    m.close()
    assert v.drawn["geometry"] == "splats" and v.drawn["gaussians"] == n > 4000  # auto: splats, every one
    page = small_page
    page.goto(v.url)
    # the selectors say what is drawn
    sync_api.expect(page.get_by_label("Resolution")).to_have_value(f"auto: {RES:g} m drawn")
    sync_api.expect(page.get_by_label("Gaussians as")).to_have_value("auto: splats")

    def bulk(c):
        return c["box_w"] > 0.6 * c["width"] and c["drawn"] > 0.03 * c["page"]

    first = _canvas(page, bulk, settled=True, timeout=40.0)
    assert bulk(first), first
    client = next(iter(v.server.get_clients().values()))
    client.camera.position = (900.0, -900.0, 600.0)
    far = _canvas(page, lambda c: c["drawn"] < 0.2 * first["drawn"])
    assert far["drawn"] < 0.2 * first["drawn"], far
    page.get_by_role("button", name="Frame the map").click()
    back = _canvas(page, bulk, settled=True, timeout=40.0)
    assert bulk(back), (first, back)


def test_indoor_first_view_is_below_the_ceiling_in_colours_of_the_clip(small_page, viewers):
    rng = np.random.default_rng(6)
    m = NdtOmMap(RES)
    T = np.eye(4)
    T[:3, 3] = (10.0, 7.0, 1.5)
    m.insert_scan(_hall_points(rng, 50000), T)
    z = m.gaussians(min_probability=0.5)["mean"][:, 2]
    v = _viewer(viewers, m.snapshot())
    m.close()
    # the first view is clipped below the ceiling (4 m), and the colour bar spans the clip's heights
    lo, hi = v.drawn["clip"]
    assert 3.0 <= hi < 4.0 and lo <= z.min(), v.drawn["clip"]
    assert v.drawn["zrange"][1] <= hi and v.drawn["gaussians"] < 0.8 * len(z)
    page = small_page
    page.goto(v.url)
    _canvas(page, lambda c: c["drawn"] > 5000, settled=True)
    client = next(iter(v.server.get_clients().values()))

    def red_share(img: np.ndarray) -> float:  # the top of the colour bar: red (hue < 20 or > 340)
        h = _saturated_pixel_hues(img)
        return float(((h < 20) | (h > 340)).mean()) if len(h) else 1.0

    img = _render_until(client, lambda im: _drawn(im) > 3000)
    hues = _saturated_pixel_hues(img)
    bins = np.histogram(hues, bins=6, range=(0, 360))[0]
    clipped = red_share(img)
    # the floor and walls show, in several colours; the red top of the scale is the walls' rim only
    # (0.31 here; 0.76 with the ceiling)
    assert (bins > 0.03 * len(hues)).sum() >= 3 and clipped < 0.45, (bins, clipped)
    # negative control: with the ceiling drawn, it covers the view in the top colour
    zlo, zhi = v.controls.zlimits
    v.controls.zclip.value = (zlo, zhi)
    assert v.drawn["clip"] is None
    img = _render_until(client, lambda im: _drawn(im) > 3000 and red_share(im) > 0.6)
    assert red_share(img) > max(0.6, 1.8 * clipped), (clipped, red_share(img))


def test_a_token_viewer_opens_from_its_url_and_refuses_a_foreign_page(page, room, viewers):
    v = _viewer(viewers, room, token="browser-test-token")
    client = _connect(page, v)  # the printed URL, token included: the page and its WebSocket get in
    assert client is not None and len(v.server.get_clients()) == 1
    # a page of another origin (another viewer, another port) tries the first viewer's WebSocket
    other = _viewer(viewers, NdtOmMap(RES))
    page2 = page.context.new_page()
    page2.goto(other.url)
    js = """(url) => new Promise((done) => {
        const ws = new WebSocket(url, ["viser-vVERSION"]);
        ws.onopen = () => done("open"); ws.onerror = () => done("refused");
        setTimeout(() => done("timeout"), 8000); })""".replace("VERSION", viser.__version__)
    refused_before = v.guard.refused
    assert page2.evaluate(js, f"ws://127.0.0.1:{v.port}") == "refused"
    assert v.guard.refused > refused_before and len(v.server.get_clients()) == 1
    # the same request from the viewer's own page opens (positive control)
    assert page.evaluate(js, f"ws://127.0.0.1:{v.port}") == "open"
    page2.close()


def test_play_button_advances_live_mapping(page, room_scans, viewers):
    v = _viewer(viewers)
    lm = v.live(room_scans, NdtOmMap(RES), compare=True, rate_hz=8.0, refresh_interval=0.2)
    client = _connect(page, v)
    counter = page.get_by_text(re.compile(r"^Scans inserted: \d+ / \d+$"))
    sync_api.expect(counter).to_have_text(f"Scans inserted: 0 / {len(room_scans)}", timeout=15_000)
    time.sleep(0.5)
    assert lm.scans_done == 0  # paused until Play
    page.get_by_role("button", name="Play").click()
    assert _wait(lambda: lm.scans_done >= 1, timeout=15)
    # the counter in the page goes up while mapping runs, and reaches the end
    seen = set()
    t_end = time.monotonic() + 30
    while time.monotonic() < t_end:
        seen.add(int(counter.inner_text().split(":")[1].split("/")[0]))
        if len(room_scans) in seen:
            break
        time.sleep(0.1)
    assert len(room_scans) in seen and len(seen - {0}) >= 2, f"counter values seen: {sorted(seen)}"
    assert lm.wait(timeout=10) and lm.scans_done == len(room_scans)
    # nothing left to play: the buttons say so in the page
    for name in ("Play", "Pause", "Step"):
        sync_api.expect(page.get_by_role("button", name=name)).to_be_disabled(timeout=10_000)
    # the map built live is drawn, with its conflicting cells (the box taken away)
    assert _wait(lambda: v.drawn.get("trajectory") == len(room_scans))
    assert v.drawn["gaussians"] > 1000 and v.drawn["conflicts"] > 0
    v.frame()
    assert _drawn(_render_until(client, lambda im: _drawn(im) > 3000)) > 3000

    def magenta(img: np.ndarray) -> int:  # the conflicting cells' colour; no height colour is near it
        px = img[img[..., 3] > 200][:, :3].astype(int)
        return int(((px[:, 0] > 150) & (px[:, 2] > 150) & (px[:, 1] < 110)).sum())

    # the few conflicting cells are easy to find: markers about a cell wide, in the first view
    img = _render_until(client, lambda im: _drawn(im) > 3000 and magenta(im) > 150)
    seen = magenta(img)
    assert seen > 150, f"{seen} magenta pixels of {v.drawn['conflicts']} conflicting cells"
    v.controls.layers["conflicts"].value = False  # negative control
    img = _render_until(client, lambda im: _drawn(im) > 3000 and magenta(im) < 0.1 * seen)
    assert magenta(img) < 0.1 * seen
    # the time-per-scan chart draws its NDT-OM line (#c81e1e)
    js = """() => {
        let n = 0;
        for (const c of document.querySelectorAll('.uplot canvas')) {
            const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
            for (let i = 0; i < d.length; i += 4)
                if (d[i + 3] > 200 && d[i] > 150 && d[i + 1] < 90 && d[i + 2] < 90) n++;
        }
        return n; }"""
    assert _wait(lambda: page.evaluate(js) > 50, timeout=10), "the chart of time per scan draws no line"


def test_html_snapshot_renders_from_a_file(page, room, tmp_path):
    from ndtom_ti.viewer.cli import view_command

    path = tmp_path / "room.ndtom"
    room.save(path)
    out = tmp_path / "snapshot.html"
    assert view_command(path, "127.0.0.1", 0, out) == 0
    page.goto(out.resolve().as_uri())
    # count drawn pixels of the largest canvas (a 0x0 overlay canvas comes first)
    js = """() => {
        const cs = [...document.querySelectorAll('canvas')];
        if (!cs.length) return -1;
        cs.sort((a, b) => b.width * b.height - a.width * a.height);
        const o = document.createElement('canvas'); o.width = 160; o.height = 120;
        const g = o.getContext('2d'); g.drawImage(cs[0], 0, 0, 160, 120);
        const d = g.getImageData(0, 0, 160, 120).data; let n = 0;
        for (let i = 3; i < d.length; i += 4) if (d[i] > 0) n++;
        return n; }"""
    n = -1
    t_end = time.monotonic() + 30
    while n <= 500 and time.monotonic() < t_end:
        time.sleep(0.5)
        n = page.evaluate(js)
    assert n > 500, f"the snapshot page drew {n} pixels"
    # with the panel's legend and statistics over the scene
    sync_api.expect(page.get_by_text("Colour: height of the Gaussian's mean")).to_be_visible()
    sync_api.expect(page.locator("#ndtom-panel").get_by_text("Gaussians", exact=True)).to_be_visible()
