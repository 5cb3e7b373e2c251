"""Signal groups on the road map: a MAP-style lane file (KML) matched to the car lanelets and their routes.

Each KML lane is a WGS84 polyline that starts at its stop line (ingress
lanes, which have connections) or at the junction's edge (egress lanes). The
polyline is projected into the map's local frame with the same projection
and origin as the map (``projection.projector``, shifted so that the origin
is (0, 0), as ``io.read_osm`` does), resampled every ``step_m`` and each
sample is assigned the nearest car lanelet whose centreline runs in the
lane's driving direction (heading within ``max_heading_rad``) and lies
within ``max_distance_m`` (the KML polylines lie about 1 m off the lane
centres). A lane is matched when at least ``min_share`` of its samples are;
its stop line is the foot point of its first point on the lanelet matched
there. Each connection (sink lane, signal group) of an ingress lane becomes a
route: the lanelet sequences from the stop lanelet through the junction to a
lanelet of the sink lane (found by following successors, at most
``max_route_lanelets``). A corridor that passes a stop lanelet gets the
stop's group from the connection route it follows; where it follows none
(it ends inside the junction, or the sink lane was not matched), the lane's
group when the lane has only one. Pure: numpy and lanelet2's projector.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from lanelet2 import core as ll_core

from stages.lib.maps.geometry import Centreline, project_to_polyline, wrap_angle_rad
from stages.lib.maps.projection import Projection, projector
from stages.lib.maps.road_map import RoadMap


@dataclass(frozen=True, kw_only=True)
class SignalMatchConfig:
    step_m: float = 1.0
    max_distance_m: float = 3.0
    max_heading_rad: float = math.radians(35.0)
    min_share: float = 0.5  # of the samples on the map (within on_map_m of a car lanelet's centreline)
    min_samples: int = 3
    max_mean_distance_m: float = 2.0  # a lane further off its lanelets on average is another (unmapped) lane
    on_map_m: float = 8.0
    max_route_lanelets: int = 6
    end_margin_m: float = 2.0  # a foot point this far beyond a lanelet's ends still counts as on it
    approach_radius_m: float = 8.0  # lanes whose stop point lies this near a stop line share its approach (fallback groups)


@dataclass(frozen=True, slots=True, kw_only=True)
class ConnectionMatch:
    """One connection of an ingress lane: sink lane, signal group, and the lanelet routes from the stop lanelet to it."""

    sink_lane: int
    signal_group: int | None
    routes: tuple[tuple[int, ...], ...]  # each starts with the stop lanelet


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class LaneMatch:
    """One KML lane on the map (``matched`` False: no lanelet fits; the other figures then describe the best attempt)."""

    lane_id: int
    name: str
    ingress: bool
    matched: bool
    lanelet_ids: tuple[int, ...]  # in driving order
    share_matched: float
    mean_distance_m: float  # KML sample to lanelet centreline, over the matched samples
    max_distance_m: float
    points_m: np.ndarray  # (n, 2) the KML polyline in the map frame, as in the file (first point: stop line)
    stop_lanelet_id: int | None = None
    stop_s_m: float = math.nan  # arc length of the stop line on the stop lanelet
    stop_xy_m: tuple[float, float] = (math.nan, math.nan)  # foot point of the stop line on the lanelet centreline
    stop_offset_m: float = math.nan  # KML stop point to that foot point
    connections: tuple[ConnectionMatch, ...] = ()

    @property
    def signal_groups(self) -> tuple[int, ...]:
        return tuple(sorted({c.signal_group for c in self.connections if c.signal_group is not None}))

    @property
    def signalised(self) -> bool:
        return self.ingress and bool(self.signal_groups)


@dataclass(frozen=True, slots=True)
class CorridorStop:
    """A signalised stop line on one corridor: arc length on the corridor, group, KML lane, and how the group was found."""

    s_m: float
    signal_group: int
    lane_id: int
    lanelet_id: int
    by_route: bool  # True: the corridor follows the connection's route; False: the lane's only group


@dataclass(frozen=True, slots=True, eq=False)
class SignalMap:
    """The lane file matched to a road map: every lane's match, and the signalised stops by lanelet."""

    lanes: tuple[LaneMatch, ...]
    projection: Projection
    stops_by_lanelet: dict[int, tuple[LaneMatch, ...]] = field(default_factory=dict)
    # per stop lanelet: (feeders, group) of every connection of the lanes of its approach, matched or not (an
    # unmapped lane's connections still say which group controls a movement); feeders: the sink lane's lanelets and
    # those that lead into them within two successor steps
    approach: dict[int, tuple[tuple[frozenset, int], ...]] = field(default_factory=dict)

    @property
    def matched(self) -> tuple[LaneMatch, ...]:
        return tuple(l for l in self.lanes if l.matched)

    @property
    def unmatched(self) -> tuple[LaneMatch, ...]:
        return tuple(l for l in self.lanes if not l.matched)

    @property
    def signal_groups(self) -> tuple[int, ...]:
        return tuple(sorted({g for l in self.lanes if l.matched for g in l.signal_groups}))

    def corridor_stops(self, lanelet_ids, lanelet_start_s_m) -> list[CorridorStop]:
        """Signalised stop lines on a corridor (its lanelet ids and their start arc lengths), in order of arc length."""
        ids = [int(x) for x in np.asarray(lanelet_ids).tolist()]
        starts = np.asarray(lanelet_start_s_m, dtype=np.float64)
        out: list[CorridorStop] = []
        for i, lid in enumerate(ids):
            for lane in self.stops_by_lanelet.get(lid, ()):
                group, by_route = _group_on(lane, ids[i:], self.approach.get(lid, ()))
                if group is None:
                    continue
                out.append(CorridorStop(float(starts[i] + lane.stop_s_m), group, lane.lane_id, lid, by_route))
        out.sort(key=lambda c: c.s_m)
        # two lanes on one lanelet with the same group: keep one stop
        dedup: list[CorridorStop] = []
        for c in out:
            if not any(abs(c.s_m - d.s_m) < 1.0 and c.signal_group == d.signal_group for d in dedup):
                dedup.append(c)
        return dedup

    def report_lines(self) -> list[str]:
        """The match report: one line per lane, then totals."""
        lines = []
        for l in sorted(self.lanes, key=lambda l: l.lane_id):
            kind = "ingress" if l.ingress else "egress"
            if l.matched:
                groups = ",".join(str(g) for g in l.signal_groups) or "-"
                text = (f"lane {l.lane_id:3d} {kind:7s} matched   lanelets {' '.join(str(x) for x in l.lanelet_ids)}"
                        f"  dist mean {l.mean_distance_m:.2f} m max {l.max_distance_m:.2f} m  share {l.share_matched:.2f}")
                if l.ingress:
                    conns = "; ".join(
                        f"->{c.sink_lane} g{c.signal_group if c.signal_group is not None else '-'}"
                        f" {'routes ' + '|'.join('-'.join(str(x) for x in r[1:]) for r in c.routes) if c.routes else 'no route'}"
                        for c in l.connections)
                    text += (f"  stop on {l.stop_lanelet_id} at s={l.stop_s_m:.1f} m (offset {l.stop_offset_m:.2f} m)"
                             f"  groups {groups}  [{conns}]")
                lines.append(text)
            else:
                why = ("no car lanelet in its direction on the map" if not math.isfinite(l.mean_distance_m)
                       else f"dist mean {l.mean_distance_m:.2f} m (> {SignalMatchConfig.max_mean_distance_m:g}: another, unmapped lane)"
                       if l.mean_distance_m > SignalMatchConfig.max_mean_distance_m
                       else f"dist mean {l.mean_distance_m:.2f} m but only {l.share_matched:.0%} of it on a lanelet")
                lines.append(f"lane {l.lane_id:3d} {kind:7s} UNMATCHED share {l.share_matched:.2f}: {why}"
                             f" (groups {','.join(str(g) for g in l.signal_groups) or '-'}, {len(l.points_m)} points)")
        m = self.matched
        ing = [l for l in self.lanes if l.ingress]
        sig = [l for l in ing if l.signal_groups]
        d = np.concatenate([[l.mean_distance_m] for l in m]) if m else np.array([math.nan])
        n_conn = sum(len(l.connections) for l in m if l.ingress)
        n_routed = sum(1 for l in m if l.ingress for c in l.connections if c.routes)
        lines.append(
            f"lanes {len(self.lanes)}: matched {len(m)} (ingress {sum(1 for l in m if l.ingress)} of {len(ing)},"
            f" egress {sum(1 for l in m if not l.ingress)} of {len(self.lanes) - len(ing)}), unmatched {len(self.unmatched)}"
            f" [{', '.join(str(l.lane_id) for l in self.unmatched)}]; signalised ingress lanes {len(sig)},"
            f" matched {sum(1 for l in sig if l.matched)}; connections routed {n_routed} of {n_conn};"
            + (f" mean distance KML to centreline {np.nanmean(d):.2f} m (median {np.nanmedian(d):.2f}, max {np.nanmax(d):.2f});"
               if np.isfinite(d).any() else " no lane matched, no distance;") +
            f" signal groups on the map {len(self.signal_groups)}"
        )
        return lines


