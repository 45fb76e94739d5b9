"""The viewer's websocket accepts only its own origin.

A browser sends the page's origin (scheme, host, port) with every websocket handshake. Viser
accepts any: a web page from elsewhere, open in the same browser, could connect to the viewer,
read the served scene and press Generate. ``own_origin_only`` makes the handshake refuse (HTTP 403)
an ``Origin`` that is not the viewer's own: ``http(s)://HOST:PORT`` with PORT the bound port and
HOST the bound host, the local address the connection arrived on, or, for a loopback or wildcard
bind, ``localhost`` / ``127.0.0.1`` / ``[::1]`` (and this machine's names for a wildcard bind).
A handshake without ``Origin`` (a program, not a browser page) is let through: browsers always send it.
"""

from __future__ import annotations

import contextlib
import inspect
import ipaddress
import socket
from http import HTTPStatus
from urllib.parse import urlsplit

WILDCARDS = ("0.0.0.0", "::", "")
LOOPBACK_NAMES = ("localhost", "127.0.0.1", "::1")


def _norm(host: str) -> str:
    host = host.strip("[]").lower()
    try:
        return ipaddress.ip_address(host).compressed
    except ValueError:
        return host.rstrip(".")


def allowed_hosts(bound_host: str, local_ip: str | None = None) -> set[str]:
    """Host names and addresses a browser may use to reach a viewer bound to ``bound_host``."""
    hosts = {_norm(bound_host)} if bound_host not in WILDCARDS else set()
    if local_ip:
        hosts.add(_norm(local_ip))
    loopback = bound_host in WILDCARDS or bound_host == "localhost"
    with contextlib.suppress(ValueError):
        loopback = loopback or ipaddress.ip_address(bound_host.strip("[]")).is_loopback
    if loopback:
        hosts |= {_norm(h) for h in LOOPBACK_NAMES}
    if bound_host in WILDCARDS:
        hosts |= {_norm(socket.gethostname()), _norm(socket.getfqdn())}
    return hosts - {""}


def origin_allowed(origin: str, bound_host: str, local_address: tuple | None) -> bool:
    """Whether a handshake's ``Origin`` header is the viewer's own (see the module doc)."""
    try:
        parts = urlsplit(origin)
        port = parts.port or {"http": 80, "https": 443}.get(parts.scheme)
    except ValueError:
        return False
    if parts.scheme not in ("http", "https") or not parts.hostname or local_address is None:
        return False
    local_ip, local_port = local_address[0], int(local_address[1])
    return port == local_port and _norm(parts.hostname) in allowed_hosts(bound_host, local_ip)


@contextlib.contextmanager
def own_origin_only(bound_host: str):
    """While a viser server is built inside this block, its websocket server refuses foreign origins.

    Viser starts its ``websockets`` server in a thread of its own before its constructor returns;
    the server keeps the handshake check this block gave it for its whole life."""
    import websockets.asyncio.server as ws_server  # imported lazily, as viser itself is

    original = ws_server.serve

    def serve(handler, *args, process_request=None, **kwargs):
        async def check_origin(connection, request):
            origin = request.headers.get("Origin")
            upgrade = request.headers.get("Upgrade", "").lower() == "websocket"
            if upgrade and origin is not None and not origin_allowed(origin, bound_host, connection.local_address):
                return connection.respond(HTTPStatus.FORBIDDEN, "Forbidden: this viewer accepts only its own origin\n")
            if process_request is None:
                return None
            response = process_request(connection, request)
            return await response if inspect.isawaitable(response) else response

        return original(handler, *args, process_request=check_origin, **kwargs)

    ws_server.serve = serve
    try:
        yield
    finally:
        ws_server.serve = original
