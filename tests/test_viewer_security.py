"""Who may talk to a viewer: raw HTTP and WebSocket requests against 127.0.0.1.

A page of another site must not read the map over ``ws://127.0.0.1:PORT`` (Origin
check), a DNS-rebinding page must not reach the viewer under its own name (Host check),
and beyond loopback a request needs the access token of the printed URL. Each refusal
has an accepted request beside it (the same request from the viewer's own page), so the
test fails if the viewer refuses everything as well as if it accepts everything.
"""

from __future__ import annotations

import base64
import os
import socket
import time

import numpy as np
import pytest

from ndtom_ti import NdtOmMap

viser = pytest.importorskip("viser", reason="the viewer needs viser: pip install ndtom_ti[viewer]")

from ndtom_ti.viewer import MapViewer
from ndtom_ti.viewer.security import AccessGuard, is_loopback_host


@pytest.fixture(scope="module")
def small_map():
    m = NdtOmMap(0.5)
    rng = np.random.default_rng(3)
    m.insert_scan(rng.normal(size=(3000, 3)) * [3, 3, 0.05] + [0, 0, -1.0], np.eye(4))
    yield m
    del m


@pytest.fixture
def viewers():
    made = []
    yield made
    for v in made:
        v.close()


def _viewer(viewers, m, **kw) -> MapViewer:
    kw.setdefault("verbose", False)
    v = MapViewer(m, environment_map=False, **kw)
    viewers.append(v)
    return v


def _request(port: int, lines: list[str], read_for: float = 1.5) -> bytes:
    """Send a raw HTTP request to 127.0.0.1:port; return all bytes received within ``read_for`` s."""
    with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
        s.sendall(("\r\n".join(lines) + "\r\n\r\n").encode())
        s.settimeout(0.3)
        out = b""
        t_end = time.monotonic() + read_for
        while time.monotonic() < t_end:
            try:
                chunk = s.recv(65536)
            except TimeoutError:
                continue
            if not chunk:
                break
            out += chunk
    return out


def _get(port: int, host: str, path: str = "/", extra: tuple[str, ...] = ()) -> bytes:
    return _request(port, [f"GET {path} HTTP/1.1", f"Host: {host}", "Connection: close", *extra])


def _upgrade(port: int, host: str, origin: str | None, extra: tuple[str, ...] = ()) -> bytes:
    key = base64.b64encode(os.urandom(16)).decode()
    lines = [
        "GET / HTTP/1.1",
        f"Host: {host}",
        "Upgrade: websocket",
        "Connection: Upgrade",
        f"Sec-WebSocket-Key: {key}",
        "Sec-WebSocket-Version: 13",
        f"Sec-WebSocket-Protocol: viser-v{viser.__version__}",
        *extra,
    ]
    if origin is not None:
        lines.append(f"Origin: {origin}")
    return _request(port, lines, read_for=2.5)


def _status(resp: bytes) -> int:
    return int(resp.split(b" ", 2)[1]) if resp.startswith(b"HTTP/1.1 ") else -1


def test_foreign_origin_and_host_get_no_bytes_of_the_map(small_map, viewers):
    v = _viewer(viewers, small_map)
    own = f"127.0.0.1:{v.port}"
    assert v.guard.loopback and v.guard.token is None and "token" not in v.url

    # the viewer's own page: the page loads and its WebSocket streams the scene
    page = _get(v.port, own)
    assert _status(page) == 200 and len(page) > 10_000
    assert _status(_get(v.port, f"localhost:{v.port}")) == 200
    ok = _upgrade(v.port, own, f"http://{own}")
    assert _status(ok) == 101 and len(ok) > 2_000, "the accepted WebSocket got no scene"
    scene_bytes = len(ok)

    refused = v.guard.refused
    cases = {
        "cross-site WebSocket": _upgrade(v.port, own, "http://evil.example"),
        "cross-site WebSocket, other port": _upgrade(v.port, own, "http://127.0.0.1:1"),
        "sandboxed page (Origin null)": _upgrade(v.port, own, "null"),
        "DNS rebinding WebSocket": _upgrade(v.port, f"evil.example:{v.port}", f"http://evil.example:{v.port}"),
        "DNS rebinding page": _get(v.port, f"evil.example:{v.port}"),
        "no Host": _request(v.port, ["GET / HTTP/1.0"]),
    }
    for what, resp in cases.items():
        assert _status(resp) in (400, 403) or resp == b"", f"{what}: {resp[:200]!r}"
        assert len(resp) < 1_000 < scene_bytes, f"{what}: {len(resp)} bytes came back"
    assert v.guard.refused >= refused + 5


