"""Who may talk to the viewer's server: the Origin check and the optional token.

viser serves the page and its websocket from one ``websockets`` server
(``viser/infra/_infra.py``: ``websockets.asyncio.server.serve(...,
process_request=viser_http_server)``), and accepts every handshake: any page
open in a browser on this machine could read the scene and drive the GUI.
viser has no option for this, so ``installed(guard)`` puts ``GuardedServe``, a
subclass of ``websockets.asyncio.server.serve``, in the place of ``serve`` for
the time ``viser.ViserServer(...)`` takes to bind its port (it returns only
once its server is listening), then puts the original back. ``GuardedServe``
only wraps viser's ``process_request`` with ``HandshakeGuard.screen``, which
runs before viser's own code for every HTTP request and every websocket
handshake:

- a request with an ``Origin`` header that is not the page's own
  (``http://127.0.0.1:PORT``, ``http://localhost:PORT``, ``http://HOST:PORT``
  for the configured host, and any of the ``origins`` parameter) is answered
  ``403 Forbidden``, before any scene data. A request without ``Origin`` is
  let through: browsers always send it on websocket handshakes, so only
  non-browser clients (tools, tests, ``curl``) omit it, and those could as
  well read the bus;
- with a token (``token = "..."``, ``"auto"`` for a fresh random one, or the
  ``IAMP_VIEWER_TOKEN`` environment variable), every request must carry it,
  as ``?token=...`` or as the cookie that the page response sets when it was
  loaded with a good ``?token=`` (viser's page opens its websocket without the
  page's query string, so the cookie carries the token there; it is
  ``HttpOnly; SameSite=Strict``, named per port); others get ``403``.

When the substitution did not reach viser's server (a viser that no longer
serves through ``websockets.asyncio.server.serve``), ``installed`` raises:
the viewer refuses to start rather than serve unguarded.
"""

from __future__ import annotations

import contextlib
import hmac
import http
import http.cookies
import ipaddress
import secrets
import threading
import urllib.parse
from typing import Any, Callable, Iterable, Iterator

import websockets.asyncio.server as ws_server
from websockets.datastructures import Headers
from websockets.http11 import Request, Response

TOKEN_PARAM = "token"
COOKIE_PREFIX = "iamp_viewer_token_"
_install_lock = threading.Lock()


def new_token() -> str:
    """A random URL-safe token (128 bits)."""
    return secrets.token_urlsafe(16)


def _origin_host(host: str) -> str:
    """``host`` as it appears in an Origin: IPv6 literals in brackets."""
    try:
        if ipaddress.ip_address(host).version == 6:
            return f"[{host}]"
    except ValueError:
        pass
    return host.lower()


def _unspecified(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).is_unspecified
    except ValueError:
        return False


