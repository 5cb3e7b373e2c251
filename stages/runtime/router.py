"""A Zenoh router for spreading stages over machines, where ``zenohd`` is not installed.

    python -m stages.runtime.router [--listen tcp/0.0.0.0:7447] [--config FILE]

A Zenoh session in router mode (the same routing code as ``zenohd``, from
the eclipse-zenoh package the project already depends on): the stages on
every machine start with ``--mode client --connect tcp/ROUTER_HOST:7447``
(launch.py: the pipeline's ``[bus]`` section) and reach each other through
it. Prints one line ``router listening on ENDPOINT ...`` once it listens,
then runs until SIGINT/SIGTERM. Exit codes: 0 clean stop, 2 bad command
line (an endpoint it cannot listen on).
"""

from __future__ import annotations

import argparse
import sys
import threading

from stages.runtime.args import on_stop_signals, open_session

DEFAULT_ROUTER_LISTEN = "tcp/0.0.0.0:7447"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m stages.runtime.router", description=__doc__.split("\n")[0].replace("``", ""))
    parser.add_argument("--listen", action="append", default=[], metavar="ENDPOINT", help=f"endpoint to listen on (default {DEFAULT_ROUTER_LISTEN})")
    parser.add_argument("--connect", action="append", default=[], metavar="ENDPOINT", help="another router to connect to")
    parser.add_argument("--config", metavar="FILE", help="zenoh JSON5 config file; the flags above override it")
    args = parser.parse_args(argv)
    try:
        session = open_session("router", args.connect, args.listen or [DEFAULT_ROUTER_LISTEN], args.config)
    except Exception as exc:  # noqa: BLE001 - a bad endpoint or config: say what, exit 2
        sys.stderr.write(f"router: cannot start: {exc}\n")
        return 2
    stop = threading.Event()
    on_stop_signals(lambda *_: stop.set())
    from stages.runtime.bus import _own_locators

    print(f"router listening on {' '.join(_own_locators(session)) or ' '.join(args.listen or [DEFAULT_ROUTER_LISTEN])}", flush=True)
    while not stop.wait(0.5):
        pass
    session.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
