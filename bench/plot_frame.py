"""Draw one frame: map lanelets, cars as oriented boxes with ids, and their corridors.

Car lanelets are filled light grey, other lanelets (walkways, crosswalks, bike
lanes) outlined; each car and its corridors share a colour (the straight
extension past the map's end is drawn thinner); pedestrians are small dark
dots. The corridors come from running the corridors core in-process over the
sequence up to the frame, so continuity state is as on the bus.

    python bench/plot_frame.py [--data PATH] [--recording NAME] [--sequence SEQ]
                               [--frame N] [--out FILE.png] [--resolution-m 0.1]
                               [--relations]

With `--relations` the relations core runs on the shown frame and draws its
conflict points as x markers (red: crossing, blue: merge; a ring around the
influencing conflict of some corridor, in the colour of the vehicle it
influences) and leader links (a dark green line from each vehicle to its
leader, with a dot at the leader).

Defaults: the TAF-BW folder beside the repository (else the embedded one),
K729, sequence 013, the frame with the most cars, <tmp>/corridors_frame.png.

matplotlib is not installed in the project's environment, so this renders
with a small numpy rasteriser (scanline polygon fill, thick segments, a 3x5
bitmap font) and writes the PNG with stages.lib.raster (zlib and struct). Hook for later
overlays (conflict points from the relations stage): `render_frame(...,
overlays=[fn])` calls each `fn(canvas)` last; `Canvas.marker` and
`Canvas.polyline` draw in map metres.

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
from stages.lib.datasets import load_recording
from stages.lib.maps import Projection, RoadMap, lanelet_bounds
from stages.lib.raster import MapRaster, write_png
from stages.relations import RelationExtractor, RelationsConfig

PALETTE = np.array(
    [
        (228, 26, 28), (55, 126, 184), (77, 175, 74), (152, 78, 163), (255, 127, 0),
        (166, 86, 40), (247, 129, 191), (0, 160, 160), (160, 160, 0), (90, 90, 220),
    ],
    dtype=np.uint8,
)

_FONT = {  # 3x5 glyphs, rows top to bottom, bits left to right
    "0": (7, 5, 5, 5, 7), "1": (2, 6, 2, 2, 7), "2": (7, 1, 7, 4, 7), "3": (7, 1, 7, 1, 7),
    "4": (5, 5, 7, 1, 1), "5": (7, 4, 7, 1, 7), "6": (7, 4, 7, 5, 7), "7": (7, 1, 1, 1, 1),
    "8": (7, 5, 7, 5, 7), "9": (7, 5, 7, 1, 7), "-": (0, 0, 7, 0, 0), " ": (0, 0, 0, 0, 0),
    "K": (5, 5, 6, 5, 5), "F": (7, 4, 6, 4, 4), "S": (7, 4, 7, 1, 7), "N": (7, 5, 5, 5, 5),
    "C": (7, 4, 4, 4, 7), "A": (7, 5, 7, 5, 5), "R": (6, 5, 6, 5, 5), "E": (7, 4, 6, 4, 7),
    ":": (0, 2, 0, 2, 0), ".": (0, 0, 0, 0, 2), "M": (5, 7, 7, 5, 5), "Q": (7, 5, 5, 7, 1),
}


# --------------------------------------------------------------------------- raster canvas


class Canvas(MapRaster):
    """``MapRaster`` plus pixel-width polylines, markers and a 3x5 font for labels."""

    def polyline(self, points_m, colour, width_px: float = 1.0, dash_px: float | None = None) -> None:
        """Thick segments (round joins); optional dashes of `dash_px` on, `dash_px` off."""
        px = self.to_px(points_m)
        half = 0.5 * max(width_px, 1.0)
        travelled = 0.0
        for p, q in zip(px[:-1], px[1:]):
            seg = q - p
            length = float(np.hypot(*seg))
            if dash_px and int(travelled // dash_px) % 2 == 1:
                travelled += length
                continue
            travelled += length
            c0 = max(0, int(min(p[0], q[0]) - half - 1))
            c1 = min(self.width, int(max(p[0], q[0]) + half + 2))
            r0 = max(0, int(min(p[1], q[1]) - half - 1))
            r1 = min(self.height, int(max(p[1], q[1]) + half + 2))
            if c1 <= c0 or r1 <= r0:
                continue
            yy, xx = np.mgrid[r0:r1, c0:c1] + 0.5
            rel_x, rel_y = xx - p[0], yy - p[1]
            t = np.clip((rel_x * seg[0] + rel_y * seg[1]) / max(length * length, 1e-12), 0.0, 1.0)
            dist = np.hypot(rel_x - t * seg[0], rel_y - t * seg[1])
            self.rgb[r0:r1, c0:c1][dist <= half] = colour

    def marker(self, x_m: float, y_m: float, colour, radius_px: float = 3.0) -> None:
        """A filled disc at a map position (the overlay hook's basic shape)."""
        cx, cy = self.to_px([x_m, y_m])[0]
        r0, r1 = max(0, int(cy - radius_px - 1)), min(self.height, int(cy + radius_px + 2))
        c0, c1 = max(0, int(cx - radius_px - 1)), min(self.width, int(cx + radius_px + 2))
        if r1 <= r0 or c1 <= c0:
            return
        yy, xx = np.mgrid[r0:r1, c0:c1] + 0.5
        self.rgb[r0:r1, c0:c1][np.hypot(xx - cx, yy - cy) <= radius_px] = colour

    def text(self, x_px: int, y_px: int, text: str, colour, scale: int = 2) -> None:
        """Upper-case text in the 3x5 font at a pixel position (top left)."""
        for k, ch in enumerate(text.upper()):
            glyph = _FONT.get(ch, _FONT[" "])
            for gy, bits in enumerate(glyph):
                for gx in range(3):
                    if bits & (4 >> gx):
                        r = y_px + gy * scale
                        c = x_px + (k * 4 + gx) * scale
                        if 0 <= r and r + scale <= self.height and 0 <= c and c + scale <= self.width:
                            self.rgb[r : r + scale, c : c + scale] = colour

    def label(self, x_m: float, y_m: float, text: str, colour, scale: int = 2) -> None:
        cx, cy = self.to_px([x_m, y_m])[0]
        w = len(text) * 4 * scale
        x, y = int(cx - w / 2), int(cy - 2.5 * scale)
        self.rgb[max(0, y - 1) : max(0, y + 5 * scale + 1), max(0, x - 1) : max(0, x + w)] = (255, 255, 255)
        self.text(x, y, text, colour, scale)


# --------------------------------------------------------------------------- map outlines


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
    resolution_m: float = 0.1,
    title: str = "",
    overlays: Sequence[Callable[[Canvas], None]] = (),
) -> Canvas:
    """Draw the map, the corridors and the objects of one frame; then each overlay."""
    canvas = Canvas(*window_m, resolution_m)
    for _id, is_car, left, right in lanelets:
        if is_car:
            canvas.fill_polygon(np.concatenate([left, right[::-1]]), (222, 222, 222))
    for _id, is_car, left, right in lanelets:
        colour = (150, 150, 150) if is_car else (120, 150, 200)
        canvas.polyline(left, colour, 1.0)
        canvas.polyline(right, colour, 1.0)
    for lanelet_id in road_map.lanelet_ids:
        canvas.polyline(road_map.lanelet(lanelet_id).centreline.points_m, (190, 190, 190), 1.0, dash_px=6)
    colours = {}
    cars = [v for v in corridor_set.vehicles if v.agent_type.is_vehicle]
    for k, vehicle in enumerate(cars):
        colours[vehicle.track_id] = tuple(int(c) for c in PALETTE[k % len(PALETTE)])
    for vehicle in cars:
        for corridor in vehicle.corridors:
            pts = np.column_stack([corridor.x_m, corridor.y_m])
            mapped = corridor.s_m <= corridor.extension_start_s_m
            canvas.polyline(pts[mapped], colours[vehicle.track_id], 3.0)
            if (~mapped).any():
                canvas.polyline(pts[np.flatnonzero(~mapped)[0] - 1 :], colours[vehicle.track_id], 1.5, dash_px=8)
    for row in range(len(frame)):
        x, y = float(frame.x_m[row]), float(frame.y_m[row])
        track_id = int(frame.track_ids[row])
        if not (math.isfinite(x) and math.isfinite(y)):
            continue
        if int(frame.agent_types[row]) == AgentType.PEDESTRIAN:
            canvas.marker(x, y, (40, 40, 40), 4.0)
            continue
        yaw = float(frame.yaw_rad[row])
        length, width = float(frame.length_m[row]), float(frame.width_m[row])
        c, s = math.cos(yaw), math.sin(yaw)
        corners = np.array([(length / 2, width / 2), (length / 2, -width / 2), (-length / 2, -width / 2), (-length / 2, width / 2)])
        box = np.column_stack([x + corners[:, 0] * c - corners[:, 1] * s, y + corners[:, 0] * s + corners[:, 1] * c])
        colour = colours.get(track_id, (0, 0, 0))
        canvas.fill_polygon(box, colour)
        canvas.polyline(np.vstack([box, box[:1]]), (0, 0, 0), 1.5)
        canvas.polyline(np.array([(x, y), (x + 0.5 * length * c, y + 0.5 * length * s)]), (0, 0, 0), 1.5)
    for vehicle in cars:
        row = int(np.flatnonzero(frame.track_ids == vehicle.track_id)[0])
        tag = str(vehicle.track_id) + ("" if vehicle.status == MatchStatus.MATCHED else " " + vehicle.status.name[:3])
        canvas.label(float(frame.x_m[row]), float(frame.y_m[row]) + 3.0, tag, (0, 0, 0))
    for overlay in overlays:
        overlay(canvas)
    if title:
        canvas.text(10, 10, title, (0, 0, 0), 3)
    return canvas


