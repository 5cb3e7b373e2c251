"""Signal-phase CSV and KML lane readers (stages.lib.datasets.signals) and their discovery beside the tracks."""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import pytest

from bus_schemas.signals import SignalPhase
from stages.lib.datasets import DatasetError, load_recording
from stages.lib.datasets.signals import BAD_LANE, UNKNOWN_MOVEMENT_STATE, read_kml_lanes, read_signal_phases

FIXTURE = Path(__file__).resolve().parents[1] / "fixtures" / "taf_bw_signals"
REC = "k733_2020-09-15"
REC_DIR = FIXTURE / "recorded_trackfiles" / REC


def test_real_signal_file_timing():
    phases = read_signal_phases([REC_DIR / "signal_phases_000.csv"])
    assert len(phases.group_ids) == 36 and phases.end_ms == 157500
    assert phases.report.ok
    # group 1 (Lane 1, 2 straight on): red until 45.8 s, red-amber for 1 s, green from 46.8 s to 59.8 s
    ph, held = phases.state(1, 10_000_000_000)
    assert ph is SignalPhase.RED and math.isnan(held)  # red since before the file's start: held unknown
    ph, held = phases.state(1, 50_000_000_000)
    assert ph is SignalPhase.GREEN and held == pytest.approx(3.2)
    assert phases.state(1, 46_000_000_000)[0] is SignalPhase.RED_AMBER
    assert phases.state(1, 61_000_000_000)[0] is SignalPhase.AMBER
    assert phases.state(1, 200_000_000_000)[0] is SignalPhase.UNKNOWN  # after the file's end
    assert phases.state(99, 1)[0] is SignalPhase.UNKNOWN


def test_bad_signal_rows_are_counted_with_file_and_line(tmp_path):
    p = tmp_path / "signal_phases_000.csv"
    p.write_text(
        "timestamp_ms,movement_state,signal_group_id\n"  # columns by name, any order
        "0,STOP_AND_REMAIN,1\n"
        "100,,1\n"  # line 3: missing
        "abc,STOP_AND_REMAIN,1\n"  # line 4: non-numeric
        "200,BLINKING,1\n"  # line 5: unknown state, kept as UNKNOWN
        "200,STOP_AND_REMAIN,1\n"  # line 6: duplicate
        "150,STOP_AND_REMAIN,1\n"  # line 7: backwards
        "300,PERMISSIVE_MOVEMENT_ALLOWED,1\n"
    )
    phases = read_signal_phases([p])
    rep = phases.report
    assert rep.rows_read == 7 and rep.rows_kept == 3
    assert rep.count("missing_field") == 1 and rep.get("missing_field").examples[0].line == 3
    assert rep.count("non_numeric") == 1 and rep.get("non_numeric").examples[0].line == 4
    assert rep.count(UNKNOWN_MOVEMENT_STATE) == 1 and rep.get(UNKNOWN_MOVEMENT_STATE).examples[0].line == 5
    assert rep.count("duplicate_frame") == 1 and rep.count("time_backwards") == 1
    assert phases.state(1, 250_000_000)[0] is SignalPhase.UNKNOWN
    assert phases.state(1, 300_000_000)[0] is SignalPhase.GREEN
    with pytest.raises(DatasetError, match="missing column"):
        bad = tmp_path / "b.csv"
        bad.write_text("group,timestamp_ms,movement_state\n1,0,DARK\n")
        read_signal_phases([bad])


def test_kml_lanes_by_element_name():
    lanes = read_kml_lanes(REC_DIR / "k733_map.kml")
    assert len(lanes.lanes) == 44 and lanes.report.ok
    assert lanes.ref_lat_deg == pytest.approx(49.0050713)
    l1 = lanes.lane(1)
    assert [c.sink_lane for c in l1.connections] == [46, 64, 63] and l1.signal_groups == (1, 2)
    assert lanes.lane(5).connections == () and not lanes.lane(5).is_ingress


def test_bad_kml_lane_counted(tmp_path):
    text = (REC_DIR / "k733_map.kml").read_text()
    text = text.replace("<value>3</value>", "<value>three</value>", 1)  # Lane 3's Source
    p = tmp_path / "x.kml"
    p.write_text(text)
    lanes = read_kml_lanes(p)
    assert len(lanes.lanes) == 43 and lanes.report.count(BAD_LANE) == 1
    assert lanes.report.get(BAD_LANE).examples[0].line > 0


