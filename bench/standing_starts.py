"""When do standing cars start? Their true 4 s future by what the scene shows at the instant (the leader on their corridor).

What it measures. For every standing vehicle (speed estimated from positions
<= 0.5 m/s, matched, with a full 4 s future) at instants ``--stride`` apart,
it looks at its most probable corridor's relation (``RelationSet``): no
leader within ``--gap`` m, a standing leader (speed <= ``--leader-moving``
m/s), a leader that moves. Per group it prints the windows, the share that
starts (the true position moves 1 m or more within 4 s), the true
displacement at 4 s (mean, median), and the start rate of an exponential
waiting time that fits P(still standing at 4 s) (λ = -ln(P_stay(4 s))/4 s),
the form of the chain's standstill mixture (``standstill_start_rate_hz``).
Chain without intentions (corridor order of the CorridorSet when no belief).
It asserts nothing.

Run::

    IAMP_TAF_BW=/path/to/taf-bw python bench/standing_starts.py --recording k729_2022-03-16 [--stride 0.4] [--gap 25]
"""

from __future__ import annotations

import argparse
import collections
import json
import math
import sys
from pathlib import Path

import numpy as np

from bus_schemas import AgentType, MatchStatus
from stages.corridors import SceneMaps
from stages.lib.datasets import DatasetError, find_recording, full_data_dir, load_ref
from stages.offline.chain import Chain
from stages.offline.truth import future_positions, ground_truth
from stages.lib.base import check_output_arg


def leader_group(rel, gap_m: float, moving_mps: float) -> str:
    if rel is None or rel.leader_track_id < 0 or not math.isfinite(rel.leader_gap_m) or rel.leader_gap_m > gap_m:
        return "no_leader"
    speed = rel.leader_speed_mps
    if not math.isfinite(speed):
        return "leader_unknown_speed"
    return "leader_moving" if speed > moving_mps else "leader_standing"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", type=Path, default=None)
    p.add_argument("--recording", required=True)
    p.add_argument("--stride", type=float, default=0.4)
    p.add_argument("--gap", type=float, default=25.0, help="a leader further than this counts as none (m)")
    p.add_argument("--leader-moving", type=float, default=1.0, help="a leader faster than this moves (m/s)")
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args(argv)
    check_output_arg(p, args.json, "--json")  # before the work: a bad path must not cost the run
    data = args.data or full_data_dir()
    if data is None:
        sys.stderr.write("standing_starts: error: set IAMP_TAF_BW or pass --data\n")
        return 2
    try:  # a data folder or recording that is not there: a bad command line
        ref = find_recording(Path(data), args.recording)
    except DatasetError as exc:
        sys.stderr.write(f"standing_starts: error: {exc}\n")
        return 2
    rec = load_ref(ref, tuple(ref.sequence_ids), display_root=Path(data))
    maps = SceneMaps(data=Path(data))
    groups: dict[str, list[tuple[bool, float]]] = collections.defaultdict(list)
    tau_ns, n_steps = 400_000_000, 10
    stride_ns = int(round(args.stride * 1e9))
    for seq in rec.sequences:
        truth = ground_truth(seq)
        first = int(seq.stamp_ns[0]) if seq.n_rows else 0
        for item in Chain(rec, seq, maps, intentions=None, run_id="bench", producer="bench"):
            if item.corridor_set is None:
                continue
            off = item.stamp_ns - first
            if off % stride_ns > 1_000_000 and stride_ns - off % stride_ns > 1_000_000:
                continue
            rels = {(r.track_id, r.corridor_id): r for r in item.relation_set.relations} if item.relation_set is not None else {}
            frame = item.frame
            rows = {int(t): i for i, t in enumerate(frame.track_ids)}
            for v in item.corridor_set.vehicles:
                if v.status != MatchStatus.MATCHED or not v.corridors or not (v.speed_mps <= 0.5):
                    continue
                if not AgentType(int(v.agent_type)).is_vehicle or v.track_id not in rows:
                    continue
                fut = future_positions(truth.get(v.track_id), item.stamp_ns, tau_ns, n_steps)
                if fut is None:
                    continue
                row = rows[v.track_id]
                start = np.array([frame.x_m[row], frame.y_m[row]])
                disp = np.hypot(*(fut - start).T)
                rel = rels.get((v.track_id, v.corridors[0].corridor_id))
                groups[leader_group(rel, args.gap, args.leader_moving)].append((bool(np.any(disp >= 1.0)), float(disp[-1])))
    out = {}
    print(f"{args.recording}: standing vehicles (<= 0.5 m/s), stride {args.stride} s, leader within {args.gap} m, moving > {args.leader_moving} m/s")
    print(f"{'group':<22} {'windows':>7} {'start':>6} {'disp4 mean':>10} {'median':>7} {'rate_hz':>8}")
    for name in sorted(groups):
        starts = np.array([s for s, _ in groups[name]])
        disp = np.array([d for _, d in groups[name]])
        stay = 1.0 - starts.mean()
        rate = -math.log(max(stay, 1e-3)) / 4.0
        out[name] = {"windows": int(starts.size), "start_share": float(starts.mean()), "disp4_mean_m": float(disp.mean()),
                     "disp4_median_m": float(np.median(disp)), "start_rate_hz": rate}
        print(f"{name:<22} {starts.size:>7d} {starts.mean():>6.2f} {disp.mean():>10.2f} {np.median(disp):>7.2f} {rate:>8.3f}")
    if args.json:
        args.json.write_text(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
