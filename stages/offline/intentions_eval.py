"""Evaluation of the intentions (route and stop/go) on recordings, in-process (docs/method.md §7, §7.6).

    python -m stages.offline.intentions_eval --data PATH [--recording NAME] [--sequence ID] [--particles N] [--seeds 0 1 2] [--json FILE]

Runs TrackPlayer → CorridorBuilder → RelationExtractor → IntentionFilter as
plain cores over every sequence (``stages.offline.chain``, the chain of
``iamp eval`` and ``iamp train``: fresh cores per sequence, maps loaded
once), then scores the published beliefs against what the cars really did
(``stages.offline.truth``, the ground truth of ``iamp eval``).

Entering an intersection. A car is inside an intersection when its matched
lanelet (``VehicleCorridors.lanelet_id``) is a member of one
(``RoadMap.intersections``) and its arc length on that lanelet has reached
the member's entry (its first conflict point), the same entrance the
relations stage reports. An *entering event* is a frame where a car is
inside and was not at its previous frame (``entering_events``).

Route (``route_top1``). A window is a frame where a car has a belief over at
least two corridors and a next entering event; τ = t_enter − t is its time
before the entrance. The corridor it really followed is judged from its
true future at t + 0.4k s, k = 1..10 (4 s): the corridor whose centreline
holds the future best, i.e. with the smallest maximum lateral distance of
the future positions (``truth.followed_corridor``, the rule of ``iamp
eval`` and ``iamp train``: over the positions that project within the
corridor, whose polyline includes its own straight extension, at least
``min_future_steps`` of them).
TAF-BW tracks end 1 to 3 s after the entrance (the sensors' field of
view), so a future shorter than 4 s is used as far as it goes (at least
``min_future_steps`` positions; the tie rule below drops the windows it
cannot decide). Windows where that is
above ``max_route_error_m`` (it followed none) or where another corridor is
within ``route_tie_m`` of it (the future cannot tell them apart) are left
out and counted. route_top1 is the share of windows whose true corridor
gets the highest probability, for three predictors: the intentions (P(R =
c)), a uniform prior and the nearest corridor (smallest |d| now); a k-way
tie for the highest probability counts 1/k (``truth.route_top1``, as in
``iamp eval``), so uniform is exactly 1/n (also reported as
``uniform_expected``). Reported per bin of τ: 3, 2, 1
and 0 s, each ± ``bin_half_width_s`` (every frame in the bin is a window).

Stop/go (``stop_go``). Per entering event, the car *stopped* when its speed
stayed below ``standstill_speed_mps`` for at least ``standstill_min_s``
between its previous entering event (or the track start) and entering;
its reference time is the start of the last such standstill. A car that
*went* has as reference time the entering itself. Reported: the mean P(I =
stop) of the car's belief at 3, 2, 1 and 0 s before the reference time (±
the bin half width), per class; also where the stoppers stood, relative to
the entrance (``stop_position_m``: distance from the standstill position to
the entrance of the intersection then ahead on the car's most probable
corridor; this measured the default ``stop_offset_m``).

A particle filter's answer is random: ``--seeds`` runs the filter once per
seed on the same windows and pools them (the shares are then means over the
seeds; the route table also gives each seed's range). ``--json`` writes the
report (tables, counts, per-frame timing of ``IntentionFilter.process``);
the tables are printed.
"""

from __future__ import annotations

import argparse
import bisect
import dataclasses
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from bus_schemas import MatchStatus
from stages.corridors import SceneMaps
from stages.lib.datasets import DEFAULT_DATA_DIR, default_recordings, discover, load_recording
from stages.lib.maps import RoadMap
from stages.tracks_source.core import file_sha256
from stages.lib.base import json_safe

from stages.intentions.core import IntentionsConfig
from stages.offline.chain import ChainFrame, chain_frames, with_beliefs
from stages.offline.truth import ROUTE_MAX_ERROR_M, ROUTE_TIE_M, Track, followed_corridor, future_run, ground_truth, route_decision, route_top1

BINS_S = (3.0, 2.0, 1.0, 0.0)
_NS = 1e-9


@dataclass(frozen=True, kw_only=True)
class IntentionEvalConfig:
    """What to evaluate and how (module docstring)."""

    data_dir: Path = DEFAULT_DATA_DIR
    recordings: tuple[str, ...] = ()
    sequences: tuple[str, ...] = ()
    params: tuple[tuple[str, Any], ...] = ()
    bins_s: tuple[float, ...] = BINS_S
    bin_half_width_s: float = 0.2
    horizon_s: float = 4.0
    step_s: float = 0.4
    min_future_steps: int = 2
    max_route_error_m: float = ROUTE_MAX_ERROR_M
    route_tie_m: float = ROUTE_TIE_M
    standstill_speed_mps: float = 0.5
    standstill_min_s: float = 1.0
    seeds: tuple[int, ...] = (0,)

    def intentions_config(self) -> IntentionsConfig:
        return IntentionsConfig.from_params(dict(self.params), where="intentions evaluation")