def _group_on(lane: LaneMatch, following: list[int], approach=()) -> tuple[int | None, bool]:
    """The group of the connection whose route the corridor's lanelets (from the stop lanelet on) follow; else the
    group of the approach's connections into a sink lane the corridor reaches (an unmapped lane's, say); else the
    lane's only group."""
    groups = set()
    for c in lane.connections:
        if c.signal_group is None:
            continue
        for r in c.routes:
            n = min(len(r), len(following))
            if n >= 2 and tuple(following[:n]) == r[:n] and (n == len(r) or n == len(following)):
                if n == len(r):
                    return c.signal_group, True
                groups.add(c.signal_group)  # the corridor ends inside the junction on this route
    if len(groups) == 1:
        return groups.pop(), True
    reached = {g for feeders, g in approach if any(x in feeders for x in following[1:])}
    if len(reached) == 1:
        return reached.pop(), False
    lane_groups = lane.signal_groups
    if len(lane_groups) == 1:
        return lane_groups[0], False
    return None, False


def kml_to_local(lat_deg, lon_deg, projection: Projection, origin_lat_deg: float, origin_lon_deg: float) -> np.ndarray:
    """(n, 2) map-frame metres of WGS84 points, projected exactly as the map (``io.read_osm``)."""
    proj = projector(projection, origin_lat_deg, origin_lon_deg)
    o = proj.forward(ll_core.GPSPoint(origin_lat_deg, origin_lon_deg, 0.0))
    out = np.empty((len(lat_deg), 2))
    for k, (la, lo) in enumerate(zip(np.asarray(lat_deg, float), np.asarray(lon_deg, float))):
        p = proj.forward(ll_core.GPSPoint(float(la), float(lo), 0.0))
        out[k] = (p.x - o.x, p.y - o.y)
    return out


