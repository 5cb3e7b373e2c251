"""Who may open the viewer: the Origin check and the token, with a real viser server and a real websocket client.

The viewer (``ViewerApp``, the core of ``stages.viewer``) is started on a
fresh port; a ``websockets`` client opens viser's websocket (offering viser's
subprotocol, as the page does) with a foreign ``Origin`` (refused with HTTP
403 before any data), with the page's own (accepted, and scene data comes),
and without one (accepted: browsers always send it, so only non-browser
clients omit it). With a token, handshakes and page loads without it or with
a wrong one are refused; with ``?token=`` or the cookie that the page load
sets they are accepted. Last, a launcher run with bus authentication and a
viewer with a token: the launcher prints the URL with the token, which is on
no command line, and the viewer serves only with it.
"""

from __future__ import annotations

import logging
import os
import secrets
import signal
import sys
import urllib.error
import urllib.request
from pathlib import Path

import pytest
import viser
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from testkit.helpers import all_command_lines, kill_all
from stages.lib.base import ConfigError
from stages.viewer.config import TOKEN_ENV, ViewerConfig
from stages.viewer.scene import ViewerApp
from test_launch_run import Launch

SUBPROTOCOL = f"viser-v{viser.__version__}"


def _start(monkeypatch, **params) -> ViewerApp:
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    app = ViewerApp(ViewerConfig(port=0, stats=False, **params), run_id="access", log=logging.getLogger("iamp.viewer"))
    app.start()
    return app


def _port(app: ViewerApp) -> int:
    return app.server.get_port()


def _handshake(port: int, *, origin: str | None, path: str = "/", cookie: str | None = None) -> int | str:
    """403 (or another refusal status), or the size of the first message the server sends once accepted."""
    headers = {}
    if origin is not None:
        headers["Origin"] = origin
    if cookie is not None:
        headers["Cookie"] = cookie
    try:
        with connect(f"ws://127.0.0.1:{port}{path}", additional_headers=headers, subprotocols=[SUBPROTOCOL], open_timeout=20) as ws:
            first = ws.recv(timeout=20)  # viser sends its persistent scene/GUI messages right away
            return f"accepted {len(first)} bytes"
    except InvalidStatus as exc:
        return exc.response.status_code


def _get(port: int, path: str = "/", origin: str | None = None) -> tuple[int, dict[str, str]]:
    req = urllib.request.Request(f"http://127.0.0.1:{port}{path}", headers={"Origin": origin} if origin else {})
    try:
        with urllib.request.urlopen(req, timeout=20) as r:
            return r.status, dict(r.headers)
    except urllib.error.HTTPError as exc:
        return exc.code, dict(exc.headers)


def test_foreign_origins_are_refused_the_pages_own_are_served(monkeypatch):
    app = _start(monkeypatch)
    try:
        port = _port(app)
        assert app.url == f"http://127.0.0.1:{port}"
        assert _handshake(port, origin="http://evil.example") == 403
        assert _handshake(port, origin=f"http://evil.example:{port}") == 403  # a DNS-rebound name is not the page
        assert _handshake(port, origin=f"http://127.0.0.1:{port + 1}") == 403  # another local port is another page
        for own in (f"http://127.0.0.1:{port}", f"http://localhost:{port}"):
            assert str(_handshake(port, origin=own)).startswith("accepted"), own
        assert str(_handshake(port, origin=None)).startswith("accepted")  # no Origin: a non-browser client
        assert _get(port, origin="http://evil.example")[0] == 403
        assert _get(port)[0] == 200
        assert app.guard.refused == 4
        with pytest.raises(InvalidStatus) as refused:  # a second, foreign Origin header does not slip through
            with connect(f"ws://127.0.0.1:{port}/", additional_headers=[("Origin", f"http://127.0.0.1:{port}"), ("Origin", "http://evil.example")], subprotocols=[SUBPROTOCOL], open_timeout=20):
                pass
        assert refused.value.response.status_code == 403
    finally:
        app.close()


def test_listed_origins_are_served(monkeypatch):
    app = _start(monkeypatch, origins=("http://viewer.lan:8080",))
    try:
        port = _port(app)
        assert str(_handshake(port, origin="http://viewer.lan:8080")).startswith("accepted")
        assert _handshake(port, origin="http://viewer.lan:8081") == 403
    finally:
        app.close()