def test_recording_folder_gets_its_signal_side(tmp_path):
    shutil.copytree(FIXTURE, tmp_path / "d")
    folder = tmp_path / "d" / "recorded_trackfiles" / REC
    (folder / "vehicle_tracks_000.csv").write_text(
        "track_id,frame_id,timestamp_ms,agent_type,x,y,vx,vy,psi_rad,length,width\n"
        + "".join(f"1,{k},{k * 100},car,{k * 1.0},0,10,0,0,4.5,1.8\n" for k in range(10))
    )
    rec = load_recording(tmp_path / "d", REC)
    assert rec.signal_phases is not None and len(rec.signal_phases.group_ids) == 36
    assert rec.kml_lanes is not None and len(rec.kml_lanes.lanes) == 44
    assert not rec.report.ignored_files and rec.report.rows_read == 10


def test_lane_file_is_looked_up_by_plain_recording_name_only():
    from stages.lib.datasets.signals import lane_file_for

    assert lane_file_for(FIXTURE, REC) == REC_DIR / "k733_map.kml"
    for hostile in ("..", "../taf_bw_signals/recorded_trackfiles/" + REC, "/etc", "", ".hidden", "a/b"):
        assert lane_file_for(FIXTURE, hostile) is None


@pytest.mark.parametrize("damage", ["half", "empty"])
def test_a_lane_file_that_cannot_be_read_costs_the_signals_not_the_recording(tmp_path, damage):
    """A KML cut in half (or empty) made the whole recording unreadable: every sequence skipped by `iamp eval`, `iamp
    train` stopped. The signal side is optional: the tracks load without it, and the report says which file was not
    used and why."""
    from stages.lib.datasets import DEFAULT_DATA_DIR, load_recording

    rec_dir = tmp_path / "recorded_trackfiles" / REC
    rec_dir.mkdir(parents=True)
    (tmp_path / "maps").mkdir()
    shutil.copy(FIXTURE / "maps" / f"{REC}.osm", tmp_path / "maps" / f"{REC}.osm")
    shutil.copy(REC_DIR / "meta_data.csv", rec_dir / "meta_data.csv")
    shutil.copy(REC_DIR / "signal_phases_000.csv", rec_dir / "signal_phases_000.csv")
    tracks = (DEFAULT_DATA_DIR / "recorded_trackfiles" / "k733_2018-05-02" / "vehicle_tracks_000.csv").read_text().splitlines()
    (rec_dir / "vehicle_tracks_000.csv").write_text("\n".join(tracks[:300]) + "\n")
    kml = (REC_DIR / "k733_map.kml").read_text()
    (rec_dir / "k733_map.kml").write_text(kml[: len(kml) // 2] if damage == "half" else "")
    rec = load_recording(tmp_path, REC)
    assert rec.sequences and rec.kml_lanes is None and rec.signal_phases is not None
    assert any("k733_map.kml (not used: " in f for f in rec.report.ignored_files), rec.report.ignored_files


def test_a_lane_with_a_coordinate_typo_is_a_bad_lane_not_a_hang(tmp_path):
    """A latitude of 89.9 for 49.0 in one point: the lane, thousands of km long, was resampled every metre and matched
    against the whole map (`iamp signals` ran for minutes into gigabytes; the relations stage and the viewer read the
    same file). It is counted as a bad lane; the other lanes are kept."""
    import json as _json

    text = (REC_DIR / "k733_map.kml").read_text()
    first = "8.43807526003106823,49.00557334673142407"
    assert first in text
    kml = tmp_path / "k733_map.kml"
    kml.write_text(text.replace(first, "8.43807526003106823,89.9", 1))
    lanes = read_kml_lanes(kml)
    whole = read_kml_lanes(REC_DIR / "k733_map.kml")
    assert len(lanes.lanes) == len(whole.lanes) - 1
    bad = lanes.report.get(BAD_LANE)
    assert bad is not None and bad.count == 1 and "km from the file's other lanes" in bad.examples[0].detail, lanes.report.summary()

    # and iamp signals --json is strict JSON (NaN for an unmatched lane's distances was written as NaN)
    from stages import cli

    out = tmp_path / "sig.json"
    assert cli.main(["signals", "--data", str(FIXTURE), "--recording", REC, "--json", str(out), "--figure", str(tmp_path / "s.png")]) == 0
    _json.loads(out.read_text(), parse_constant=lambda c: (_ for _ in ()).throw(ValueError(f"{c} in strict JSON")))
