"""Who may talk to a viewer: the Host and Origin checks, and the access token.

A viewer serves its page over HTTP and the map over a WebSocket on one port. Without
checks, any web page the user opens could connect to ``ws://127.0.0.1:PORT`` (browsers
let pages open WebSockets to any address) and read the map or drive the GUI, and a
DNS-rebinding page could fetch from the port under its own name. So every request goes
through :meth:`AccessGuard.check`:

- its ``Host`` must be a loopback name or address, or the address the viewer is bound
  to (for a wildcard bind: a name or address of this machine);
- a WebSocket upgrade with an ``Origin`` (browsers always send one) must come from the
  viewer's own page: ``http://`` + the request's ``Host``;
- beyond loopback, the request must also carry the access token: ``?token=`` in the URL
  the viewer prints (the page's response sets it as a cookie, which the browser sends
  with the page's other requests and its WebSocket).

viser has no hook for this, so :func:`guarded_server` hands the check to the
``process_request`` of the websockets server viser starts (see there).
"""

from __future__ import annotations

import contextlib
import hmac
import http
import ipaddress
import secrets
import socket
import threading
from collections.abc import Iterator
from http.cookies import SimpleCookie
from typing import Any
from urllib.parse import parse_qs, urlsplit

__all__ = ["AccessGuard", "guarded_server", "is_loopback_host"]

COOKIE = "ndtom_viewer_token"
LOOPBACK_NAMES = frozenset({"localhost", "localhost.localdomain", "ip6-localhost", "ip6-loopback"})


def _strip(host: str) -> str:
    host = host.strip().lower().rstrip(".")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    return host


def _is_loopback_literal(host: str) -> bool:
    host = _strip(host)
    if host in LOOPBACK_NAMES or host.endswith(".localhost"):
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def is_loopback_host(host: str) -> bool:
    """True when every address ``host`` resolves to is a loopback address."""
    if _is_loopback_literal(host):
        return True
    if _strip(host) in ("", "0.0.0.0", "::"):
        return False
    try:
        infos = socket.getaddrinfo(host, None, type=socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError):
        return False
    return bool(infos) and all(ipaddress.ip_address(str(i[4][0]).split("%")[0]).is_loopback for i in infos)


def _split_host_header(value: str) -> tuple[str, str | None]:
    """(host, port) of a Host header value ('example:8080', '[::1]:80', 'name')."""
    value = value.strip()
    if value.startswith("["):
        end = value.find("]")
        if end < 0:
            return value, None
        host, rest = value[1:end], value[end + 1 :]
        return host.lower(), rest[1:] if rest.startswith(":") else None
    if value.count(":") == 1:
        host, port = value.split(":")
        return host.lower(), port
    return value.lower(), None


def machine_addresses() -> set[str]:
    """Names and addresses of this machine that a wildcard-bound viewer answers to."""
    names = {socket.gethostname().lower(), socket.getfqdn().lower()}
    out = set(names)
    for name in names:
        with contextlib.suppress(OSError, UnicodeError):
            for info in socket.getaddrinfo(name, None, type=socket.SOCK_STREAM):
                out.add(str(info[4][0]).split("%")[0].lower())
    out.add(primary_address())
    out.add(primary_address(ipv6=True))
    return {_strip(a) for a in out if a}


def primary_address(ipv6: bool = False) -> str:
    """The address this machine reaches other machines from (no packet is sent), or its
    host name's address; '127.0.0.1' when it has none. ``ipv6``: its IPv6 address, '::1'
    when it has none (a viewer bound to '::' listens on IPv6 only)."""
    if ipv6:
        with contextlib.suppress(OSError):
            s = socket.socket(socket.AF_INET6, socket.SOCK_DGRAM)
            try:
                s.connect(("2001:db8::1", 9))  # the documentation prefix: only picks the interface
                return str(s.getsockname()[0]).split("%")[0]
            finally:
                s.close()
        return "::1"
    with contextlib.suppress(OSError):
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            s.connect(("192.0.2.1", 9))  # TEST-NET-1: only picks the outgoing interface
            return s.getsockname()[0]
        finally:
            s.close()
    with contextlib.suppress(OSError):
        return socket.gethostbyname(socket.gethostname())
    return "127.0.0.1"