# --------------------------------------------------------------------------- running the chain
# ``chain_frames`` and ``ChainFrame``: ``stages.offline.chain``; ``run_filter``: a fresh filter over the frames.

run_filter = with_beliefs


# --------------------------------------------------------------------------- ground truth (``stages.offline.truth``) and entering


def entering_events(frames: Sequence[ChainFrame], road_map: RoadMap) -> dict[int, list[tuple[int, int]]]:
    """Per track id: (stamp_ns, intersection id) of every entering event (module docstring), in time order."""
    inside_before: dict[int, bool] = {}
    events: dict[int, list[tuple[int, int]]] = {}
    for item in frames:
        stamp = int(item.frame.header.stamp_ns)
        for vehicle in item.corridor_set.vehicles:
            if vehicle.status != MatchStatus.MATCHED or not vehicle.corridors or not road_map.has_lanelet(vehicle.lanelet_id):
                continue
            intersection = road_map.intersection_of(vehicle.lanelet_id)
            inside = False
            if intersection is not None:
                member = intersection.member(vehicle.lanelet_id)
                for corridor in vehicle.corridors:
                    hit = np.flatnonzero(np.asarray(corridor.lanelet_ids) == vehicle.lanelet_id)
                    if hit.size:
                        inside = corridor.vehicle_s_m - float(corridor.lanelet_start_s_m[hit[0]]) >= member.entry_s_m
                        break
            if inside and inside_before.get(vehicle.track_id) is False:
                events.setdefault(vehicle.track_id, []).append((stamp, intersection.intersection_id))
            inside_before[vehicle.track_id] = inside
    return events


# --------------------------------------------------------------------------- metrics


def bin_of(tau_s: float, bins_s: Sequence[float], half_width_s: float) -> float | None:
    """The bin centre τ falls in (± half width), or None."""
    for b in bins_s:
        if abs(tau_s - b) <= half_width_s + 1e-9:
            return b
    return None


@dataclass(frozen=True, slots=True)
class RouteWindow:
    """One scored frame of one car: its bin, its corridors' scores and the true corridor's index."""

    recording: str
    track_id: int
    stamp_ns: int
    tau_s: float
    bin_s: float
    truth: int
    probabilities: np.ndarray
    abs_d_m: np.ndarray
    manoeuvres: tuple[int, ...] = ()


def route_windows(
    frames: Sequence[ChainFrame], tracks, events, cfg: IntentionEvalConfig, recording: str, skipped: dict[str, int]
) -> list[RouteWindow]:
    """The route windows of one sequence (module docstring); reasons for leaving frames out are counted in `skipped`.

    `tracks`: ``truth.ground_truth`` of the sequence.
    """
    out = []
    step_ns = int(round(cfg.step_s * 1e9))
    n_steps = int(round(cfg.horizon_s / cfg.step_s))
    for item in frames:
        if item.belief is None:
            continue
        stamp = int(item.frame.header.stamp_ns)
        corridors_of = {v.track_id: v.corridors for v in item.corridor_set.vehicles}
        for vb in item.belief.vehicles:
            if len(vb.corridors) < 2:
                continue
            track_events = events.get(vb.track_id, [])
            later = [t for t, _ in track_events if t >= stamp - cfg.bin_half_width_s / _NS]
            if not later:
                continue
            tau = (later[0] - stamp) * _NS
            b = bin_of(tau, cfg.bins_s, cfg.bin_half_width_s)
            if b is None:
                continue
            future = future_run(tracks[vb.track_id], stamp, step_ns, n_steps)
            if len(future) < cfg.min_future_steps:
                skipped["short_future"] = skipped.get("short_future", 0) + 1
                continue
            by_id = {c.corridor_id: c for c in corridors_of.get(vb.track_id, ())}
            corridors = [by_id[c.corridor_id] for c in vb.corridors]
            followed = followed_corridor(corridors, future, min_inside=cfg.min_future_steps)
            why = route_decision(followed, cfg.max_route_error_m, cfg.route_tie_m)
            if why is not None:
                why = "route_undecided_by_future" if why == "route_tied" else why
                skipped[why] = skipped.get(why, 0) + 1
                continue
            index = followed.index
            out.append(
                RouteWindow(
                    recording=recording,
                    track_id=vb.track_id,
                    stamp_ns=stamp,
                    tau_s=tau,
                    bin_s=b,
                    truth=index,
                    probabilities=np.array([c.probability for c in vb.corridors]),
                    abs_d_m=np.array([abs(c.vehicle_d_m) for c in corridors]),
                    manoeuvres=tuple(int(c.manoeuvre) for c in vb.corridors),
                )
            )
    return out


