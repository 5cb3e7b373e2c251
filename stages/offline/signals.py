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
import sys
from pathlib import Path

from stages.lib.base import ConfigError, check_output, json_safe
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
    """The map with the KML lanes and the matched stop lines coloured by signal group (``figures.signal_map_figure``)."""
    from stages.offline.figures import signal_map_figure  # matplotlib's one home; loaded only when a figure is asked for

    fig = signal_map_figure(smap, road_map, title)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)


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
        check_output(args.figure or Path(f"signals_{args.recording}.png"), "--figure")
        check_output(args.json, "--json")
        smap, road_map, info = load_signal_map(args.data, args.recording, args.map, args.projection)
    except (DatasetError, ConfigError) as exc:
        print(f"iamp signals: {exc}", file=sys.stderr)
        return EXIT_USAGE
    print(f"recording {args.recording}: map {info['map']} ({info['projection']}, origin {info['origin'][0]}, {info['origin'][1]}); lane file {info['kml_report']}")
    for line in smap.report_lines():
        print(line)
    figure = args.figure or Path(f"signals_{args.recording}.png")
    draw(smap, road_map, figure, f"{args.recording}: KML lanes on the Lanelet2 map, stop lines by signal group ({info['projection']})")
    print(f"figure: {figure}")
    if args.json:
        # NaN (an unmatched lane's distances) as null: strict JSON, as iamp eval writes
        args.json.write_text(json.dumps(json_safe(json.loads(json.dumps(match_json(smap), default=float))), indent=1, allow_nan=False))
    if smap.lanes and not smap.matched:  # another location's map, or the wrong projection: nothing to play phases on
        print(f"iamp signals: no lane of the lane file matched a lanelet of {info['map']} ({info['projection']}): is it this"
              f" recording's map (--map) and projection (--projection)? The figure shows both.", file=sys.stderr)
        return EXIT_USAGE
    return 0


__all__ = ["add_arguments", "draw", "load_signal_map", "match_json", "recording_folder", "run_cli"]
