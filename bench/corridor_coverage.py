"""Corridor coverage on TAF-BW: how often the true future stays on one of a car's corridors.

Runs the corridors core in-process over every frame of every sequence of
each recording, then, per recording and overall:

- ``car_positions_matched_share``: car (vehicle, frame) pairs that are MATCHED;
- ``cars_with_corridor_share``: car tracks that got corridors in at least one
  frame (``cars_always_matched_share``: in every frame);
- ``corridors_per_car_mean``: corridors per MATCHED pair;
- ``future_within_2m_share``: among car pairs with a full 4 s future (true
  positions at t + 0.4 k s, k = 1..10), the share whose ten future positions
  all lie within 2 m of the centreline of one single corridor of that pair:
  the ceiling for every later prediction;
- ``frames``: frames processed;
- ``misses``: the pairs that fail, by first applicable cause:
  ``off_map_start`` (not MATCHED at t; ``off_map_heading_start`` when lanelets
  were near but none agreed in heading), ``too_short`` (a corridor holds the
  future laterally but ends before it), ``future_off_map`` (a future
  position lies inside no car lanelet: unmapped lane or area, such as K733's
  missing fourth lane), ``wide_of_centreline`` (the final position is on a
  corridor's lanelets, but the path strays > 2 m from the centreline),
  ``lane_change`` (it ends on a left/right neighbour of a corridor lanelet or
  a successor of one), ``route_not_among`` (anything else);
  ``misses_within_2_5m``: misses whose best corridor holds the future
  within 2.5 m (marginal).

    python bench/corridor_coverage.py [--data PATH] [--recording NAME] [--json FILE] [--set KEY=VALUE ...]

``--set`` overrides a ``CorridorsConfig`` parameter (JSON value, else a
string), e.g. ``--set lane_change_corridors=false``.

PATH defaults to the full TAF-BW recordings named by ``$IAMP_TAF_BW``, else
the embedded ``stages/data/taf-bw``.
Prints figures, asserts nothing.
"""

from __future__ import annotations

import argparse
import collections
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

from bus_schemas import AgentType, MatchStatus
from plot_frame import default_data_dir, scene_for, track_frames
from stages.corridors import CorridorBuilder, CorridorsConfig, SceneMaps
from stages.lib.datasets import DatasetError, discover, find_recording, load_recording
from stages.lib.base import check_output_arg

HORIZON_STEPS = 10
STEP_FRAMES = 4  # 0.4 s at 10 Hz
TOLERANCE_M = 2.0
MARGINAL_M = 2.5
CAUSES = (
    "off_map_start",
    "off_map_heading_start",
    "too_short",
    "future_off_map",
    "wide_of_centreline",
    "lane_change",
    "route_not_among",
)


def _distances_m(points: np.ndarray, line: np.ndarray) -> np.ndarray:
    """Distance of points (n, 2) to a polyline (m, 2), segments clipped at its ends."""
    seg = np.diff(line, axis=0)
    len2 = np.maximum((seg**2).sum(axis=1), 1e-18)
    rel = points[:, None, :] - line[None, :-1, :]
    t = np.clip((rel * seg[None]).sum(axis=2) / len2[None], 0.0, 1.0)
    return np.sqrt(((rel - t[..., None] * seg[None]) ** 2).sum(axis=2).min(axis=1))


def _frenet(points: np.ndarray, line: np.ndarray):
    """(s, |d|) of points on a polyline extended straight at both ends; s in the line's arc length."""
    seg = np.diff(line, axis=0)
    seg_len = np.hypot(seg[:, 0], seg[:, 1])
    arc = np.concatenate([[0.0], np.cumsum(seg_len)])
    lower = np.zeros(len(seg))
    upper = np.ones(len(seg))
    lower[0], upper[-1] = -np.inf, np.inf
    rel = points[:, None, :] - line[None, :-1, :]
    t = np.clip((rel * seg[None]).sum(axis=2) / np.maximum(seg_len**2, 1e-18)[None], lower[None], upper[None])
    dist2 = ((rel - t[..., None] * seg[None]) ** 2).sum(axis=2)
    j = dist2.argmin(axis=1)
    rows = np.arange(len(points))
    return arc[j] + t[rows, j] * seg_len[j], np.sqrt(dist2[rows, j]), arc[-1]


