"""The viewer's server: where it can listen, the URL it prints, and viser's server set up for a map."""

from __future__ import annotations

import contextlib
import io
import socket
from collections.abc import Iterable
from typing import Any

from ._deps import require_viser
from .security import AccessGuard, guarded_server, primary_address

__all__ = ["announcement", "listen_port", "start_server", "url_for"]


def listen_port(host: str, port: int) -> int:
    """The port to listen on at ``host``: ``port`` when it is free (or 0: any), else the next
    free one above it. ``ValueError`` if nothing can listen on ``host``, or no port from
    ``port`` to 65535 is free (viser, left to look itself, raised in a thread past 65535
    and never started)."""
    try:
        infos = socket.getaddrinfo(host, None, type=socket.SOCK_STREAM)
    except socket.gaierror as exc:
        raise ValueError(f"cannot listen on host {host!r}: {exc.strerror or exc}") from None

    def try_bind(family: int, addr: tuple, p: int) -> OSError | None:
        s = socket.socket(family, socket.SOCK_STREAM)
        try:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as asyncio's servers do
            s.bind((addr[0], p, *addr[2:]))
            return None
        except OSError as exc:
            return exc
        finally:
            s.close()

    usable = [(fam, addr) for fam, _, _, _, addr in infos if try_bind(fam, addr, 0) is None]
    if not usable:
        err = try_bind(infos[0][0], infos[0][4], 0)
        raise ValueError(f"cannot listen on host {host!r}: {getattr(err, 'strerror', None) or err}")
    for p in range(port, 65536) if port else ():
        if all(try_bind(fam, addr, p) is None for fam, addr in usable):
            return p
    if port:
        raise ValueError(
            f"port {port} is in use on {host}, and so is every port above it up to 65535; "
            "choose another port (or 0 for any free one)"
        )
    return 0


def url_for(host: str, port: int, token: str | None = None) -> str:
    """The URL a browser opens: a wildcard bind is shown as this machine's address."""
    # ("::" listens on IPv6 only, as asyncio binds it: its URL is an IPv6 address)
    shown = primary_address(ipv6=host == "::") if host in ("", "0.0.0.0", "::") else host
    if ":" in shown and not shown.startswith("["):
        shown = f"[{shown}]"
    return f"http://{shown}:{port}/" + (f"?token={token}" if token else "")


def start_server(host: str, port: int, *, label: str, guard: AccessGuard, environment_map: bool) -> Any:
    """viser's server on ``host``:``port`` (a busy port becomes the next free one), behind
    ``guard``, quiet, lit for a map, its panel docked at the right and without a share button."""
    viser = require_viser()
    # viser's own messages (a URL without the token, "server stopped") stay off: the viewer
    # prints a URL that works
    with guarded_server(guard), contextlib.redirect_stdout(io.StringIO()):
        server = viser.ViserServer(host=host, port=port, label=label, verbose=False)
    scene = server.scene
    scene.configure_default_lights(enabled=True, cast_shadow=False)  # shadows of 1000s of ellipsoids: slow
    if not environment_map:
        # no image-based light: an even sky/ground light keeps the colours readable
        scene.configure_environment_map(hdri=None)
        scene.add_light_hemisphere(
            "/lights/hemisphere", sky_color=(255, 255, 255), ground_color=(160, 160, 160), intensity=1.2
        )
    # no "share" button: it would send the map to a public relay
    server.gui.configure_theme(show_share_button=False)
    # the panel docked at the right edge: the scene is drawn beside it, never under it
    with contextlib.suppress(AttributeError):
        server.gui.main_panel.dock_right()
        server.gui.main_panel.set_width(280)
    return server


def announcement(guard: AccessGuard, host: str, port: int, port_note: str, notes: Iterable[str]) -> list[str]:
    """What a viewer prints once it serves: the notes, a warning beyond loopback, the URL."""
    token = guard.token
    lines = [f"Note: {note}" for note in notes]
    if port_note:
        lines.append(f"Note: {port_note}")
    if not guard.loopback:
        lines.append(
            f"WARNING: the viewer listens on {host}, beyond this machine: anyone who can reach "
            f"port {port} and has the URL below (with its access token) can see the map and "
            "use the controls. Use --host 127.0.0.1 to keep it on this machine."
        )
    lines.append(f"NDT-OM viewer: {url_for(host, port, token)}")
    if host in ("", "0.0.0.0", "::"):
        local = "::1" if host == "::" else "127.0.0.1"
        lines.append(f"  (on this machine also: {url_for(local, port, token)})")
    return lines
