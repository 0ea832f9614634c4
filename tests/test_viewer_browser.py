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

from ndtom_ti.viewer import MapViewer
from ndtom_ti.viewer import geometry as geo

RES = 0.5
FLAGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--enable-unsafe-swiftshader",
]  # fmt: skip
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


def test_small_map_renders_in_occupancy_colours_and_controls_change_it(page, room, viewers):
    v = _viewer(viewers, room)
    client = _connect(page, v)
    img = _render_until(client, lambda im: _drawn(im) > 3000)
    assert _drawn(img) > 3000, "the map's Gaussians are not drawn"

    # the colours drawn are the occupancy colours of the map's Gaussians (lighting changes
    # brightness, not hue): nearly every coloured pixel has one of their hues
    g = room.gaussians(min_probability=0.5)
    expected = _hues(np.unique(geo.occupancy_colors(g["p_occ"]), axis=0))
    hues = _saturated_pixel_hues(img)
    assert len(hues) > 1000
    near = _hue_distance(hues, expected) < 12.0
    assert near.mean() > 0.9, f"only {near.mean():.0%} of the pixels have an occupancy colour"
    most = _hues(geo.occupancy_colors(np.array([np.median(g["p_occ"])])))
    assert (_hue_distance(hues, most) < 12.0).mean() > 0.3  # the typical cell's colour dominates
    assert (_hue_distance(hues, _hues(np.array(geo.CONFLICT_RGB))) < 12.0).mean() < 0.01  # no magenta here

    # layer toggle, clicked in the page: the Gaussians go (0 drawn pixels) and come back
    page.get_by_label("Gaussians", exact=True).click()
    assert _wait(lambda: not v.layer_visible("gaussians"))
    off = _render_until(client, lambda im: _drawn(im) == 0)
    assert _drawn(off) == 0
    page.get_by_label("Gaussians", exact=True).click()
    assert _wait(lambda: v.layer_visible("gaussians"))
    back = _render_until(client, lambda im: _drawn(im) > 3000)
    assert abs(_drawn(back) - _drawn(img)) < 0.05 * _drawn(img)

    # resolution selector, chosen in the page: the 2x level draws fewer, larger ellipsoids
    page.get_by_label("Resolution").click()
    page.get_by_role("option", name="1 m (2x)").click()
    assert _wait(lambda: v.level == 2 and v.drawn["gaussians"] < len(g["n"]))
    before = back[..., 3] > 0

    def changed(im):
        mask = im[..., 3] > 0
        return mask.sum() > 1000 and (mask ^ before).mean() > 0.03

    coarse = _render_until(client, changed)
    assert changed(coarse), "switching the resolution did not change what is drawn"


def test_empty_map_draws_nothing(page, room, viewers):
    v = _viewer(viewers, NdtOmMap(RES))
    client = _connect(page, v)
    assert v.drawn["gaussians"] == 0
    assert _drawn(_render(client)) == 0
    time.sleep(1.0)
    assert _drawn(_render(client)) == 0
    # control: the same page draws as soon as the map has content
    v.set_maps(room)
    assert _drawn(_render_until(client, lambda im: _drawn(im) > 3000)) > 3000


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
    # the map built live is drawn, with its conflicting cells (the box taken away)
    assert _wait(lambda: v.drawn.get("trajectory") == len(room_scans))
    assert v.drawn["gaussians"] > 1000 and v.drawn["conflicts"] > 0
    v.frame()
    assert _drawn(_render_until(client, lambda im: _drawn(im) > 3000)) > 3000
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