class _Tally:
    def __init__(self) -> None:
        self.frames = 0
        self.car_pairs = 0
        self.matched = 0
        self.corridors = 0
        self.tracks: dict[tuple[str, int], list[int]] = {}
        self.with_future = 0
        self.covered = 0
        self.misses: collections.Counter = collections.Counter()
        self.marginal = 0
        self.core_s = 0.0

    def add(self, other: "_Tally") -> None:
        self.frames += other.frames
        self.car_pairs += other.car_pairs
        self.matched += other.matched
        self.corridors += other.corridors
        self.tracks.update(other.tracks)
        self.with_future += other.with_future
        self.covered += other.covered
        self.misses.update(other.misses)
        self.marginal += other.marginal
        self.core_s += other.core_s

    def summary(self) -> dict:
        def share(a: int, b: int) -> float:
            return round(a / b, 4) if b else float("nan")

        n_tracks = len(self.tracks)
        return {
            "car_positions_matched_share": share(self.matched, self.car_pairs),
            "cars_with_corridor_share": share(sum(1 for m, _ in self.tracks.values() if m > 0), n_tracks),
            "corridors_per_car_mean": round(self.corridors / self.matched, 3) if self.matched else float("nan"),
            "future_within_2m_share": share(self.covered, self.with_future),
            "frames": self.frames,
            "cars_always_matched_share": share(sum(1 for m, n in self.tracks.values() if m == n), n_tracks),
            "car_pairs": self.car_pairs,
            "car_tracks": n_tracks,
            "pairs_with_future": self.with_future,
            "misses": {cause: self.misses.get(cause, 0) for cause in CAUSES},
            "misses_within_2_5m": self.marginal,
            "core_ms_per_frame": round(1e3 * self.core_s / self.frames, 3) if self.frames else float("nan"),
        }


def evaluate_sequence(recording, sequence, scene_maps: SceneMaps, config: CorridorsConfig) -> _Tally:
    """Run the core over one sequence and score every car pair with a full future."""
    tally = _Tally()
    scene = scene_for(recording, sequence)
    builder = CorridorBuilder(config, scene_maps=scene_maps)
    vehicle_values = [t.value for t in AgentType if t.is_vehicle]
    results: dict[tuple[int, int], object] = {}
    issue_kind: dict[tuple[int, int], str] = {}
    for view, frame in track_frames(sequence, scene.scene_id):
        t0 = time.perf_counter()
        corridor_set, issues = builder.process(frame, scene)
        tally.core_s += time.perf_counter() - t0
        tally.frames += 1
        for issue in issues:
            issue_kind[(issue.agent_id, view.frame_index)] = issue.kind
        for vehicle in corridor_set.vehicles:
            if int(vehicle.agent_type) not in vehicle_values:
                continue
            results[(vehicle.track_id, view.frame_index)] = vehicle
            tally.car_pairs += 1
            key = (sequence.id, vehicle.track_id)
            counts = tally.tracks.setdefault(key, [0, 0])
            counts[1] += 1
            if vehicle.status == MatchStatus.MATCHED:
                tally.matched += 1
                tally.corridors += len(vehicle.corridors)
                counts[0] += 1
    road_map = builder.scene_map.road_map if builder.scene_map is not None else None
    positions = {(int(t), int(f)): (x, y) for t, f, x, y in zip(sequence.track_id, sequence.frame_index, sequence.x_m, sequence.y_m)}
    for (track_id, frame_index), vehicle in results.items():
        future_keys = [(track_id, frame_index + STEP_FRAMES * k) for k in range(1, HORIZON_STEPS + 1)]
        if not all(k in positions for k in future_keys):
            continue
        tally.with_future += 1
        future = np.array([positions[k] for k in future_keys])
        if vehicle.status != MatchStatus.MATCHED or road_map is None:
            heading = issue_kind.get((track_id, frame_index)) == "off_map_heading"
            tally.misses["off_map_heading_start" if heading else "off_map_start"] += 1
            continue
        lines = [np.column_stack([c.x_m, c.y_m]) for c in vehicle.corridors]
        best_m = min(float(_distances_m(future, line).max()) for line in lines)
        if best_m <= TOLERANCE_M:
            tally.covered += 1
            continue
        tally.marginal += best_m <= MARGINAL_M
        tally.misses[_cause(road_map, vehicle, lines, future)] += 1
    return tally


