"""Draw one frame with matplotlib: map lanelets, cars as oriented boxes with ids, and their corridors.

Car lanelets are filled light grey, other lanelets (walkways, crosswalks, bike
lanes) outlined in blue-grey, lanelet centrelines dashed; each car and its
corridors share a colour (the straight extension past the map's end is
drawn thinner and dashed); pedestrians are small dark dots. The corridors
come from running the corridors core in-process over the sequence up to the
frame, so continuity state is as on the bus. Axes in metres, a legend, a
title that names the recording, sequence and frame.

    python bench/plot_frame.py [--data PATH] [--recording NAME] [--sequence SEQ]
                               [--frame N] [--out FILE.png] [--dpi 100] [--no-svg]
                               [--relations]

Writes FILE.png and, beside it, FILE.svg (unless --no-svg). With
`--relations` the relations core runs on the shown frame and draws its
conflict points as x markers (red: crossing, blue: merge; a ring around the
influencing conflict of some corridor, in the colour of the vehicle it
influences) and leader links (a dark green line from each vehicle to its
leader, with a dot at the leader).

Defaults: the TAF-BW folder beside the repository (else the embedded one),
K729, sequence 013, the frame with the most cars, <tmp>/corridors_frame.png.

Hook for later overlays: `render_frame(..., overlays=[fn])` calls each
`fn(ax)` last with the matplotlib Axes (map metres).

Other lanelets come from the OSM file through `stages.lib.maps.lanelet_bounds`
(the map library, the one lanelet2 wrapper), projected and shifted exactly as
the corridors stage's road map, with the scene's projection and origin.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from stages.lib.datasets import DEFAULT_DATA_DIR

REPO = Path(__file__).resolve().parents[1]

from bus_schemas import AgentType, CorridorSet, Header, MatchStatus, SceneInfo, TrackFrame
from stages.corridors import CorridorBuilder, CorridorsConfig
from stages.lib.base import check_output_arg
from stages.lib.datasets import DatasetError, load_recording
from stages.lib.maps import Projection, RoadMap, lanelet_bounds
from stages.relations import RelationExtractor, RelationsConfig

PALETTE = ["#e41a1c", "#377eb8", "#4daf4a", "#984ea3", "#ff7f00", "#a65628", "#f781bf", "#00a0a0", "#a0a000", "#5a5adc"]


def osm_lanelets(osm_path: Path, road_map: RoadMap, scene: SceneInfo, projection: Projection) -> list[tuple[int, bool, np.ndarray, np.ndarray]]:
    """Every lanelet of the OSM file as (id, is_car, left (n, 2), right (m, 2)) in map metres; is_car: one of `road_map`'s."""
    found, problems = lanelet_bounds(osm_path, scene.origin_lat_deg, scene.origin_lon_deg, projection)
    if found is None:
        raise SystemExit(f"cannot read {osm_path}: " + "; ".join(p.detail for p in problems))
    car_ids = set(road_map.lanelet_ids)
    return [(x.lanelet_id, x.lanelet_id in car_ids, x.left_bound_m, x.right_bound_m) for x in found]


# --------------------------------------------------------------------------- the frame


