"""``BusClient``: a plain Zenoh session for tools that are not stages (launcher, replay, recorder tests, benchmarks)."""

from __future__ import annotations

import functools
import socket
from typing import Any, Callable, Iterable

import zenoh

from stages.runtime.args import endpoint_address, open_session


@functools.lru_cache(maxsize=64)
def _addresses(host: str, port: int) -> frozenset[str]:
    """``host`` and the addresses it resolves to (resolved once: the launcher asks again every few seconds)."""
    try:
        return frozenset({host} | {str(info[4][0]) for info in socket.getaddrinfo(host, port)})
    except OSError:
        return frozenset({host})


class BusClient:
    """A plain session for tools that are not stages: publish, subscribe, watch liveliness.

    Used by the launcher (liveliness, progress), replay, tests and benchmarks,
    so that they too never import zenoh themselves.
    """

    def __init__(self, mode: str = "peer", connect: Iterable[str] = (), listen: Iterable[str] = (), config_file: str | None = None) -> None:
        self.session = open_session(mode, connect, listen, config_file)
        self._keep: list[Any] = []

    def __enter__(self) -> "BusClient":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def close(self) -> None:
        try:
            self.session.close()
        except Exception:
            pass

    def locators(self) -> list[str]:
        """Endpoints this session listens on (with the real port when 0 was asked)."""
        return _own_locators(self.session)

    def linked_to(self, endpoint: str) -> bool:
        """Whether this session has a link whose far end is ``endpoint`` (its host name resolved): the link it opens to
        a ``--connect`` endpoint once something there accepts it. (A peer at that endpoint that opened its own link to
        this session first is reached through that one instead, which is not counted here.)"""
        want = endpoint_address(endpoint)
        if want is None:
            return False
        proto, host, port = want
        hosts = _addresses(host, port)
        for link in self.session.info.links():
            got = endpoint_address(str(link.dst))
            if got is not None and got[0] == proto and got[2] == port and got[1] in hosts:
                return True
        return False

    def publisher(self, key: str, *, block: bool = True) -> Callable[[bytes], None]:
        pub = self.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP)
        self._keep.append(pub)
        return lambda data: pub.put(data)

    def publisher_with_matching(self, key: str) -> tuple[Callable[[bytes], None], Callable[[], bool]]:
        pub = self.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
        self._keep.append(pub)
        return (lambda data: pub.put(data)), (lambda: bool(pub.matching_status.matching))

    def put(self, key: str, data: bytes) -> None:
        self.session.put(key, data, congestion_control=zenoh.CongestionControl.BLOCK)

    def subscribe(self, key: str, callback: Callable[[str, bytes], None]) -> None:
        def cb(sample: Any) -> None:
            callback(str(sample.key_expr), sample.payload.to_bytes())

        self._keep.append(self.session.declare_subscriber(key, cb))

    def watch_alive(self, pattern: str, callback: Callable[[str, bool], None]) -> None:
        """Call ``callback(node_id, alive)`` for every liveliness change (with history)."""

        def cb(sample: Any) -> None:
            callback(str(sample.key_expr).rsplit("/", 1)[-1], sample.kind == zenoh.SampleKind.PUT)

        self._keep.append(self.session.liveliness().declare_subscriber(pattern, cb, history=True))

    def alive_now(self, pattern: str, timeout_s: float = 2.0) -> set[str]:
        out = set()
        for reply in self.session.liveliness().get(pattern, timeout=timeout_s):
            if reply.ok is not None:
                out.add(str(reply.ok.key_expr).rsplit("/", 1)[-1])
        return out

    def declare_queryable(self, key: str, reply: Callable[[], bytes | None]) -> None:
        """Answer queries on ``key`` with ``reply()`` (nothing when it returns None)."""

        def cb(query: Any) -> None:
            data = reply()
            if data is not None:
                query.reply(key, data)

        self._keep.append(self.session.declare_queryable(key, cb))

    def declare_token(self, key: str) -> None:
        self._keep.append(self.session.liveliness().declare_token(key))

    def query(self, key: str, timeout_s: float = 2.0) -> list[bytes]:
        out = []
        for reply in self.session.get(key, timeout=timeout_s):
            if reply.ok is not None:
                out.append(reply.ok.payload.to_bytes())
        return out


def _own_locators(session: zenoh.Session) -> list[str]:
    info = session.info
    # zenoh-python exposes the session's own locators through its config/state; fall back to none
    for attr in ("locators",):
        fn = getattr(info, attr, None)
        if callable(fn):
            try:
                return [str(x) for x in fn()]
            except Exception:
                pass
    return []
