"""``BusClient``: a plain Zenoh session for tools that are not stages (launcher, replay, recorder tests, benchmarks)."""

from __future__ import annotations

from typing import Any, Callable, Iterable

import zenoh

from stages.runtime.args import open_session


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