class HandshakeGuard:
    """Decides, per HTTP request or websocket handshake, whether viser may answer it."""

    def __init__(self, *, host: str, token: str = "", origins: Iterable[str] = (), log: Any = None) -> None:
        self.host = host
        self.token = token
        self.extra_origins = {o.rstrip("/").lower() for o in origins}
        self.log = log
        self.refused = 0
        self.attached = 0  # servers this guard was attached to (GuardedServe instances)
        self._warned: set[str] = set()

    def allowed_origins(self, port: int) -> set[str]:
        hosts = {"127.0.0.1", "localhost", "[::1]"}
        if not _unspecified(self.host):  # 0.0.0.0 / :: is no page address: list those in ``origins``
            hosts.add(_origin_host(self.host))
        return {f"http://{h}:{port}" for h in hosts} | self.extra_origins

    def cookie_name(self, port: int) -> str:
        return f"{COOKIE_PREFIX}{port}"

    def _presented_tokens(self, request: Request, port: int) -> tuple[str | None, str | None]:
        query = urllib.parse.parse_qs(urllib.parse.urlsplit(request.path).query)
        from_query = query.get(TOKEN_PARAM, [None])[0]
        from_cookie = None
        for header in request.headers.get_all("Cookie"):
            jar = http.cookies.SimpleCookie()
            try:
                jar.load(header)
            except http.cookies.CookieError:
                continue
            if self.cookie_name(port) in jar:
                from_cookie = jar[self.cookie_name(port)].value
        return from_query, from_cookie

    def _good(self, presented: str | None) -> bool:
        return presented is not None and hmac.compare_digest(presented.encode(), self.token.encode())

    def refusal(self, request: Request, port: int) -> tuple[str, bool] | None:
        """``None`` to let the request through, else ``(why, ...)``; the bool says a good ``?token=`` came in the query."""
        origins = request.headers.get_all("Origin")
        if len(origins) > 1:
            return "several Origin headers", False
        if origins and origins[0].rstrip("/").lower() not in self.allowed_origins(port):
            return f"origin {origins[0]!r} is not this viewer's page", False
        if not self.token:
            return None
        from_query, from_cookie = self._presented_tokens(request, port)
        if self._good(from_query):
            return None
        if self._good(from_cookie) and from_query is None:
            return None
        return ("wrong token" if (from_query or from_cookie) else "no token"), False

    def screen(self, connection: Any, request: Request, inner: Callable[..., Any] | None) -> Response | None:
        """The ``process_request`` that viser's server runs: refuse, or hand over to viser's own."""
        port = _local_port(connection)
        why = self.refusal(request, port)
        if why is not None:
            self.refused += 1
            kind = "handshake" if (request.headers.get("Upgrade") or "").lower() == "websocket" else "request"
            if self.log is not None and why[0] not in self._warned:
                self._warned.add(why[0])  # one line per reason: a page retrying must not flood the log
                self.log.warning("viewer: refused a %s from %s: %s", kind, _peer(connection), why[0])
            text = "Forbidden: " + why[0] + (". Open the viewer URL the launcher printed (with its ?token=)." if self.token else ".") + "\n"
            return Response(http.HTTPStatus.FORBIDDEN, "Forbidden", Headers({"Content-Type": "text/plain; charset=utf-8", "Content-Length": str(len(text.encode()))}), text.encode())
        response = inner(connection, request) if inner is not None else None
        if response is not None and self.token:
            from_query, _ = self._presented_tokens(request, port)
            if self._good(from_query):  # the page's websocket carries no query string: the cookie takes the token there
                response.headers["Set-Cookie"] = f"{self.cookie_name(port)}={self.token}; Path=/; HttpOnly; SameSite=Strict"
        return response


def _local_port(connection: Any) -> int:
    try:
        return int(connection.local_address[1])
    except Exception:  # noqa: BLE001 - no address: no origin can match
        return -1


def _peer(connection: Any) -> str:
    try:
        host, port = connection.remote_address[:2]
        return f"{host}:{port}"
    except Exception:  # noqa: BLE001
        return "?"


class GuardedServe(ws_server.serve):
    """``websockets.asyncio.server.serve`` with ``process_request`` wrapped by a ``HandshakeGuard``."""

    guard: HandshakeGuard | None = None  # set on the subclass that ``installed`` makes

    def __init__(self, *args: Any, process_request: Any = None, **kwargs: Any) -> None:
        guard = type(self).guard
        if guard is None:
            raise RuntimeError("GuardedServe used without a guard")
        if process_request is not None and not callable(process_request):
            raise RuntimeError("viser passed a process_request the guard cannot wrap")
        guard.attached += 1
        super().__init__(*args, process_request=lambda conn, req: guard.screen(conn, req, process_request), **kwargs)


@contextlib.contextmanager
def installed(guard: HandshakeGuard) -> Iterator[None]:
    """Within the block, servers made by ``websockets.asyncio.server.serve`` are guarded; raises if none was made."""
    with _install_lock:
        original = ws_server.serve
        ws_server.serve = type("GuardedServe", (GuardedServe,), {"guard": guard})
        try:
            yield
        finally:
            ws_server.serve = original
    if guard.attached == 0:
        raise RuntimeError(
            "the viewer's Origin/token check did not reach viser's websocket server "
            "(viser no longer calls websockets.asyncio.server.serve while ViserServer() starts); not serving unguarded"
        )