def render_frame(
    road_map: RoadMap,
    lanelets: Sequence[tuple[int, bool, np.ndarray, np.ndarray]],
    frame: TrackFrame,
    corridor_set: CorridorSet,
    *,
    window_m: tuple[float, float, float, float],
    title: str = "",
    overlays: Sequence[Callable] = (),
):
    """Draw the map, the corridors and the objects of one frame, then each overlay; returns the matplotlib Figure."""
    from matplotlib.collections import LineCollection
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    from stages.offline.figures import LANELET_EDGE, LANELET_FACE, draw_lanelets, new_figure

    fig = new_figure((9.0, 8.0))
    ax = fig.add_subplot(111)
    ax.set_aspect("equal", adjustable="box")
    draw_lanelets(ax, [np.concatenate([left, right[::-1]]) for _id, is_car, left, right in lanelets if is_car])
    others = [b for _id, is_car, left, right in lanelets if not is_car for b in (left, right)]
    if others:
        ax.add_collection(LineCollection(others, colors="#7896c8", linewidths=0.6, zorder=1))
    centre = [road_map.lanelet(i).centreline.points_m for i in road_map.lanelet_ids]
    ax.add_collection(LineCollection(centre, colors="#bebebe", linewidths=0.6, linestyles=(0, (4, 4)), zorder=1))
    cars = [v for v in corridor_set.vehicles if v.agent_type.is_vehicle]
    colours = {v.track_id: PALETTE[k % len(PALETTE)] for k, v in enumerate(cars)}
    for vehicle in cars:
        for corridor in vehicle.corridors:
            pts = np.column_stack([corridor.x_m, corridor.y_m])
            mapped = corridor.s_m <= corridor.extension_start_s_m
            ax.plot(pts[mapped, 0], pts[mapped, 1], color=colours[vehicle.track_id], lw=1.8, alpha=0.8, zorder=2)
            if (~mapped).any():
                ext = pts[np.flatnonzero(~mapped)[0] - 1 :]
                ax.plot(ext[:, 0], ext[:, 1], color=colours[vehicle.track_id], lw=0.9, ls="--", alpha=0.8, zorder=2)
    pedestrians = []
    for row in range(len(frame)):
        x, y = float(frame.x_m[row]), float(frame.y_m[row])
        track_id = int(frame.track_ids[row])
        if not (math.isfinite(x) and math.isfinite(y)):
            continue
        if int(frame.agent_types[row]) == AgentType.PEDESTRIAN:
            pedestrians.append((x, y))
            continue
        yaw = float(frame.yaw_rad[row])
        length, width = float(frame.length_m[row]), float(frame.width_m[row])
        c, s = math.cos(yaw), math.sin(yaw)
        corners = np.array([(length / 2, width / 2), (length / 2, -width / 2), (-length / 2, -width / 2), (-length / 2, width / 2)])
        box = np.column_stack([x + corners[:, 0] * c - corners[:, 1] * s, y + corners[:, 0] * s + corners[:, 1] * c])
        ax.fill(box[:, 0], box[:, 1], facecolor=colours.get(track_id, "black"), edgecolor="black", lw=0.8, zorder=4)
        ax.plot([x, x + 0.5 * length * c], [y, y + 0.5 * length * s], color="black", lw=0.8, zorder=4)
    if pedestrians:
        p = np.array(pedestrians)
        ax.plot(p[:, 0], p[:, 1], "o", color="#282828", ms=3, zorder=4)
    for vehicle in cars:
        row = int(np.flatnonzero(frame.track_ids == vehicle.track_id)[0])
        tag = str(vehicle.track_id) + ("" if vehicle.status == MatchStatus.MATCHED else " " + vehicle.status.name[:3])
        ax.annotate(tag, (float(frame.x_m[row]), float(frame.y_m[row])), xytext=(0, 9), textcoords="offset points", ha="center",
                    fontsize=7, zorder=6, bbox=dict(boxstyle="round,pad=0.1", fc="white", ec="none", alpha=0.8))
    for overlay in overlays:
        overlay(ax)
    ax.set_xlim(window_m[0], window_m[2])
    ax.set_ylim(window_m[1], window_m[3])
    ax.set_xlabel("x east (m)")
    ax.set_ylabel("y north (m)")
    handles = [
        Patch(facecolor=LANELET_FACE, edgecolor=LANELET_EDGE, label="car lanelets"),
        Line2D([], [], color="#7896c8", lw=0.6, label="other lanelets (walkways, crossings, bike lanes)"),
        Line2D([], [], color="#bebebe", lw=0.6, ls=(0, (4, 4)), label="lanelet centrelines"),
        Line2D([], [], color=PALETTE[0], lw=1.8, label="corridors (colour of their car; dashed: extension past the map)"),
        Patch(facecolor=PALETTE[0], edgecolor="black", label="car at this frame (id; UNM/AMB: not matched)"),
    ]
    if pedestrians:
        handles.append(Line2D([], [], color="#282828", marker="o", ls="none", ms=3, label="pedestrian"))
    for overlay in overlays:
        handles += list(getattr(overlay, "legend_handles", []))
    ax.legend(handles=handles, loc="upper left", fontsize=7, framealpha=0.9)
    if title:
        ax.set_title(title, fontsize=10)
    return fig


