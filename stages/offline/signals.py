"""``iamp signals``: match a recording's KML lane file to its Lanelet2 map; print the report, draw the figure.

::

    iamp signals --data DIR --recording NAME [--map FILE.osm] [--projection P] [--figure FILE.png] [--json FILE]

The recording folder is ``DIR/recorded_trackfiles/NAME`` or ``DIR/NAME``; it
needs ``meta_data.csv`` (the origin) and one ``*.kml`` lane file; tracks are
not needed. The map is ``--map`` or ``DIR/maps/NAME.osm``; the projection
that of the location (``projection_for_location``: K733 scaled Mercator)
unless given. The figure (matplotlib, Agg backend) shows the car lanelets,
the KML lanes (matched: solid, unmatched: dashed red) and each matched stop
line across its lanelet, coloured by signal group.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

from stages.lib.datasets import DatasetError
from stages.lib.datasets import interaction
from stages.lib.datasets.signals import is_lane_file, is_signal_file, read_kml_lanes, read_signal_phases
from stages.lib.maps import load_map, parse_projection, projection_for_location, Projection
from stages.lib.maps.signals import SignalMap, match_lanes

EXIT_USAGE = 2


def add_arguments(parser) -> None:
    parser.add_argument("--data", type=Path, required=True, help="data folder: DIR/recorded_trackfiles/NAME or DIR/NAME holds meta_data.csv and the *.kml lane file")
    parser.add_argument("--recording", required=True, help="recording name (folder name)")
    parser.add_argument("--map", type=Path, default=None, help="Lanelet2 map (default DIR/maps/NAME.osm)")
    parser.add_argument("--projection", default="", help="LOCAL_CARTESIAN, SCALED_MERCATOR or UTM (default: the location's, K733 SCALED_MERCATOR)")
    parser.add_argument("--figure", type=Path, default=None, help="write the map figure here (default signals_NAME.png in the working folder)")
    parser.add_argument("--json", type=Path, default=None, help="write the match as JSON")


def recording_folder(data: Path, name: str) -> Path:
    for folder in (data / "recorded_trackfiles" / name, data / name):
        if folder.is_dir():
            return folder
    raise DatasetError(f"no recording folder {name!r} under {data} (looked in recorded_trackfiles/{name} and {name})")


def load_signal_map(data: Path, name: str, map_path: Path | None = None, projection: str = "") -> tuple[SignalMap, object, dict]:
    """(SignalMap, RoadMap, info) of a recording folder with a KML lane file."""
    folder = recording_folder(data, name)
    metas = interaction.read_meta(folder / interaction.META_FILE)
    meta = next(iter(metas.values()))
    lanes_files = [p for p in sorted(folder.iterdir()) if is_lane_file(p)]
    if len(lanes_files) != 1:
        raise DatasetError(f"{folder}: expected one *.kml lane file, found {len(lanes_files)}")
    map_path = map_path or data / "maps" / f"{name}.osm"
    if not map_path.is_file():
        raise DatasetError(f"no map {map_path}: pass --map FILE.osm")
    proj = parse_projection(projection) if projection else projection_for_location(meta.location_id)
    if proj in (Projection.UNKNOWN, Projection.AUTO):
        raise DatasetError(f"projection {projection!r}: use LOCAL_CARTESIAN, SCALED_MERCATOR or UTM")
    road_map, problems = load_map(map_path, meta.origin_lat_deg, meta.origin_lon_deg, proj)
    if road_map is None:
        raise DatasetError(f"{map_path}: unusable map: {'; '.join(p.detail for p in problems)}")
    kml = read_kml_lanes(lanes_files[0], data)
    smap = match_lanes(road_map, kml, proj, meta.origin_lat_deg, meta.origin_lon_deg)
    signal_files = [p for p in sorted(folder.iterdir()) if is_signal_file(p)]
    phases = read_signal_phases(signal_files, data) if signal_files else None
    info = {"folder": str(folder), "map": str(map_path), "projection": proj.name, "origin": (meta.origin_lat_deg, meta.origin_lon_deg),
            "kml_report": kml.report.summary(), "phases": phases}
    return smap, road_map, info


def draw(smap: SignalMap, road_map, path: Path, title: str, phases=None, stamp_ns: int | None = None) -> None:
    """The map with the KML lanes and the matched stop lines coloured by signal group (Agg backend)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, ax = plt.subplots(figsize=(11, 10), dpi=110)
    for lid in road_map.lanelet_ids:
        info = road_map.lanelet(lid)
        poly = np.vstack([info.left_bound_m, info.right_bound_m[::-1]])
        ax.fill(poly[:, 0], poly[:, 1], color="0.9", ec="0.6", lw=0.4, zorder=1)
        c = info.centreline.points_m
        ax.plot(c[:, 0], c[:, 1], color="0.75", lw=0.5, zorder=2)
    cmap = plt.get_cmap("tab20")
    groups = smap.signal_groups
    colour = {g: cmap(i % 20) for i, g in enumerate(groups)}
    for lane in smap.lanes:
        p = lane.points_m
        style = dict(color="0.35", lw=0.9, zorder=3) if lane.matched else dict(color="tab:red", lw=0.9, ls="--", zorder=3)
        ax.plot(p[:, 0], p[:, 1], **style)
        ax.annotate(f"{lane.lane_id}", p[0], fontsize=6, color=style["color"], zorder=6)
    for lane in smap.matched:
        if not lane.signalised or lane.stop_lanelet_id is None:
            continue
        info = road_map.lanelet(lane.stop_lanelet_id)
        c = info.centreline
        xy = c.to_xy(lane.stop_s_m)[0]
        h = float(c.heading_at(lane.stop_s_m))
        half = 0.5 * info.width_m
        nx, ny = -math.sin(h) * half, math.cos(h) * half
        gs = lane.signal_groups
        for k, g in enumerate(gs):  # a lane with two groups: the line split in two colours
            a, b = -1 + 2 * k / len(gs), -1 + 2 * (k + 1) / len(gs)
            ax.plot([xy[0] + a * nx, xy[0] + b * nx], [xy[1] + a * ny, xy[1] + b * ny], color=colour[g], lw=4, solid_capstyle="butt", zorder=5)
        ax.annotate("g" + "/".join(str(g) for g in gs), (xy[0] + nx, xy[1] + ny), fontsize=7, zorder=7,
                    xytext=(2, 2), textcoords="offset points")
    handles = [plt.Line2D([], [], color=colour[g], lw=4, label=f"group {g}") for g in groups]
    handles += [plt.Line2D([], [], color="0.35", lw=1, label="KML lane (matched)"),
                plt.Line2D([], [], color="tab:red", lw=1, ls="--", label="KML lane (unmatched)")]
    ax.legend(handles=handles, fontsize=7, loc="upper left", ncol=2)
    allp = np.vstack([road_map.lanelet(x).centreline.points_m for x in road_map.lanelet_ids])
    lo, hi = allp.min(axis=0) - 10, allp.max(axis=0) + 10
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_xlabel("x east (m)")
    ax.set_ylabel("y north (m)")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


