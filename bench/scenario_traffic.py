"""Vehicles per frame of a scenario: how busy the traffic a run shows is.

    python bench/scenario_traffic.py [--data PATH] [--recording NAME] [--sequence ID ...]
    python bench/scenario_traffic.py --mcap RUN.mcap

Counts, per frame, the vehicles (car, truck, bus, motorcycle) of a scenario as
the tracks source plays it (default: the launcher's default scenario, the
embedded K733 recording), or of the TrackFrames of a recording (``--mcap``),
and prints the median, mean, share of frames with 5 or more vehicles and the
distribution.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from bus_schemas import VEHICLE_TYPE_VALUES


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default="", help="data folder (default: the embedded stages/data/taf-bw)")
    p.add_argument("--recording", default="k733_2018-05-02")
    p.add_argument("--sequence", action="append", default=[])
    p.add_argument("--mcap", help="count the TrackFrames of this recording instead")
    args = p.parse_args()
    counts: list[int] = []
    if args.mcap:
        from bus_schemas import TrackFrame
        from stages.recorder.inspect import RecordingError, read_messages

        try:  # (raised before the first message: a file that is missing or not an MCAP recording)
            for m in read_messages(args.mcap):
                if m.schema == TrackFrame.SCHEMA:
                    f = TrackFrame.decode(m.data)
                    counts.append(int(np.isin(np.asarray(f.agent_types, dtype=np.int64), list(VEHICLE_TYPE_VALUES)).sum()))
        except RecordingError as exc:
            p.error(f"--mcap: {exc}")
        if not counts:
            p.error(f"--mcap {args.mcap}: no TrackFrame in it")
        what = args.mcap
    else:
        from stages.lib.datasets import DEFAULT_DATA_DIR, DatasetError, load_recording

        try:
            rec = load_recording(args.data or DEFAULT_DATA_DIR, args.recording, args.sequence or None)
        except DatasetError as exc:  # a data folder, recording or sequence that is not there: a bad command line
            print(f"scenario_traffic: error: {exc}", file=sys.stderr)
            return 2
        for seq in rec.sequences:
            frames, inverse = np.unique(np.asarray(seq.frame_index), return_inverse=True)
            vehicle = np.isin(np.asarray(seq.agent_type, dtype=np.int64), list(VEHICLE_TYPE_VALUES))
            counts += np.bincount(inverse, weights=vehicle, minlength=len(frames)).astype(int).tolist()
        what = f"{args.recording} {','.join(s.id for s in rec.sequences)}"
    c = np.asarray(counts)
    hist = np.bincount(c) if len(c) else np.zeros(1, int)
    print(f"{what}: frames {len(c)}, vehicles per frame median {np.median(c):.0f}, mean {c.mean():.2f}, max {c.max()}, "
          f">= 5 vehicles in {100 * (c >= 5).mean():.0f} % of frames")
    print("vehicles: frames  " + "  ".join(f"{i}: {n}" for i, n in enumerate(hist) if n))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