class AccessGuard:
    """The checks of one viewer. ``token`` is made (random) when ``host`` is not loopback;
    ``allowed_hosts`` adds names the viewer answers to (e.g. behind a known DNS name)."""

    def __init__(self, host: str, *, token: str | None = None, allowed_hosts: tuple[str, ...] = ()):
        self.bind_host = host
        self.loopback = is_loopback_host(host)
        allowed = {"localhost", "127.0.0.1", "::1", _strip(host)}
        allowed |= {_strip(h) for h in allowed_hosts}
        if _strip(host) in ("", "0.0.0.0", "::"):
            allowed |= machine_addresses()
        self.allowed = allowed
        self.token = token if token is not None else (None if self.loopback else secrets.token_urlsafe(18))
        self.refused = 0  # requests refused so far (for the log and tests)
        self.installed = False  # guarded_server: viser's server took the checks
        self._lock = threading.Lock()

    # ------------------------------------------------------------------ rules

    def host_allowed(self, host_header: str | None) -> bool:
        if not host_header:
            return False
        host, _ = _split_host_header(host_header)
        host = _strip(host)
        return host in self.allowed or _is_loopback_literal(host)

    @staticmethod
    def cookie_name(host_header: str | None) -> str:
        """The token cookie of the viewer at this Host's port (cookies are shared by every
        port of a host: viewers on other ports keep their own)."""
        _, port = _split_host_header(host_header or "")
        return f"{COOKIE}_{port or 80}"

    def _token_ok(self, path: str, cookie_header: str | None, host_header: str | None = None) -> bool:
        if self.token is None:
            return True
        query = parse_qs(urlsplit(path).query)
        for value in query.get("token", []):
            if hmac.compare_digest(value.encode(), self.token.encode()):
                return True
        if cookie_header:
            jar = SimpleCookie()
            with contextlib.suppress(Exception):
                jar.load(cookie_header)
            morsel = jar.get(self.cookie_name(host_header))
            if morsel is not None and hmac.compare_digest(morsel.value.encode(), self.token.encode()):
                return True
        return False

    def check(self, path: str, headers: Any) -> tuple[int, str] | None:
        """None when the request may proceed, else (HTTP status, reason)."""
        get_all = getattr(headers, "get_all", None)  # (websockets' Headers: get() raises on repeats)
        if get_all is not None:
            for name in ("Host", "Origin", "Upgrade"):
                if len(get_all(name)) > 1:
                    return 400, f"more than one {name} header"
        host = headers.get("Host")
        if not self.host_allowed(host):
            return 403, f"Host {host!r} is not this viewer's address"
        if str(headers.get("Upgrade", "")).lower() == "websocket":
            origin = headers.get("Origin")
            if origin is not None and origin.strip().lower() != f"http://{host.strip().lower()}":
                return 403, f"Origin {origin!r} is not this viewer's page"
        if not self._token_ok(path, headers.get("Cookie"), host):
            return 401, "this viewer needs its access token: open the URL it printed (with ?token=...)"
        return None

    # ------------------------------------------------------------------ websockets hook

    def process_request(self, inner: Any) -> Any:
        """A websockets ``process_request`` that checks first, then calls ``inner``."""

        def process(connection: Any, request: Any) -> Any:
            refused = self.check(request.path, request.headers)
            if refused is not None:
                with self._lock:
                    self.refused += 1
                status, reason = refused
                return connection.respond(http.HTTPStatus(status), f"Refused: {reason}.\n")
            response = inner(connection, request) if inner is not None else None
            if response is not None and self.token is not None and "token=" in request.path:
                # the page's own later requests (assets, the WebSocket) carry the token as a cookie
                name = self.cookie_name(request.headers.get("Host"))
                response.headers["Set-Cookie"] = f"{name}={self.token}; Path=/; HttpOnly; SameSite=Strict"
            return response

        return process


_hook_lock = threading.Lock()
_pending: list[AccessGuard] = []


def _is_viser_handler(handler: Any) -> bool:
    return getattr(handler, "__qualname__", "").endswith("_background_worker.<locals>.ws_handler")


@contextlib.contextmanager
def guarded_server(guard: AccessGuard) -> Iterator[None]:
    """Within this block, the next viser server started gets ``guard`` in front of its
    HTTP and WebSocket handling.

    viser (1.1) starts websockets' ``serve(ws_handler, ..., process_request=...)`` from its
    server thread before ``ViserServer()`` returns; while the block runs, that function is
    wrapped so that viser's call gets ``guard.process_request(...)``. Calls from other code
    pass through unchanged. Raises RuntimeError if the server started without the guard
    (a viser whose server start this does not know)."""
    import websockets.asyncio.server as wss

    with _hook_lock:
        original = wss.serve

        def serve(handler: Any, *args: Any, **kwargs: Any) -> Any:
            if _pending and _is_viser_handler(handler):
                g = _pending.pop()
                kwargs["process_request"] = g.process_request(kwargs.get("process_request"))
                g.installed = True
            return original(handler, *args, **kwargs)

        guard.installed = False
        _pending.append(guard)
        wss.serve = serve
        try:
            yield
        finally:
            wss.serve = original
            _pending.clear()
    if not guard.installed:
        raise RuntimeError(
            "the viewer could not install its Host/Origin checks in this viser version's server; "
            "refusing to serve the map unprotected"
        )