def route_table(windows: Sequence[RouteWindow], bins_s: Sequence[float]) -> dict[str, dict[str, float | int]]:
    """route_top1 per bin for the intentions, uniform and nearest corridor (module docstring)."""
    table = {}
    for b in bins_s:
        sel = [w for w in windows if w.bin_s == b]
        table[f"{b:g}"] = {
            "windows": len(sel),
            "cars": len({(w.recording, w.track_id) for w in sel}),
            "intentions": route_top1([w.probabilities for w in sel], [w.truth for w in sel]),
            "uniform": route_top1([np.ones(len(w.probabilities)) for w in sel], [w.truth for w in sel]),
            "uniform_expected": float(np.mean([1.0 / len(w.probabilities) for w in sel])) if sel else math.nan,
            "nearest": route_top1([-w.abs_d_m for w in sel], [w.truth for w in sel]),
            "p_true_mean": float(np.mean([w.probabilities[w.truth] for w in sel])) if sel else math.nan,
        }
    return table


@dataclass(frozen=True, slots=True)
class StopGoEvent:
    """One entering event: whether the car stood before it, and the reference time for the P(stop) bins."""

    recording: str
    track_id: int
    stopped: bool
    reference_ns: int
    enter_ns: int


def stop_go_events(tracks: dict[int, Track], events, cfg: IntentionEvalConfig, recording: str) -> list[StopGoEvent]:
    """Classify every entering event (module docstring); `tracks`: ``truth.ground_truth`` of the sequence."""
    out = []
    min_ns = cfg.standstill_min_s / _NS
    for track_id, track_events in events.items():
        stamps, speed = tracks[track_id].stamps_ns, tracks[track_id].speed_mps
        slow = speed < cfg.standstill_speed_mps
        previous = int(stamps[0])
        for enter_ns, _isect in track_events:
            sel = np.flatnonzero((stamps >= previous) & (stamps <= enter_ns))
            start = None
            last_start = None
            for k in sel:
                if slow[k]:
                    if start is None:
                        start = int(stamps[k])
                    if int(stamps[k]) - start >= min_ns:
                        last_start = start
                else:
                    start = None
            stopped = last_start is not None
            out.append(StopGoEvent(recording, track_id, stopped, last_start if stopped else enter_ns, enter_ns))
            previous = enter_ns
    return out


def stop_go_samples(frames: Sequence[ChainFrame], stop_events: Sequence[StopGoEvent], cfg: IntentionEvalConfig):
    """(class, bin, P(stop)) of every frame of an event's car that falls in a bin before its reference time."""
    beliefs: dict[int, list[tuple[int, float]]] = {}
    for item in frames:
        if item.belief is None:
            continue
        for vb in item.belief.vehicles:
            beliefs.setdefault(vb.track_id, []).append((int(item.frame.header.stamp_ns), vb.p_stop))
    out = []
    for event in stop_go_events_sorted(stop_events):
        series = beliefs.get(event.track_id, [])
        stamps = [s for s, _ in series]
        lo = bisect.bisect_left(stamps, event.reference_ns - int((max(cfg.bins_s) + cfg.bin_half_width_s + 0.05) / _NS))
        hi = bisect.bisect_right(stamps, event.reference_ns + int((cfg.bin_half_width_s + 0.05) / _NS))
        for stamp, p in series[lo:hi]:
            b = bin_of((event.reference_ns - stamp) * _NS, cfg.bins_s, cfg.bin_half_width_s)
            if b is not None:
                out.append(("stopped" if event.stopped else "went", b, p, (event.recording, event.track_id, event.enter_ns)))
    return out


def stop_go_events_sorted(events: Sequence[StopGoEvent]) -> list[StopGoEvent]:
    return sorted(events, key=lambda e: (e.recording, e.track_id, e.enter_ns))