def relations_overlay(frame: TrackFrame, relation_set, colours: dict[int, str]) -> Callable:
    """Draw a RelationSet on an Axes: conflict points as x markers, influencing conflicts ringed, leader links."""
    from matplotlib.lines import Line2D

    def draw(ax) -> None:
        rows = {int(t): k for k, t in enumerate(frame.track_ids)}
        for rel in relation_set.relations:
            if rel.leader_track_id >= 0 and rel.leader_track_id in rows:
                a, b = rows[rel.track_id], rows[rel.leader_track_id]
                ax.plot([frame.x_m[a], frame.x_m[b]], [frame.y_m[a], frame.y_m[b]], color="#006e00", lw=1.4, zorder=5)
                ax.plot(float(frame.x_m[b]), float(frame.y_m[b]), "o", color="#006e00", ms=4, zorder=5)
        for rel in relation_set.relations:
            for k in range(len(rel.conflict_x_m)):
                colour = "#dc0000" if rel.conflict_kinds[k] == 1 else "#0000e6"
                ax.plot(float(rel.conflict_x_m[k]), float(rel.conflict_y_m[k]), "x", color=colour, ms=7, mew=1.6, zorder=5)
            if rel.influencing_index >= 0:
                k = rel.influencing_index
                ax.plot(float(rel.conflict_x_m[k]), float(rel.conflict_y_m[k]), "o", mfc="none", mec=colours.get(rel.track_id, "black"),
                        ms=14, mew=1.4, zorder=5)

    draw.legend_handles = [
        Line2D([], [], color="#006e00", lw=1.4, marker="o", ms=4, label="leader link (dot: the leader)"),
        Line2D([], [], color="#dc0000", marker="x", ls="none", ms=7, label="conflict point: crossing"),
        Line2D([], [], color="#0000e6", marker="x", ls="none", ms=7, label="conflict point: merge"),
        Line2D([], [], color="black", marker="o", mfc="none", ls="none", ms=10, label="influencing conflict (colour of the car)"),
    ]
    return draw


def default_data_dir() -> Path:
    from stages.lib.datasets import full_data_dir

    return full_data_dir() or DEFAULT_DATA_DIR


def scene_for(recording, sequence) -> SceneInfo:
    """The SceneInfo a tracks source would publish for this sequence (projection auto)."""
    return SceneInfo(
        header=Header(run_id="bench", frame_index=0, stamp_ns=int(sequence.stamp_ns[0]) if sequence.n_rows else 0, producer="bench"),
        scene_id=f"{recording.name}/{sequence.id}",
        recording=recording.name,
        location_id=recording.location_id,
        map_name=recording.map_path.name,
        map_sha256="",
        projection="auto",
        origin_lat_deg=sequence.origin_lat_deg,
        origin_lon_deg=sequence.origin_lon_deg,
        frame_rate_hz=sequence.frame_rate_hz,
        speed_limit_mps=recording.speed_limit_mps,
        n_frames=sequence.n_frames,
    )


def track_frames(sequence, scene_id: str = ""):
    """The sequence's frames as TrackFrame messages (as the tracks source sends them)."""
    for k, view in enumerate(sequence.frames()):
        yield view, TrackFrame(
            header=Header(run_id="bench", frame_index=k, stamp_ns=view.stamp_ns, producer="bench"),
            scene_id=scene_id,
            track_ids=view.track_id,
            agent_types=view.agent_type,
            x_m=view.x_m,
            y_m=view.y_m,
            vx_mps=view.vx_mps,
            vy_mps=view.vy_mps,
            yaw_rad=view.yaw_rad,
            length_m=view.length_m,
            width_m=view.width_m,
        )