def _resample(points: np.ndarray, step_m: float) -> np.ndarray:
    seg = np.hypot(*np.diff(points, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    n = max(int(math.ceil(s[-1] / step_m)), 1)
    t = np.linspace(0.0, s[-1], n + 1)
    return np.column_stack([np.interp(t, s, points[:, 0]), np.interp(t, s, points[:, 1])])


def _nearest_lanelets(road_map: RoadMap, pts: np.ndarray, heading: np.ndarray, cfg: SignalMatchConfig):
    """Per point: (lanelet id, |d| (inf: none), s on it) of the nearest lanelet running in ``heading`` (ids may be negative)."""
    best_id = np.zeros(len(pts), dtype=np.int64)
    best_d = np.full(len(pts), np.inf)
    best_s = np.full(len(pts), np.nan)
    for lid in road_map.lanelet_ids:
        c: Centreline = road_map.lanelet(lid).centreline
        lo, hi = pts.min(axis=0) - 20.0, pts.max(axis=0) + 20.0
        cp = c.points_m
        if np.any(cp.max(axis=0) < lo) or np.any(cp.min(axis=0) > hi):
            continue
        f = project_to_polyline(pts, cp, c.s_m, c.heading_rad)
        ok = (
            (np.abs(f.d_m) <= cfg.max_distance_m)
            & (f.s_m >= -cfg.end_margin_m)
            & (f.s_m <= c.length_m + cfg.end_margin_m)
            & (np.abs(wrap_angle_rad(f.heading_rad - heading)) <= cfg.max_heading_rad)
        )
        # beyond an end the foot is on the extension: count the distance to the end point
        d = np.abs(f.d_m) + np.maximum(-f.s_m, 0.0) + np.maximum(f.s_m - c.length_m, 0.0)
        better = ok & (d < best_d)
        best_id[better], best_d[better], best_s[better] = lid, d[better], np.clip(f.s_m[better], 0.0, c.length_m)
    return best_id, best_d, best_s


def _routes(road_map: RoadMap, start: int, targets: set[int], max_len: int) -> tuple[tuple[int, ...], ...]:
    out: list[tuple[int, ...]] = []
    stack = [(start,)]
    while stack:
        path = stack.pop()
        if len(path) > 1 and path[-1] in targets:
            out.append(path)
            continue
        if len(path) >= max_len:
            continue
        for succ in road_map.successors(path[-1]):
            if succ not in path:
                stack.append(path + (succ,))
    return tuple(sorted(out, key=lambda r: (len(r), r)))


def match_lanes(
    road_map: RoadMap,
    kml_lanes,
    projection: Projection,
    origin_lat_deg: float,
    origin_lon_deg: float,
    config: SignalMatchConfig = SignalMatchConfig(),
) -> SignalMap:
    """Match every lane of a ``KmlLanes`` (stages.lib.datasets.signals) to ``road_map`` (module docstring)."""
    cfg = config
    matches: dict[int, LaneMatch] = {}
    raw: dict[int, np.ndarray] = {}
    all_pts = np.vstack([road_map.lanelet(x).centreline.points_m for x in road_map.lanelet_ids])
    for lane in kml_lanes.lanes:
        pts = kml_to_local(lane.lat_deg, lane.lon_deg, projection, origin_lat_deg, origin_lon_deg)
        raw[lane.lane_id] = pts
        ingress = lane.is_ingress
        # ingress polylines run upstream from the stop line; egress polylines run downstream from the junction
        drive = pts[::-1] if ingress else pts
        samples = _resample(drive, cfg.step_m)
        seg = np.diff(samples, axis=0)
        heading = np.arctan2(seg[:, 1], seg[:, 0])
        heading = np.concatenate([heading, heading[-1:]])
        ids, dist, _ = _nearest_lanelets(road_map, samples, heading, cfg)
        hit = np.isfinite(dist)
        # the map covers the junction and some tens of metres of each approach; the lane file reaches further
        near = np.hypot(*(all_pts[None, :, :] - samples[:, None, :]).transpose(2, 0, 1)).min(axis=1) <= cfg.on_map_m
        share = float(hit[near].mean()) if near.any() else 0.0
        order: list[int] = []
        for x in ids[hit].tolist():
            if not order or order[-1] != x:
                if x not in order:
                    order.append(x)
        matched = share >= cfg.min_share and int(hit.sum()) >= cfg.min_samples and float(dist[hit].mean()) <= cfg.max_mean_distance_m
        mean_d = float(dist[hit].mean()) if hit.any() else math.nan
        max_d = float(dist[hit].max()) if hit.any() else math.nan
        kwargs = {}
        if matched and ingress:
            stop_pt = pts[:1]
            h0 = heading[-1:]  # the driving direction at the stop line
            sid, sdist, ss = _nearest_lanelets(road_map, stop_pt, h0, cfg)
            if np.isfinite(sdist[0]):
                lid, s_stop = int(sid[0]), float(ss[0])
                c = road_map.lanelet(lid).centreline
                foot = c.to_xy(s_stop)[0]
                if s_stop < cfg.end_margin_m:  # at the start of a junction lanelet: the stop belongs to the approach's end
                    preds = road_map.predecessors(lid)
                    pick = [x for x in preds if x in order] or (list(preds) if len(preds) == 1 else [])
                    if pick:
                        lid = int(pick[0])
                        s_stop = road_map.lanelet(lid).length_m
                kwargs = dict(stop_lanelet_id=lid, stop_s_m=s_stop, stop_xy_m=(float(foot[0]), float(foot[1])),
                              stop_offset_m=float(np.hypot(*(foot - stop_pt[0]))))
        matches[lane.lane_id] = LaneMatch(
            lane_id=lane.lane_id, name=lane.name, ingress=ingress, matched=matched, lanelet_ids=tuple(order),
            share_matched=share, mean_distance_m=mean_d, max_distance_m=max_d, points_m=pts,
            connections=tuple(ConnectionMatch(sink_lane=c.sink_lane, signal_group=c.signal_group, routes=()) for c in lane.connections),
            **kwargs,
        )
    # routes of each connection: from the stop lanelet to a lanelet of the (matched) sink lane
    by_lanelet: dict[int, list[LaneMatch]] = {}
    final: list[LaneMatch] = []
    for lane_id, m in matches.items():
        if m.matched and m.ingress and m.stop_lanelet_id is not None:
            conns = []
            for c in m.connections:
                sink = matches.get(c.sink_lane)
                targets = set(sink.lanelet_ids) if sink is not None and sink.matched else set()
                routes = _routes(road_map, m.stop_lanelet_id, targets, cfg.max_route_lanelets) if targets else ()
                conns.append(ConnectionMatch(sink_lane=c.sink_lane, signal_group=c.signal_group, routes=routes))
            m = LaneMatch(**{**{k: getattr(m, k) for k in m.__dataclass_fields__}, "connections": tuple(conns)})
            if m.signal_groups:
                by_lanelet.setdefault(m.stop_lanelet_id, []).append(m)
        final.append(m)
    approach: dict[int, tuple[tuple[frozenset, int], ...]] = {}
    by_id = {m.lane_id: m for m in final}
    for lid, stop_lanes in by_lanelet.items():
        foot = np.array(stop_lanes[0].stop_xy_m)
        conns = []
        for m in final:
            if not m.ingress or np.hypot(*(m.points_m[0] - foot)) > cfg.approach_radius_m:
                continue
            for c in m.connections:
                sink = by_id.get(c.sink_lane)
                if c.signal_group is not None and sink is not None and sink.matched:
                    feeders = set(sink.lanelet_ids)
                    frontier = set(sink.lanelet_ids)
                    for _ in range(2):
                        frontier = {x for f in frontier for x in road_map.predecessors(f)} - feeders
                        feeders |= frontier
                    feeders.discard(lid)
                    conns.append((frozenset(feeders), c.signal_group))
        approach[lid] = tuple(conns)
    return SignalMap(lanes=tuple(final), projection=projection, stops_by_lanelet={k: tuple(v) for k, v in by_lanelet.items()},
                     approach=approach)


__all__ = ["ConnectionMatch", "CorridorStop", "LaneMatch", "SignalMap", "SignalMatchConfig", "kml_to_local", "match_lanes"]