def stop_go_table(samples, bins_s: Sequence[float]) -> dict[str, dict[str, dict[str, float | int]]]:
    """Mean P(stop) per class and bin, with the number of frames and events."""
    table: dict[str, dict[str, dict[str, float | int]]] = {}
    for kind in ("stopped", "went"):
        table[kind] = {}
        for b in bins_s:
            values = [p for k, bb, p, _ in samples if k == kind and bb == b]
            table[kind][f"{b:g}"] = {
                "frames": len(values),
                "events": len({e for k, bb, _p, e in samples if k == kind and bb == b}),
                "p_stop_mean": float(np.mean(values)) if values else math.nan,
            }
    return table


def stop_positions(frames: Sequence[ChainFrame], stop_events: Sequence[StopGoEvent]) -> list[float]:
    """Distance from each stopper's standstill start to the entrance ahead on its most probable corridor (m)."""
    wanted = {(e.track_id, e.reference_ns) for e in stop_events if e.stopped}
    out = []
    for item in frames:
        stamp = int(item.frame.header.stamp_ns)
        if item.belief is None:
            continue
        for vb in item.belief.vehicles:
            if (vb.track_id, stamp) in wanted and math.isfinite(vb.intersection_distance_m):
                out.append(vb.intersection_distance_m)
    return out


# --------------------------------------------------------------------------- the whole evaluation


def evaluate(cfg: IntentionEvalConfig, *, progress: bool = False) -> dict[str, Any]:
    """Run the chain and the filter (once per seed) over the selected recordings and return the report.

    Windows and stop/go samples of all seeds are pooled (every seed scores the
    same windows, so a pooled share is the mean over seeds);
    ``route_top1_by_seed`` gives each seed's intentions column.
    """
    icfg = cfg.intentions_config()
    scene_maps = SceneMaps(data=cfg.data_dir)
    names = list(cfg.recordings) or default_recordings(cfg.data_dir, [ref.name for ref in discover(cfg.data_dir)])
    windows: dict[int, list[RouteWindow]] = {seed: [] for seed in cfg.seeds}
    samples = []
    positions: list[float] = []
    times: list[float] = []
    vehicles_per_frame: list[int] = []
    skipped: dict[str, int] = {}
    n_events = {"stopped": 0, "went": 0}
    for name in names:
        rec = load_recording(cfg.data_dir, name, tuple(cfg.sequences) or None)
        sha = file_sha256(rec.map_path) if rec.map_path is not None else ""
        for seq in rec.sequences:
            if progress:
                print(f"{name} {seq.id}: {seq.n_frames} frames", file=sys.stderr, flush=True)
            chain = chain_frames(rec, seq, scene_maps, map_sha256=sha)
            if not chain:
                continue
            road_map = scene_maps.get(chain[0].scene, icfg.projection).road_map
            tracks = ground_truth(seq)
            events = entering_events(chain, road_map)
            stop_events = stop_go_events(tracks, events, cfg, name)
            for e in stop_events:
                n_events["stopped" if e.stopped else "went"] += 1
            for k, seed in enumerate(cfg.seeds):
                frames, ms = with_beliefs(chain, dataclasses.replace(icfg, seed=seed), scene_maps, producer="eval")
                times.extend(ms)
                vehicles_per_frame.extend(len(f.belief.vehicles) if f.belief is not None else 0 for f in frames)
                windows[seed].extend(route_windows(frames, tracks, events, cfg, name, skipped if k == 0 else {}))
                samples.extend(stop_go_samples(frames, stop_events, cfg))
                if k == 0:
                    positions.extend(stop_positions(frames, stop_events))
    pooled = [w for seed in cfg.seeds for w in windows[seed]]
    t = np.asarray(times) if times else np.full(1, np.nan)
    return {
        "data": str(cfg.data_dir),
        "recordings": names,
        "particles_per_vehicle": icfg.particles_per_vehicle,
        "seeds": list(cfg.seeds),
        "params": {k: v for k, v in cfg.params},
        "route_top1": route_table(pooled, cfg.bins_s),
        "route_top1_by_seed": {
            str(seed): {b: row["intentions"] for b, row in route_table(windows[seed], cfg.bins_s).items()}
            for seed in cfg.seeds
        },
        "route_top1_by_recording": {
            name: route_table([w for w in pooled if w.recording == name], cfg.bins_s) for name in names
        },
        "route_skipped": dict(sorted(skipped.items())),
        "stop_go": stop_go_table(samples, cfg.bins_s),
        "stop_go_events": n_events,
        "stop_position_m": {
            "n": len(positions),
            "median": float(np.median(positions)) if positions else math.nan,
            "p25": float(np.percentile(positions, 25)) if positions else math.nan,
            "p75": float(np.percentile(positions, 75)) if positions else math.nan,
        },
        "frame_ms_mean": float(np.mean(t)),
        "frame_ms_p95": float(np.percentile(t, 95)),
        "vehicles_per_frame_mean": float(np.mean(vehicles_per_frame)) if vehicles_per_frame else math.nan,
        "frames": len(times),
    }