def test_with_a_token_only_who_has_it_gets_in(monkeypatch):
    token = secrets.token_urlsafe(18)
    app = _start(monkeypatch, token=token)
    try:
        port = _port(app)
        own = f"http://127.0.0.1:{port}"
        assert app.url == f"{own}/?token={token}"
        assert _handshake(port, origin=own) == 403
        assert _handshake(port, origin=None) == 403
        assert _handshake(port, origin=own, path="/?token=" + "x" * 24) == 403
        assert _handshake(port, origin="http://evil.example", path=f"/?token={token}") == 403  # the Origin check still holds
        assert str(_handshake(port, origin=own, path=f"/?token={token}")).startswith("accepted")
        # the page: refused without the token; with it, it sets the cookie that the page's websocket (no query string) carries
        assert _get(port)[0] == 403
        status, headers = _get(port, f"/?token={token}")
        assert status == 200
        cookie = headers["Set-Cookie"]
        assert cookie.startswith(f"iamp_viewer_token_{port}={token};") and "HttpOnly" in cookie and "SameSite=Strict" in cookie
        assert str(_handshake(port, origin=own, cookie=cookie.split(";")[0])).startswith("accepted")
        assert _handshake(port, origin=own, cookie=f"iamp_viewer_token_{port}=wrong-wrong-wrong-wrong") == 403
    finally:
        app.close()


def test_auto_and_environment_tokens(monkeypatch):
    app = _start(monkeypatch, token="auto")
    try:
        assert len(app.token) >= 16 and app.url.endswith(f"/?token={app.token}")
        assert _handshake(_port(app), origin=None) == 403
    finally:
        app.close()
    token = secrets.token_urlsafe(18)
    monkeypatch.setenv(TOKEN_ENV, token)
    app = ViewerApp(ViewerConfig(port=0, stats=False), run_id="access", log=logging.getLogger("iamp.viewer"))
    app.start()
    try:
        assert app.token == token
        assert str(_handshake(_port(app), origin=None, path=f"/?token={token}")).startswith("accepted")
    finally:
        app.close()


@pytest.mark.parametrize(
    "params, message",
    [
        ({"token": "short"}, r"token: expected \"auto\" or 16 to 256 characters"),
        ({"token": "has spaces in it, 24 chars"}, r"token: expected"),
        ({"origins": ["evil.example"]}, r"origins: 'evil.example' is not a page origin"),
        ({"origins": ["http://host:8080/path"]}, r"is not a page origin"),
    ],
)
def test_bad_token_and_origins_say_what_to_fix(monkeypatch, params, message):
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    with pytest.raises(ConfigError, match=message):
        ViewerConfig.from_params(params, where="viewer")


def test_bad_environment_token_is_refused(monkeypatch):
    monkeypatch.setenv(TOKEN_ENV, "short")
    with pytest.raises(ConfigError, match=r"\$IAMP_VIEWER_TOKEN: expected"):
        ViewerConfig.from_params({}, where="viewer")


def test_launched_viewer_with_token_and_bus_auth(tmp_path, monkeypatch):
    """The launcher prints the URL with the token; neither the token nor the bus password is on a command line."""
    token = secrets.token_urlsafe(18)
    password = "pw-" + secrets.token_hex(12)
    monkeypatch.setenv("IAMP_TEST_VIEWER_BUS_PW", password)
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    pipeline = tmp_path / "viewer.toml"
    pipeline.write_text(f"""name = "viewer-access"
[bus]
run_id = "viewer-access"
[bus.auth]
user = "iamp"
password_env = "IAMP_TEST_VIEWER_BUS_PW"
[[nodes]]
id = "viewer"
stage = "stages.viewer"
inputs = {{ track_frame = "tracker/track_frame", scene = "tracker/scene" }}
params = {{ port = 0, token = "{token}" }}
[external]
"tracker/track_frame" = "iamp.TrackFrame"
"tracker/scene" = "iamp.SceneInfo"
""")
    run = Launch(str(pipeline), cwd=tmp_path)
    try:
        m = run.wait_line(r"^\[launch\] viewer: http://127\.0\.0\.1:(\d+)/\?token=(\S+)$")
        port, printed = int(m.group(1)), m.group(2)
        assert printed == token
        run.wait_line(r"^\[launch\] all 1 nodes alive")
        lines = all_command_lines()
        assert not [c for c in lines if token in c], "the viewer token is on a command line"
        assert not [c for c in lines if password in c], "the bus password is on a command line"
        own = f"http://127.0.0.1:{port}"
        assert _handshake(port, origin="http://evil.example", path=f"/?token={token}") == 403
        assert _handshake(port, origin=own) == 403
        assert str(_handshake(port, origin=own, path=f"/?token={token}")).startswith("accepted")
        run.proc.send_signal(signal.SIGINT)
        assert run.wait() == 0, run.text()[-4000:]
    finally:
        kill_all([run.proc])
    assert "refused a handshake" in run.text()
