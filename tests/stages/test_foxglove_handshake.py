"""The live Foxglove bridge and a client that offers only the old subprotocol name.

foxglove-sdk's server (0.30) accepts the subprotocol ``foxglove.sdk.v1``
(and ``foxglove.sdk.v1.1``) only, and has no hook for the handshake: a client
that offers only ``foxglove.websocket.v1`` (older Foxglove and Lichtblick
releases) gets a bare HTTP 400 ("Missing expected sec-websocket-protocol
header") and the SDK logs "Dropping client ...: handshake failed". The
bridge turns that line into one that says which subprotocol the server
speaks and what to upgrade. Raw HTTP upgrade requests on 127.0.0.1.
"""

from __future__ import annotations

import base64
import logging
import os
import socket

import pytest

from testkit.helpers import free_port, wait_until

pytest.importorskip("foxglove")

from stages.foxglove_bridge.config import FoxgloveConfig  # noqa: E402
from stages.foxglove_bridge.core import FoxgloveBridge  # noqa: E402


def handshake(port: int, protocol: str | None) -> tuple[str, str]:
    """Send a WebSocket upgrade request offering ``protocol``; returns (the response head and body, the client's host:port)."""
    with socket.create_connection(("127.0.0.1", port), timeout=30) as s:
        client = "%s:%d" % s.getsockname()
        key = base64.b64encode(os.urandom(16)).decode()
        request = (f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                   f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n")
        if protocol is not None:
            request += f"Sec-WebSocket-Protocol: {protocol}\r\n"
        s.sendall((request + "\r\n").encode())
        data = b""
        while b"\r\n\r\n" not in data:
            chunk = s.recv(4096)
            if not chunk:
                break
            data += chunk
        if data.startswith(b"HTTP/1.1 400"):  # the body follows the head; the server closes after it
            while chunk := s.recv(4096):
                data += chunk
    return data.decode("latin-1"), client


@pytest.fixture
def bridge():
    b = FoxgloveBridge(FoxgloveConfig(port=free_port()), run_id="hs", log=logging.getLogger("iamp.foxglove.test"))
    b.start()
    try:
        yield b
    finally:
        b.close()


def test_a_client_offering_only_the_old_subprotocol_is_refused_with_one_line_that_says_what_to_upgrade(bridge, caplog):
    caplog.set_level(logging.INFO)
    # a current client (offering both names, as current Foxglove and Lichtblick do) is accepted
    ok, current = handshake(bridge.port, "foxglove.sdk.v1, foxglove.websocket.v1")
    assert ok.startswith("HTTP/1.1 101") and "sec-websocket-protocol: foxglove.sdk.v1" in ok.lower(), ok

    response, client = handshake(bridge.port, "foxglove.websocket.v1")
    assert response.startswith("HTTP/1.1 400"), response  # the SDK's refusal: no hook to change it

    def refusals():
        return [r for r in caplog.records if "refused at the WebSocket handshake" in r.getMessage()]

    wait_until(lambda: any(client in r.getMessage() for r in refusals()), 30.0, f"a log line naming the refused client {client}")
    (line,) = refusals()  # one line, and none for the accepted client
    text = line.getMessage()
    assert client in text and current not in text and line.levelno == logging.WARNING and "\n" not in text, text
    assert "subprotocol foxglove.sdk.v1" in text and "foxglove.websocket.v1" in text and "upgraded" in text, text
    assert not [r for r in caplog.records if "Dropping client" in r.getMessage()], "the SDK's bare line is replaced"
    assert bridge.handshake_note.refused >= 1


def test_the_repeat_filter_gives_every_handler_the_same_answer_for_one_record():
    from stages.foxglove_bridge.core import RepeatFilter

    flt = RepeatFilter(clock=lambda: 0.0)
    got: list[list[str]] = [[], []]

    class Collect(logging.Handler):
        def __init__(self, into: list[str]) -> None:
            super().__init__()
            self.into = into
            self.addFilter(flt)

        def emit(self, record: logging.LogRecord) -> None:
            self.into.append(record.getMessage())

    logger = logging.getLogger("foxglove.test_repeat")
    logger.propagate, logger.level = False, logging.INFO
    handlers = [Collect(got[0]), Collect(got[1])]
    for h in handlers:
        logger.addHandler(h)
    try:
        logger.error("Dropping client 127.0.0.1:1: handshake failed")
        logger.error("Dropping client 127.0.0.1:2: handshake failed")  # the same kind at once: held back at both
    finally:
        for h in handlers:
            logger.removeHandler(h)
    assert got[0] == got[1] == ["Dropping client 127.0.0.1:1: handshake failed"]