def format_tables(report: dict[str, Any]) -> str:
    """The route_top1 and stop/go tables as text."""
    seeds = report["seeds"]
    lines = [
        f"particles per vehicle: {report['particles_per_vehicle']}; seeds: {', '.join(map(str, seeds))};"
        f" recordings: {', '.join(report['recordings'])}"
    ]
    lines.append("route_top1 (windows with >= 2 corridors) vs time before the intersection entrance; windows per seed")
    lines.append(
        f"{'before':>7} {'windows':>8} {'cars':>5} {'intentions':>11} {'(seeds min..max)':>17} {'uniform':>8} {'(1/n)':>6}"
        f" {'nearest':>8} {'P(true)':>8}"
    )
    for b, row in report["route_top1"].items():
        by_seed = [report["route_top1_by_seed"][str(seed)][b] for seed in seeds]
        lines.append(
            f"{b + ' s':>7} {row['windows'] // max(len(seeds), 1):>8d} {row['cars']:>5d} {row['intentions']:>11.3f}"
            f" {f'{min(by_seed):.2f}..{max(by_seed):.2f}':>17} {row['uniform']:>8.3f}"
            f" {row['uniform_expected']:>6.3f} {row['nearest']:>8.3f} {row['p_true_mean']:>8.3f}"
        )
    lines.append(f"left out: {report['route_skipped']}")
    events = report["stop_go_events"]
    lines.append(f"mean P(stop) before the stop position (stopped, {events['stopped']} events) / entrance (went, {events['went']} events)")
    lines.append(f"{'before':>7} {'stopped':>8} {'(frames)':>9} {'went':>8} {'(frames)':>9}   (frames pooled over seeds)")
    for b in report["stop_go"]["stopped"]:
        st, go = report["stop_go"]["stopped"][b], report["stop_go"]["went"][b]
        lines.append(f"{b + ' s':>7} {st['p_stop_mean']:>8.3f} {st['frames']:>9d} {go['p_stop_mean']:>8.3f} {go['frames']:>9d}")
    sp = report["stop_position_m"]
    lines.append(f"stoppers stood {sp['median']:.1f} m (quartiles {sp['p25']:.1f}, {sp['p75']:.1f}; n={sp['n']}) before the entrance")
    lines.append(
        f"IntentionFilter.process: {report['frame_ms_mean']:.2f} ms/frame mean, {report['frame_ms_p95']:.2f} ms p95,"
        f" {report['vehicles_per_frame_mean']:.1f} vehicles/frame, {report['frames']} frames"
    )
    return "\n".join(lines)




def _parse_set(items: Sequence[str]) -> tuple[tuple[str, Any], ...]:
    out = []
    for item in items:
        key, _, raw = item.partition("=")
        try:
            value = json.loads(raw)
        except json.JSONDecodeError:
            value = raw
        out.append((key.strip(), tuple(value) if isinstance(value, list) else value))
    return tuple(out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m stages.offline.intentions_eval", description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA_DIR, help="data folder laid out like stages/data/taf-bw")
    parser.add_argument("--recording", action="extend", nargs="+", default=[], help="recording names (one or more, the flag repeatable; default: all of --data; in the embedded folder its K729 recording)")
    parser.add_argument("--sequence", action="extend", nargs="+", default=[], help="sequence id (one or more, the flag repeatable; default: all)")
    parser.add_argument("--particles", type=int, default=None, help="particles per vehicle (default: the stage's)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0], help="filter seeds to run and pool (default: 0)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="an IntentionsConfig parameter (JSON value)")
    parser.add_argument("--json", type=Path, default=None, help="write the report here")
    parser.add_argument("--quiet", action="store_true", help="no progress lines")
    args = parser.parse_args(argv)
    params = _parse_set(args.set)
    if args.particles is not None:
        params = params + (("particles_per_vehicle", args.particles),)
    try:
        cfg = IntentionEvalConfig(
            data_dir=args.data, recordings=tuple(args.recording), sequences=tuple(args.sequence), params=params, seeds=tuple(args.seeds)
        )
        cfg.intentions_config()
    except ValueError as exc:
        print(f"bad configuration: {exc}", file=sys.stderr)
        return 2
    report = evaluate(cfg, progress=not args.quiet)
    print(format_tables(report))
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(json_safe(report), indent=2, sort_keys=False) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