def match_json(smap: SignalMap) -> dict:
    return {
        "lanes": [
            {"lane_id": l.lane_id, "ingress": l.ingress, "matched": l.matched, "lanelet_ids": list(l.lanelet_ids),
             "share_matched": l.share_matched, "mean_distance_m": l.mean_distance_m, "max_distance_m": l.max_distance_m,
             "stop_lanelet_id": l.stop_lanelet_id, "stop_s_m": l.stop_s_m, "stop_offset_m": l.stop_offset_m,
             "signal_groups": list(l.signal_groups),
             "connections": [{"sink_lane": c.sink_lane, "signal_group": c.signal_group, "routes": [list(r) for r in c.routes]} for c in l.connections]}
            for l in smap.lanes
        ],
        "unmatched": [l.lane_id for l in smap.unmatched],
        "signal_groups": list(smap.signal_groups),
    }


def run_cli(args) -> int:
    try:
        smap, road_map, info = load_signal_map(args.data, args.recording, args.map, args.projection)
    except DatasetError as exc:
        print(f"iamp signals: {exc}", file=sys.stderr)
        return EXIT_USAGE
    print(f"recording {args.recording}: map {info['map']} ({info['projection']}, origin {info['origin'][0]}, {info['origin'][1]}); lane file {info['kml_report']}")
    for line in smap.report_lines():
        print(line)
    figure = args.figure or Path(f"signals_{args.recording}.png")
    draw(smap, road_map, figure, f"{args.recording}: KML lanes on the Lanelet2 map, stop lines by signal group ({info['projection']})")
    print(f"figure: {figure}")
    if args.json:
        args.json.write_text(json.dumps(match_json(smap), indent=1, default=float))
    return 0


__all__ = ["add_arguments", "draw", "load_signal_map", "match_json", "recording_folder", "run_cli"]