def written_path(parser: argparse.ArgumentParser, out: Path) -> Path:
    """The file ``--out`` names as matplotlib writes it: without a suffix, matplotlib adds that of its default
    format (``savefig.format``, png), so the name gets it here and is printed as written; a suffix matplotlib
    cannot write is refused."""
    import matplotlib
    from matplotlib.backend_bases import FigureCanvasBase

    if not out.suffix:
        return out.with_name(f"{out.name}.{matplotlib.rcParams['savefig.format']}")

    formats = FigureCanvasBase.get_supported_filetypes()
    if out.suffix[1:].lower() not in formats:
        parser.error(f"--out {out}: matplotlib cannot write {out.suffix!r} files; give one of {', '.join('.' + f for f in sorted(formats))}")
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=None, help="data folder laid out like taf-bw")
    parser.add_argument("--recording", default="k729_2022-03-16")
    parser.add_argument("--sequence", default="013")
    parser.add_argument("--frame", type=int, default=None, help="frame_index in the sequence (default: most cars)")
    parser.add_argument("--out", type=Path, default=Path(tempfile.gettempdir()) / "corridors_frame.png")
    parser.add_argument("--dpi", type=int, default=100, help="PNG resolution (default 100)")
    parser.add_argument("--no-svg", action="store_true", help="write the PNG only (default: an SVG beside it too)")
    parser.add_argument("--margin-m", type=float, default=25.0)
    parser.add_argument("--relations", action="store_true", help="draw conflict points and leader links (relations core)")
    args = parser.parse_args(argv)
    check_output_arg(parser, args.out, "--out")  # before the work: a folder or a path that cannot be written
    args.out = written_path(parser, args.out)
    check_output_arg(parser, args.out, "--out")  # (the name with the suffix added: not a folder either)
    if args.dpi < 1:
        parser.error(f"--dpi {args.dpi}: must be >= 1")
    data = args.data or default_data_dir()
    try:
        recording = load_recording(data, args.recording, [args.sequence])
    except DatasetError as exc:  # a data folder, recording or sequence that is not there: a bad command line
        print(f"plot_frame: error: {exc}", file=sys.stderr)
        return 2
    sequence = recording.sequences[0]
    is_car = np.isin(sequence.agent_type, [t.value for t in AgentType if t.is_vehicle])
    if args.frame is None:
        values, counts = np.unique(sequence.frame_index[is_car], return_counts=True)
        args.frame = int(values[counts.argmax()])
    scene = scene_for(recording, sequence)
    builder = CorridorBuilder(CorridorsConfig())
    shown = None
    for view, frame in track_frames(sequence, scene.scene_id):
        corridor_set, _issues = builder.process(frame, scene)
        if view.frame_index == args.frame:
            shown = (frame, corridor_set)
            break
    if shown is None:
        print(f"no frame {args.frame} in {recording.name}/{sequence.id}", file=sys.stderr)
        return 2
    road_map = builder.scene_map.road_map
    lanelets = osm_lanelets(recording.map_path, road_map, scene, builder.scene_map.projection)
    xs, ys = sequence.x_m, sequence.y_m
    window = (xs.min() - args.margin_m, ys.min() - args.margin_m, xs.max() + args.margin_m, ys.max() + args.margin_m)
    frame, corridor_set = shown
    title = f"Corridors of one frame: {recording.name} ({recording.location_id}) sequence {sequence.id}, frame {args.frame}" + (
        ", relations" if args.relations else "")
    overlays = []
    relation_set = None
    if args.relations:
        extractor = RelationExtractor(RelationsConfig(), scene_maps=builder.scene_maps)
        relation_set, _issues = extractor.process(frame, corridor_set, scene)
        cars = [v for v in corridor_set.vehicles if v.agent_type.is_vehicle]
        colours = {v.track_id: PALETTE[k % len(PALETTE)] for k, v in enumerate(cars)}
        overlays.append(relations_overlay(frame, relation_set, colours))
    fig = render_frame(road_map, lanelets, frame, corridor_set, window_m=window, title=title, overlays=overlays)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=args.dpi)
    print(f"wrote {args.out}, {recording.name}/{sequence.id} frame {args.frame}")
    if not args.no_svg and args.out.suffix.lower() != ".svg":
        fig.savefig(args.out.with_suffix(".svg"))
        print(f"wrote {args.out.with_suffix('.svg')}")
    for vehicle in corridor_set.vehicles:
        routes = "; ".join(
            f"{c.corridor_id % 100000:05d}: {'>'.join(str(x) for x in c.lanelet_ids)}" + (f" +ext@{c.extension_start_s_m:.0f}m" if c.extension_start_s_m < c.s_m[-1] else "")
            for c in vehicle.corridors
        )
        print(f"  track {vehicle.track_id:4d} {vehicle.agent_type.name:10s} {vehicle.status.name:13s} v={vehicle.speed_mps:4.1f} {routes}")
    for rel in relation_set.relations if relation_set is not None else ():
        conflicts = ", ".join(
            f"{int(rel.conflict_track_ids[k])}@({rel.conflict_x_m[k]:.1f},{rel.conflict_y_m[k]:.1f}) T={rel.conflict_time_s[k]:.1f}/{rel.conflict_other_time_s[k]:.1f} p={int(rel.conflict_priority[k]):+d}"
            for k in range(len(rel.conflict_x_m))
        )
        influencing = f" influenced by {int(rel.conflict_track_ids[rel.influencing_index])} ({rel.influencing_rule})" if rel.influencing_index >= 0 else ""
        leader = f" leader {rel.leader_track_id} gap {rel.leader_gap_m:.1f} m" if rel.leader_track_id >= 0 else ""
        print(f"  relations {rel.track_id:4d}/{rel.corridor_id % 100000:05d}:{leader}{influencing} conflicts [{conflicts}]")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
