"""Signal groups on the real K733 map: the KML lane file matched to lanelets, routes and corridors; ``iamp signals``."""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

import numpy as np
import pytest

from stages.lib.datasets.signals import read_kml_lanes
from stages.lib.maps import Projection, load_map
from stages.lib.maps.signals import match_lanes

FIXTURE = Path(__file__).resolve().parents[1] / "fixtures" / "taf_bw_signals"
REC = "k733_2020-09-15"
ORIGIN = (49.005306, 8.4374089)  # the recording's meta_data.csv


@pytest.fixture(scope="module")
def matched():
    road_map, _ = load_map(FIXTURE / "maps" / f"{REC}.osm", *ORIGIN, Projection.SCALED_MERCATOR)
    lanes = read_kml_lanes(FIXTURE / "recorded_trackfiles" / REC / "k733_map.kml")
    return road_map, match_lanes(road_map, lanes, Projection.SCALED_MERCATOR, *ORIGIN)


def test_k733_lanes_match_their_lanelets(matched):
    road_map, smap = matched
    by_id = {l.lane_id: l for l in smap.lanes}
    # the approach lanes of the north-east and south-west arms lie within ~1 m of their lanelet centrelines
    for lane_id, lanelet in ((1, -103648), (3, -103650), (41, -103635), (42, -103634), (44, -103632)):
        lane = by_id[lane_id]
        assert lane.matched and lane.stop_lanelet_id == lanelet, lane_id
        assert lane.mean_distance_m < 1.0 and lane.stop_offset_m < 1.0
        # the stop line is at the approach lanelet's end, where the lane meets the junction
        assert road_map.lanelet(lanelet).length_m - lane.stop_s_m < 2.5
    # lane 43 is the unmapped fourth lane of the south-west approach; 2-point lanes are crossings (no car lanelet)
    assert not by_id[43].matched
    assert not any(by_id[x].matched for x in (11, 12, 31, 51, 71))
    assert len(smap.matched) >= 22 and len(smap.signal_groups) >= 10


def test_corridor_gets_the_group_of_its_connection(matched):
    road_map, smap = matched
    # lane 1 (NE approach): straight on to lane 46 is group 1, left to lane 64 is group 2
    for route, group in (((-103648, -103596, -103641), 1), ((-103648, -103593, -104128), 2)):
        starts = np.concatenate([[0.0], np.cumsum([road_map.lanelet(x).length_m for x in route[:-1]])])
        stops = smap.corridor_stops(np.array(route), starts)
        assert [s.signal_group for s in stops] == [group]
        assert stops[0].by_route and stops[0].s_m == pytest.approx(smap.stops_by_lanelet[-103648][0].stop_s_m)
    # a corridor that does not pass a stop lanelet has none
    assert smap.corridor_stops(np.array([-103641]), np.array([0.0])) == []


def test_iamp_signals_prints_report_and_writes_figure(tmp_path, capsys):
    from stages.cli import main

    fig = tmp_path / "k733.png"
    js = tmp_path / "k733.json"
    assert main(["signals", "--data", str(FIXTURE), "--recording", REC, "--figure", str(fig), "--json", str(js)]) == 0
    out = capsys.readouterr().out
    assert "lane   1 ingress matched" in out and "unmatched" in out and "SCALED_MERCATOR" in out
    assert fig.stat().st_size > 10_000 and js.stat().st_size > 1000
    assert main(["signals", "--data", str(tmp_path), "--recording", REC]) == 2
    # another location's map: every lane unmatched; it said so in a table, warned from numpy and exited 0
    from stages.lib.datasets import DEFAULT_DATA_DIR, DEFAULT_RECORDING

    capsys.readouterr()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        code = main(["signals", "--data", str(FIXTURE), "--recording", REC, "--map", str(DEFAULT_DATA_DIR / "maps" / f"{DEFAULT_RECORDING}.osm"),
                     "--figure", str(tmp_path / "wrong.png")])
    out, err = capsys.readouterr()
    assert code == 2 and "no lane matched, no distance" in out
    assert "no lane of the lane file matched a lanelet" in err and "--map" in err


def test_source_publishes_signal_state_when_the_recording_has_phases(tmp_path):
    from bus_schemas import SignalPhase, SignalState
    from stages.lib.datasets import load_recording
    from stages.tracks_source.core import TrackPlayer, TracksSourceConfig
    from testkit.signal_scenes import GROUP, SW_STRAIGHT, Car, signal_recording

    data = signal_recording(tmp_path / "d", [Car(1, SW_STRAIGHT, 90.0, 2.0, 5.0, ((4.0, 0.0),))])
    rec = load_recording(data, REC)
    for signals in (True, False):
        player = TrackPlayer(TracksSourceConfig(recording=REC, signals=signals), rec, map_sha256="", run_id="t", producer="source")
        states = [(stamp, r.outputs.get("signal_state")) for stamp, r in player]
        if not signals:
            assert all(s is None for _, s in states)
            continue
        assert all(isinstance(s, SignalState) and len(s) == 36 and s.header.stamp_ns == stamp for stamp, s in states)
        by_time = {stamp // 100_000_000: s for stamp, s in states}
        assert by_time[915].phase_of(GROUP)[0] is SignalPhase.RED  # 91.5 s
        assert by_time[922].phase_of(GROUP)[0] is SignalPhase.RED_AMBER
        phase, held = by_time[935].phase_of(GROUP)
        assert phase is SignalPhase.GREEN and held == pytest.approx(0.7)
        assert SignalState.decode(by_time[935].encode()).phase_of(GROUP)[0] is SignalPhase.GREEN


def test_viewer_colours_stop_lines_by_phase():
    import bus_schemas as bs
    from stages.tracks_source.core import file_sha256
    from stages.viewer.signals import PHASE_COLOURS, UNKNOWN_COLOUR, load_stop_lines, stop_line_segments

    osm = FIXTURE / "maps" / f"{REC}.osm"
    scene = bs.SceneInfo(
        header=bs.Header(run_id="t", frame_index=0, stamp_ns=0, producer="t"), scene_id="s", recording=REC, location_id="k733",
        map_name=osm.name, map_sha256=file_sha256(osm), projection="auto", origin_lat_deg=ORIGIN[0], origin_lon_deg=ORIGIN[1],
        frame_rate_hz=10.0, speed_limit_mps=13.9, n_frames=1,
    )
    lines, problems = load_stop_lines(scene, str(FIXTURE))
    assert not problems and len(lines) >= 13 and {7, 8} <= {l.group for l in lines}
    grey = stop_line_segments(lines, None)
    assert len(grey) == len(lines) and np.all(grey.colours == np.array(UNKNOWN_COLOUR, np.uint8))
    state = bs.SignalState(header=scene.header, scene_id="s", group_ids=np.array([7, 8], np.int64),
                           phases=np.array([int(bs.SignalPhase.RED), int(bs.SignalPhase.GREEN)], np.uint8), held_s=np.full(2, np.nan))
    seg = stop_line_segments(lines, state)
    for i, line in enumerate(lines):
        want = {7: PHASE_COLOURS[bs.SignalPhase.RED], 8: PHASE_COLOURS[bs.SignalPhase.GREEN]}.get(line.group, UNKNOWN_COLOUR)
        assert tuple(seg.colours[i, 0]) == want
    # a scene without a lane file (the embedded K729 data) has no stop lines
    other = dataclasses.replace(scene, recording="k729_2022-03-16")
    assert load_stop_lines(other, None) == ([], ())
