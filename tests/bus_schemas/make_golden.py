"""Write golden payloads for schemas that have none yet; never overwrite one.

    python tests/bus_schemas/make_golden.py

A golden file pins the wire format of one schema version: once committed it
must keep decoding. A format change bumps VERSION and adds a new golden file.
"""

from __future__ import annotations

import sys
from pathlib import Path

from testkit.samples import SAMPLES

GOLDEN = Path(__file__).resolve().parent / "golden"


def main() -> int:
    GOLDEN.mkdir(exist_ok=True)
    for schema, make in SAMPLES.items():
        msg = make()
        path = GOLDEN / f"{schema}.v{msg.VERSION}.msgpack"
        if path.exists():
            print(f"kept {path.name}")
            continue
        path.write_bytes(msg.encode())
        print(f"wrote {path.name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