def _cause(road_map, vehicle, lines, future: np.ndarray) -> str:
    for line in lines:
        s, d, end = _frenet(future, line)
        if (d <= TOLERANCE_M).all() and (s > end).any():
            return "too_short"
    containing = road_map.lanelets_containing(future)
    if any(not ids for ids in containing):
        return "future_off_map"
    corridor_lanelets = {int(x) for c in vehicle.corridors for x in c.lanelet_ids}
    final = set(containing[-1])
    if final & corridor_lanelets:
        return "wide_of_centreline"
    adjacent = set()
    for lanelet_id in corridor_lanelets:
        neighbours = road_map.neighbours(lanelet_id)
        for other in (neighbours.left_id, neighbours.right_id):
            if other is not None and road_map.has_lanelet(other):
                adjacent.add(other)
                for succ in road_map.successors(other):
                    adjacent.add(succ)
                    adjacent.update(road_map.successors(succ))
    return "lane_change" if final & adjacent else "route_not_among"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=None, help="folder laid out like taf-bw (default: beside the repo)")
    parser.add_argument("--recording", action="append", default=[], help="recording name (repeatable; default all)")
    parser.add_argument("--json", type=Path, default=None, help="write the figures here")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a CorridorsConfig parameter")
    args = parser.parse_args(argv)
    check_output_arg(parser, args.json, "--json")  # before the work: a bad path must not cost the run
    data = args.data or default_data_dir()
    try:  # before the work: a data folder or recording that is not there is a bad command line
        names = args.recording or [ref.name for ref in discover(data)]
        for name in args.recording:
            find_recording(data, name)
    except DatasetError as exc:
        print(f"corridor_coverage: error: {exc}", file=sys.stderr)
        return 2
    params = {}
    for item in args.set:
        key, _, value = item.partition("=")
        try:
            params[key.strip()] = json.loads(value)
        except json.JSONDecodeError:
            params[key.strip()] = value
    config = CorridorsConfig.from_params(params, where="--set")
    overall = _Tally()
    report: dict = {"data": str(data), "config": {k: getattr(config, k) for k in config.__dataclass_fields__}, "recordings": {}}
    for name in names:
        recording = load_recording(data, name)
        scene_maps = SceneMaps(config, data=data)
        tally = _Tally()
        for sequence in recording.sequences:
            if sequence.n_rows:
                tally.add(evaluate_sequence(recording, sequence, scene_maps, config))
        report["recordings"][name] = tally.summary()
        overall.add(tally)
    report["overall"] = overall.summary()
    columns = ("car_positions_matched_share", "cars_with_corridor_share", "corridors_per_car_mean", "future_within_2m_share", "frames", "pairs_with_future")
    short = ("matched", "cars_w_corr", "corr/car", "future<=2m", "frames", "pairs_4s")
    print(f"{'recording':18s} " + " ".join(f"{h:>11s}" for h in short))
    for name, row in list(report["recordings"].items()) + [("overall", report["overall"])]:
        print(f"{name:18s} " + " ".join(f"{row[c]:>11}" for c in columns))
    print("\nmisses by cause (pairs with a full 4 s future):")
    print(f"{'recording':18s} " + " ".join(f"{c:>22s}" for c in CAUSES))
    for name, row in list(report["recordings"].items()) + [("overall", report["overall"])]:
        print(f"{name:18s} " + " ".join(f"{row['misses'][c]:>22d}" for c in CAUSES))
    print("\nmisses within 2.5 m: " + ", ".join(f"{n} {r['misses_within_2_5m']}" for n, r in list(report["recordings"].items()) + [("overall", report["overall"])]))
    print(f"core time per frame: overall {report['overall']['core_ms_per_frame']} ms")
    if args.json:
        args.json.write_text(json.dumps(report, indent=2, default=lambda x: None if isinstance(x, float) and math.isnan(x) else str(x)))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