def relations_overlay(frame: TrackFrame, relation_set, colours: dict[int, tuple[int, int, int]]) -> Callable[[Canvas], None]:
    """Draw a RelationSet: conflict points as x markers, influencing conflicts ringed, leader links."""

    def draw(canvas: Canvas) -> None:
        rows = {int(t): k for k, t in enumerate(frame.track_ids)}
        size = 0.9
        for rel in relation_set.relations:
            if rel.leader_track_id >= 0 and rel.leader_track_id in rows:
                a, b = rows[rel.track_id], rows[rel.leader_track_id]
                link = np.array([(frame.x_m[a], frame.y_m[a]), (frame.x_m[b], frame.y_m[b])])
                canvas.polyline(link, (0, 110, 0), 2.0)
                canvas.marker(float(frame.x_m[b]), float(frame.y_m[b]), (0, 110, 0), 3.0)
        for rel in relation_set.relations:
            for k in range(len(rel.conflict_x_m)):
                x, y = float(rel.conflict_x_m[k]), float(rel.conflict_y_m[k])
                colour = (220, 0, 0) if rel.conflict_kinds[k] == 1 else (0, 0, 230)
                canvas.polyline(np.array([(x - size, y - size), (x + size, y + size)]), colour, 2.0)
                canvas.polyline(np.array([(x - size, y + size), (x + size, y - size)]), colour, 2.0)
            if rel.influencing_index >= 0:
                k = rel.influencing_index
                angles = np.linspace(0.0, 2.0 * math.pi, 25)
                ring = np.column_stack([rel.conflict_x_m[k] + 1.8 * np.cos(angles), rel.conflict_y_m[k] + 1.8 * np.sin(angles)])
                canvas.polyline(ring, colours.get(rel.track_id, (0, 0, 0)), 2.0)

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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=None, help="data folder laid out like taf-bw")
    parser.add_argument("--recording", default="k729_2022-03-16")
    parser.add_argument("--sequence", default="013")
    parser.add_argument("--frame", type=int, default=None, help="frame_index in the sequence (default: most cars)")
    parser.add_argument("--out", type=Path, default=Path(tempfile.gettempdir()) / "corridors_frame.png")
    parser.add_argument("--resolution-m", type=float, default=0.1)
    parser.add_argument("--margin-m", type=float, default=25.0)
    parser.add_argument("--relations", action="store_true", help="draw conflict points and leader links (relations core)")
    args = parser.parse_args(argv)
    data = args.data or default_data_dir()
    recording = load_recording(data, args.recording, [args.sequence])
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
    title = f"{recording.location_id} {sequence.id} F{args.frame}"
    overlays = []
    relation_set = None
    if args.relations:
        extractor = RelationExtractor(RelationsConfig(), scene_maps=builder.scene_maps)
        relation_set, _issues = extractor.process(frame, corridor_set, scene)
        cars = [v for v in corridor_set.vehicles if v.agent_type.is_vehicle]
        colours = {v.track_id: tuple(int(c) for c in PALETTE[k % len(PALETTE)]) for k, v in enumerate(cars)}
        overlays.append(relations_overlay(frame, relation_set, colours))
    canvas = render_frame(
        road_map, lanelets, frame, corridor_set, window_m=window, resolution_m=args.resolution_m, title=title, overlays=overlays
    )
    write_png(args.out, canvas.rgb)
    print(f"wrote {args.out} ({canvas.width}x{canvas.height} px), {recording.name}/{sequence.id} frame {args.frame}")
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
