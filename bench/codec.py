#!/usr/bin/env python3
"""Bus message codec: decode and encode ms per message type, generated codec against the reference; prints figures.

    python bench/codec.py [FILE.mcap] [--per-schema 200] [--vehicles 18] [--frames 40] [--repeat 3]

Messages: with ``FILE.mcap`` (a recording of the pipeline, e.g. ``launch.py
--record``), the first ``--per-schema`` payloads of each schema in it, as
recorded. Without it, the chain's messages (TrackFrame, CorridorSet,
RelationSet, IntentionBelief, SceneInfo; ``testkit/chain_messages.py``) for
``--frames`` frames of a recording of about ``--vehicles`` vehicles per frame
that the dense data builder (``stages/lib/datasets/superimpose.py``, as
``bench/dense.py``) superimposes from the embedded K729 sequences, so that it
runs on a fresh checkout (with ``$IAMP_TAF_BW`` set, from k733_2018-05-02 as
``bench/dense.py``).

Per schema: payloads, mean kB, then ms per message of CPU time of this
process (``time.process_time``, best of ``--repeat`` passes over all the
messages; less sensitive to other load than wall time) for ``decode`` and
``encode``, each with the reference codec alone (``bus_schemas._wire.FAST =
False``, the codec before the generated one) and with the generated codec
(``_fastcodec``, the default), and the ratio. ``same`` says whether every
message re-encodes to its payload with both codecs (for a recording made by
this build: its bytes; messages of an older schema version re-encode to
today's version and say so). Asserts nothing.
"""

from __future__ import annotations

import argparse
import collections
import sys
import tempfile
import time
from pathlib import Path

import bus_schemas as bs
from bus_schemas import _wire

SOURCES = {"k733": "k733_2018-05-02", "k729": "k729_2022-03-16"}


def recorded_payloads(path: Path, per_schema: int) -> dict[str, list[bytes]]:
    from stages.recorder.inspect import read_messages

    out: dict[str, list[bytes]] = collections.defaultdict(list)
    for rec in read_messages(str(path)):
        try:
            schema, _version = bs.peek_schema(rec.data)
        except bs.SchemaError:
            continue
        if len(out[schema]) < per_schema:
            out[schema].append(rec.data)
    return out


def chain_payloads(vehicles: int, frames: int, per_schema: int) -> tuple[str, dict[str, list[bytes]]]:
    from stages.lib.datasets import full_data_dir
    from testkit.chain_messages import dense_messages

    full = full_data_dir()
    data, recording = (full, SOURCES["k733"]) if full is not None else (None, SOURCES["k729"])
    with tempfile.TemporaryDirectory(prefix="iamp-codec-") as tmp:
        msgs = dense_messages(vehicles, frames, tmp, data_dir=data, recording=recording)
    out: dict[str, list[bytes]] = collections.defaultdict(list)
    for m in msgs:
        if len(out[m.SCHEMA]) < per_schema:
            out[m.SCHEMA].append(m.encode())
    where = f"{'full data ' + str(full) if full is not None else 'embedded data'}: {recording} superimposed to {vehicles} vehicles, {frames} frames"
    return where, out


def best_cpu_ms(fn, items: list, repeat: int) -> float:
    """Best over ``repeat`` passes of the CPU ms per item of ``fn(item)``."""
    best = float("inf")
    for _ in range(repeat):
        t0 = time.process_time()
        for item in items:
            fn(item)
        best = min(best, time.process_time() - t0)
    return best * 1e3 / max(len(items), 1)


def measure(payloads: list[bytes], repeat: int) -> dict:
    row: dict = {}
    for label, fast in (("ref", False), ("fast", True)):
        _wire.FAST = fast
        try:
            msgs = [bs.decode(d) for d in payloads]  # also builds the generated codec before timing
            row[f"same_{label}"] = all(m.encode() == d for m, d in zip(msgs, payloads))
            row[f"dec_{label}"] = best_cpu_ms(bs.decode, payloads, repeat)
            row[f"enc_{label}"] = best_cpu_ms(lambda m: m.encode(), msgs, repeat)
        finally:
            _wire.FAST = True
    return row


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("mcap", nargs="?", type=Path, help="a recording (MCAP); default: messages of the chain on a dense recording")
    parser.add_argument("--per-schema", type=int, default=200, help="payloads per schema (default 200)")
    parser.add_argument("--vehicles", type=int, default=18, help="without a file: vehicles per frame of the dense recording (default 18)")
    parser.add_argument("--frames", type=int, default=40, help="without a file: frames played through the chain (default 40)")
    parser.add_argument("--repeat", type=int, default=3, help="passes per measurement, best kept (default 3)")
    args = parser.parse_args(argv)
    for flag, value in (("--per-schema", args.per_schema), ("--vehicles", args.vehicles), ("--frames", args.frames), ("--repeat", args.repeat)):
        if value < 1:
            parser.error(f"{flag} {value}: must be >= 1")
    from stages.lib.datasets import DatasetError
    from stages.recorder.inspect import RecordingError

    try:
        if args.mcap is not None:
            where, payloads = f"recording {args.mcap}", recorded_payloads(args.mcap, args.per_schema)
        else:
            where, payloads = chain_payloads(args.vehicles, args.frames, args.per_schema)
    except (RecordingError, DatasetError) as exc:  # a file that is missing or not an MCAP recording; --vehicles out of range
        print(f"codec: error: {exc}", file=sys.stderr)
        return 2
    print(f"messages: {where}; CPU ms per message, best of {args.repeat}; ref: reference codec alone, fast: generated codec")
    print(f"{'schema':<26}{'n':>5}{'kB':>8} | {'decode ref':>10}{'fast':>8}{'x':>6} | {'encode ref':>10}{'fast':>8}{'x':>6} | same")
    for schema in sorted(payloads):
        data = payloads[schema]
        r = measure(data, args.repeat)
        kb = sum(map(len, data)) / len(data) / 1e3
        same = "yes" if r["same_ref"] and r["same_fast"] else f"no (ref {r['same_ref']}, fast {r['same_fast']})"
        print(f"{schema:<26}{len(data):>5}{kb:>8.1f} | {r['dec_ref']:>10.2f}{r['dec_fast']:>8.2f}{r['dec_ref'] / max(r['dec_fast'], 1e-9):>6.1f}"
              f" | {r['enc_ref']:>10.2f}{r['enc_fast']:>8.2f}{r['enc_ref'] / max(r['enc_fast'], 1e-9):>6.1f} | {same}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