def test_guard_rules():
    """Unit rules of the guard: names, ports, IPv6 and case."""
    g = AccessGuard("127.0.0.1")
    assert g.host_allowed("127.0.0.1:8080") and g.host_allowed("LOCALHOST:8080") and g.host_allowed("[::1]:8080")
    assert not g.host_allowed("evil.example:8080") and not g.host_allowed("") and not g.host_allowed(None)
    ws = {"Upgrade": "websocket", "Host": "localhost:8080"}
    assert g.check("/", {**ws, "Origin": "http://localhost:8080"}) is None
    assert g.check("/", {**ws, "Origin": "http://LOCALHOST:8080"}) is None
    assert g.check("/", {**ws, "Origin": "https://localhost:8080"})[0] == 403
    assert g.check("/", {**ws, "Origin": "http://localhost:8081"})[0] == 403
    assert g.check("/", ws) is None  # no Origin: not a web page (browsers always send one)
    # the whole origin must match, not a prefix of it
    bare = {"Upgrade": "websocket", "Host": "localhost"}
    assert g.check("/", {**bare, "Origin": "http://localhost"}) is None
    assert g.check("/", {**bare, "Origin": "http://localhost.evil.example"})[0] == 403
    assert g.check("/", {**bare, "Origin": "http://localhost:8080"})[0] == 403
    port80 = {"Upgrade": "websocket", "Host": "127.0.0.1:80"}
    assert g.check("/", {**port80, "Origin": "http://127.0.0.1:80"}) is None
    assert g.check("/", {**port80, "Origin": "http://127.0.0.1:8080"})[0] == 403
    assert g.check("/", {**port80, "Origin": "http://127.0.0.1:80.evil.example"})[0] == 403
    assert is_loopback_host("127.0.0.1") and is_loopback_host("localhost") and is_loopback_host("::1")
    assert not is_loopback_host("0.0.0.0") and not is_loopback_host("192.0.2.1")
    wide = AccessGuard("0.0.0.0")
    assert not wide.loopback and wide.token and len(wide.token) >= 20
    assert wide.check("/", {"Host": "127.0.0.1:1"})[0] == 401
    assert wide.check(f"/?token={wide.token}", {"Host": "127.0.0.1:1"}) is None
    assert wide.check("/?token=wrong", {"Host": "127.0.0.1:1"})[0] == 401


def test_token_viewer_needs_the_printed_url(small_map, viewers):
    # a token makes the viewer behave as it does beyond loopback (bound here to 127.0.0.1)
    v = _viewer(viewers, small_map, token="s3cret-token")
    own = f"127.0.0.1:{v.port}"
    assert v.url == f"http://127.0.0.1:{v.port}/?token=s3cret-token"
    assert _status(_get(v.port, own)) == 401
    assert _status(_upgrade(v.port, own, f"http://{own}")) == 401
    page = _get(v.port, own, "/?token=s3cret-token")
    name = f"ndtom_viewer_token_{v.port}"  # one cookie per port: viewers on other ports keep theirs
    assert _status(page) == 200 and f"Set-Cookie: {name}=s3cret-token".encode() in page
    assert b"HttpOnly" in page and b"SameSite=Strict" in page
    # the page's WebSocket carries the cookie
    cookie = (f"Cookie: {name}=s3cret-token",)
    ok = _upgrade(v.port, own, f"http://{own}", cookie)
    assert _status(ok) == 101 and len(ok) > 2_000
    assert _status(_upgrade(v.port, own, f"http://{own}", (f"Cookie: {name}=guess",))) == 401
    other_port = ("Cookie: ndtom_viewer_token_1=s3cret-token",)  # another port's cookie does not open this one
    assert _status(_upgrade(v.port, own, f"http://{own}", other_port)) == 401
    # a foreign page does not get in with the cookie either (Origin check first)
    assert _status(_upgrade(v.port, own, "http://evil.example", cookie)) == 403


def test_wildcard_host_warns_and_prints_a_url_with_its_token(small_map, viewers, capsys):
    lines = []
    v = _viewer(viewers, small_map, host="0.0.0.0", verbose=True, progress=lines.append)
    text = "\n".join(lines)
    assert "WARNING" in text and "beyond this machine" in text
    assert v.guard.token and f"?token={v.guard.token}" in v.url and v.url in text
    assert "0.0.0.0" not in v.url  # a URL a browser can open
    local = f"http://127.0.0.1:{v.port}/?token={v.guard.token}"
    assert local in text
    # that URL works (asked on 127.0.0.1 only); without the token it does not
    assert _status(_get(v.port, f"127.0.0.1:{v.port}", f"/?token={v.guard.token}")) == 200
    assert _status(_get(v.port, f"127.0.0.1:{v.port}")) == 401
    assert _status(_get(v.port, f"evil.example:{v.port}", f"/?token={v.guard.token}")) == 403


@pytest.mark.parametrize("twice", ["Host: 127.0.0.1:{port}", "Origin: http://127.0.0.1:{port}", "Upgrade: websocket"])
def test_repeated_headers_are_a_bad_request_not_a_server_error(small_map, viewers, twice, capsys):
    """A request with two Host, Origin or Upgrade headers: 400, no traceback in the log;
    the same request with the header once is served."""
    v = _viewer(viewers, small_map, port=0)
    host = f"127.0.0.1:{v.port}"
    once = _upgrade(v.port, host, f"http://{host}")
    assert _status(once) == 101, once[:200]
    resp = _upgrade(v.port, host, f"http://{host}", extra=(twice.format(port=v.port),))
    assert _status(resp) == 400, resp[:300]
    assert b"more than one" in resp
    err = capsys.readouterr()
    assert "Traceback" not in err.err + err.out
