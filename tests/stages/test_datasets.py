"""Dataset readers: real TAF-BW files, bad rows, extra files, the inD fixture, kinematics."""

from __future__ import annotations

import csv
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from bus_schemas import AgentType
from stages.lib.datasets import (
    DEFAULT_DATA_DIR,
    full_data_dir,
    DEFAULT_RECORDING,
    DatasetError,
    RepairRule,
    derive_kinematics,
    discover,
    load_recording,
    repair_track,
)

REPO = Path(__file__).resolve().parents[2]
TAF = full_data_dir() or REPO / "no-full-data"  # $IAMP_TAF_BW: the full TAF-BW recordings
IND_SMALL = REPO / "tests/fixtures/ind_small"
K729 = "k729_2022-03-16"
K733 = "k733_2018-05-02"

needs_taf = pytest.mark.skipif(not (TAF / "recorded_trackfiles").is_dir(), reason="full TAF-BW data not found: set IAMP_TAF_BW to its folder")

META_HEADER = (
    "id,frameRate_hz,locationId,speedLimit_kmh,date,weekDay,startTime,duration,"
    "originLat,originLon,spatAvailable,simulated,tracking,timeZone"
)
META_ROW = "000,10,K729,50,2022-03-16,Wed,11:17:19.098,25.5,49.01160993928274,8.43856470258739,no,no,online,GMT+1"
K729_HEADER = "track_id,frame_id,timestamp_ms,agent_type,vx,vy,psi_rad,length,width,time,x,y"
K733_HEADER = "track_id,frame_id,timestamp_ms,agent_type,x,y,vx,vy,psi_rad,length,width"


def read_raw(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as fh:
        return list(csv.DictReader(fh))


def make_folder(root: Path, tracks: dict[str, str], meta: str | None = f"{META_HEADER}\n{META_ROW}\n", name: str = "rec") -> Path:
    """A minimal INTERACTION-format data folder with the given track files (name -> CSV text)."""
    folder = root / "recorded_trackfiles" / name
    folder.mkdir(parents=True)
    (root / "maps").mkdir(exist_ok=True)
    (root / "maps" / f"{name}.osm").write_text("<osm version='0.6'/>\n")
    if meta is not None:
        (folder / "meta_data.csv").write_text(meta)
    for file_name, text in tracks.items():
        (folder / file_name).write_text(text)
    return root


def good_rows_k733(track_id: int = 1, n: int = 6, speed_mps: float = 5.0, skip: tuple[int, ...] = ()) -> list[str]:
    """A car driving east at ``speed_mps`` in k733 column order, 10 Hz, without the frames in ``skip``."""
    rows = []
    for k in range(n):
        if k in skip:
            continue
        x = -20.0 + speed_mps * 0.1 * k
        rows.append(f"{track_id},{100 + k},{100 * k},Car,{x:.4f},-10.0,{speed_mps},0.0,0.0,4.5,1.8")
    return rows


# --------------------------------------------------------------------------- real TAF-BW data


@needs_taf
def test_both_column_orders_read_to_the_same_fields(tmp_path: Path) -> None:
    # the real files order their columns differently
    k729_file = TAF / "recorded_trackfiles" / K729 / "vehicle_tracks_013.csv"
    k733_file = TAF / "recorded_trackfiles" / K733 / "vehicle_tracks_000.csv"
    assert k729_file.open().readline().strip() == K729_HEADER
    assert k733_file.open().readline().strip() == K733_HEADER

    # the same rows written in both orders load to identical arrays
    values = [
        dict(track_id=7, frame_id=10 + k, timestamp_ms=100 * k, agent_type="Car", x=1.0 + 0.5 * k, y=-2.0 + 0.25 * k,
             vx=5.0, vy=2.5, psi_rad=math.atan2(2.5, 5.0), length=4.6, width=2.1, time=f"2022-03-16 11:17:19.{k}00")
        for k in range(8)
    ]
    def text(header: str) -> str:
        cols = header.split(",")
        return header + "\n" + "".join(",".join(str(v[c]) for c in cols) + "\n" for v in values)

    a = load_recording(make_folder(tmp_path / "a", {"vehicle_tracks_000.csv": text(K729_HEADER)}), "rec").sequences[0]
    b = load_recording(make_folder(tmp_path / "b", {"vehicle_tracks_000.csv": text(K733_HEADER)}), "rec").sequences[0]
    for name in ("frame_index", "stamp_ns", "track_id", "agent_type", "x_m", "y_m", "vx_mps", "vy_mps", "yaw_rad", "length_m", "width_m"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    np.testing.assert_allclose(a.x_m, [v["x"] for v in values])
    np.testing.assert_allclose(a.length_m, 4.6)

    # and a real row of each file lands in the right fields
    for path, rec_name in ((k729_file, K729), (k733_file, K733)):
        raw = read_raw(path)[10]
        seq = load_recording(TAF, rec_name, [path.stem.rsplit("_", 1)[1]]).sequences[0]
        i = np.flatnonzero((seq.track_id == int(raw["track_id"])) & (seq.stamp_ns == int(raw["timestamp_ms"]) * 1_000_000))
        assert i.size == 1, rec_name
        assert seq.x_m[i[0]] == float(raw["x"]) and seq.y_m[i[0]] == float(raw["y"])
        assert seq.length_m[i[0]] == float(raw["length"]) and seq.width_m[i[0]] == float(raw["width"])
        assert seq.agent_type[i[0]] == AgentType.CAR


@needs_taf
def test_k729_sequence_013_counts_match_an_independent_read() -> None:
    raw = read_raw(TAF / "recorded_trackfiles" / K729 / "vehicle_tracks_013.csv")
    stamps = {int(r["timestamp_ms"]) for r in raw}
    tracks = {int(r["track_id"]) for r in raw}
    cars = {int(r["track_id"]) for r in raw if r["agent_type"] == "Car"}
    walkers = {int(r["track_id"]) for r in raw if r["agent_type"] == "Pedestrian"}

    rec = load_recording(TAF, K729, ["013"])
    seq = rec.sequence("013")
    assert (seq.n_rows, seq.n_frames, seq.n_tracks) == (len(raw), len(stamps), len(tracks))
    assert (len(raw), len(stamps), len(tracks)) == (3537, 1123, 44)  # measured; plausible for 117.7 s at 10 Hz
    assert seq.n_frames / rec.frame_rate_hz <= seq.duration_s + 1.0
    assert seq.tracks_by_type() == {AgentType.CAR: len(cars), AgentType.PEDESTRIAN: len(walkers)}
    assert rec.report.ok, rec.report.summary()  # k729 013 needs no skip and no repair
    assert rec.location_id == "K729" and rec.frame_rate_hz == 10.0
    assert rec.speed_limit_mps == pytest.approx(50 / 3.6)
    assert seq.start_time == "2022-03-16T11:24:32.398+01:00"
    # sorted by (frame, track), stamps from timestamp_ms
    key = seq.frame_index * 10**9 + seq.track_id
    assert np.all(np.diff(key) > 0)
    np.testing.assert_array_equal(seq.stamp_ns, seq.frame_index * 100_000_000)


@needs_taf
def test_k733_duplicates_skipped_and_kinematics_made_consistent_with_positions() -> None:
    rec = load_recording(TAF, K733)
    rep = rec.report
    dup = rep.get("duplicate_frame")
    assert dup is not None and dup.count == 104  # measured: 104 rows repeat (track, timestamp)
    assert dup.examples[0].line == 2637 and dup.examples[0].file.endswith("vehicle_tracks_000.csv")
    assert rep.rows_read == 12079 and rep.rows_kept == 12079 - 104
    # the sign of k733's velocity is inverted and its yaw known modulo pi: the yaw is repaired; the
    # velocity only on request (the stages' estimator calibrates the sign itself, causally)
    assert rep.count("velocity_sign_flipped") == 0
    assert load_recording(TAF, K733, rule=RepairRule(repair_velocity=True)).report.count("velocity_sign_flipped") > 10_000
    assert rep.count("yaw_flipped") > 1000
    seq = rec.sequences[0]
    yaw_cos, velocity_cos = [], []
    for tid in np.unique(seq.track_id):
        m = np.flatnonzero(seq.track_id == tid)
        if m.size < 5:
            continue
        kin = derive_kinematics(seq.stamp_ns[m] * 1e-9, seq.x_m[m], seq.y_m[m])
        fast = kin.speed_mps > 2.0
        yaw_cos.append(np.cos(seq.yaw_rad[m][fast] - np.arctan2(kin.vy_mps[fast], kin.vx_mps[fast])))
        velocity_cos.append(
            (seq.vx_mps[m][fast] * kin.vx_mps[fast] + seq.vy_mps[m][fast] * kin.vy_mps[fast])
            / np.maximum(np.hypot(seq.vx_mps[m][fast], seq.vy_mps[m][fast]) * kin.speed_mps[fast], 1e-9)
        )
    assert np.mean(np.concatenate(yaw_cos) > 0.5) > 0.98
    assert np.mean(np.concatenate(velocity_cos) < -0.5) > 0.98  # left as the tracker reported them


@needs_taf
def test_embedded_scenario_loads_only_sequences_that_have_a_track_file() -> None:
    refs = {r.name: r for r in discover(DEFAULT_DATA_DIR)}
    assert sorted(refs) == [DEFAULT_RECORDING, "k733_2018-05-02"]  # K729 (the default) and K733
    ref = refs[DEFAULT_RECORDING]
    assert ref.map_path is not None
    assert len(read_raw(ref.meta_path)) == 25  # meta_data.csv kept whole
    assert ref.sequence_ids == ("002", "013", "019", "022")
    rec = load_recording(DEFAULT_DATA_DIR, DEFAULT_RECORDING)
    assert [s.id for s in rec.sequences] == ["002", "013", "019", "022"]
    with pytest.raises(DatasetError, match="no track file for sequence '005'.*available: 002, 013, 019, 022"):
        load_recording(DEFAULT_DATA_DIR, DEFAULT_RECORDING, ["005"])
    # the embedded files are byte-identical copies
    for p in [p for r in refs.values() for p in (r.map_path, r.meta_path, *r.track_files)]:
        assert p.read_bytes() == (TAF / p.relative_to(DEFAULT_DATA_DIR)).read_bytes()


# --------------------------------------------------------------------------- bad rows and bad folders


def test_each_bad_row_reason_is_counted_with_file_and_line(tmp_path: Path) -> None:
    good = good_rows_k733(track_id=1, n=7, skip=(2,))
    lines = [K733_HEADER, *good]  # lines 2..7 are good: track 1 at 0, 100, 300 ... 600 ms
    lines += [
        "2,200,0,Car,,1.0,0,0,0,4,2",  # 8: missing x
        "2,201,100,Car,abc,1.0,0,0,0,4,2",  # 9: non-numeric x
        "2,202,200,Car,nan,1.0,0,0,0,4,2",  # 10: NaN position
        "2,203,300,Car,1.0,inf,0,0,0,4,2",  # 11: inf position
        "1,104,400,Car,-18.0,-10.0,5,0,0,4.5,1.8",  # 12: track 1 at 400 ms again
        "1,99,200,Car,-19.0,-10.0,5,0,0,4.5,1.8",  # 13: track 1 back to 200 ms after 600 ms
        "3,300,0,Car",  # 14: short row
        "4,400,0,Hovercraft,5.0,5.0,0,0,0.5,3,2",  # 15: unknown type, kept
        "5,500,0,Car,6.0,6.0,nan,nan,nan,4,2",  # 16: NaN velocity and yaw, kept and repaired
        "5,501,100,Car,6.5,6.0,5,0,0.0,4,2",
        "5,502,200,Car,7.0,6.0,5,0,0.0,4,2",
    ]
    root = make_folder(tmp_path, {"vehicle_tracks_000.csv": "\n".join(lines) + "\n"})
    rec = load_recording(root, "rec")
    rep = rec.report
    expected = {
        "missing_field": (2, 8),
        "non_numeric": (1, 9),
        "non_finite_position": (2, 10),
        "duplicate_frame": (1, 12),
        "time_backwards": (1, 13),
        "unknown_agent_type": (1, 15),
    }
    for reason, (count, first_line) in expected.items():
        p = rep.get(reason)
        assert p is not None, f"{reason} not reported: {rep.summary()}"
        assert p.count == count, reason
        assert p.examples[0].line == first_line, reason
        assert p.examples[0].file == "recorded_trackfiles/rec/vehicle_tracks_000.csv"
    assert rep.get("missing_field").examples[1].line == 14
    assert rep.get("time_backwards").action == "skipped" and rep.get("unknown_agent_type").action == "kept"
    assert rep.rows_read == len(lines) - 1
    assert rep.rows_skipped == 7 and rep.rows_kept == rep.rows_read - 7
    seq = rec.sequences[0]
    assert AgentType.UNKNOWN in seq.tracks_by_type()  # kept, not dropped
    # NaN velocity and yaw of track 5 were derived from its positions (5 m/s east)
    i = np.flatnonzero(seq.track_id == 5)[0]
    assert seq.vx_mps[i] == pytest.approx(5.0) and seq.vy_mps[i] == pytest.approx(0.0, abs=1e-9)
    assert seq.yaw_rad[i] == pytest.approx(0.0, abs=1e-9)
    assert rep.get("velocity_nan_from_positions").examples[0].line == 16
    for name in ("x_m", "y_m", "vx_mps", "vy_mps", "yaw_rad", "length_m", "width_m"):
        assert np.all(np.isfinite(getattr(seq, name))), name


def test_file_with_no_usable_row_raises_naming_the_file(tmp_path: Path) -> None:
    bad = "\n".join([K733_HEADER, "1,1,0,Car,,1,0,0,0,4,2", "1,2,100,Car,x,1,0,0,0,4,2"]) + "\n"
    root = make_folder(tmp_path / "a", {"vehicle_tracks_000.csv": bad})
    with pytest.raises(DatasetError, match=r"vehicle_tracks_000\.csv: no usable row \(skipped missing_field=1, non_numeric=1\)"):
        load_recording(root, "rec")
    root = make_folder(tmp_path / "b", {"vehicle_tracks_000.csv": K733_HEADER + "\n"})
    with pytest.raises(DatasetError, match=r"vehicle_tracks_000\.csv: no usable row \(no data rows\)"):
        load_recording(root, "rec")
    root = make_folder(tmp_path / "c", {"vehicle_tracks_000.csv": "track_id,frame_id,x,y\n1,1,0,0\n"})
    with pytest.raises(DatasetError, match=r"vehicle_tracks_000\.csv: missing column\(s\) timestamp_ms, agent_type"):
        load_recording(root, "rec")


def test_missing_meta_or_origin_raises(tmp_path: Path) -> None:
    tracks = {"vehicle_tracks_000.csv": "\n".join([K733_HEADER, *good_rows_k733()]) + "\n"}
    with pytest.raises(DatasetError, match="meta_data.csv is missing"):
        load_recording(make_folder(tmp_path / "a", tracks, meta=None), "rec")
    no_origin = f"{META_HEADER}\n" + META_ROW.replace("49.01160993928274", "") + "\n"
    with pytest.raises(DatasetError, match=r"meta_data.csv:2: no value for originLat"):
        load_recording(make_folder(tmp_path / "b", tracks, meta=no_origin), "rec")
    other_seq = f"{META_HEADER}\n" + META_ROW.replace("000,", "007,", 1) + "\n"
    with pytest.raises(DatasetError, match="no row for sequence 000"):
        load_recording(make_folder(tmp_path / "c", tracks, meta=other_seq), "rec")


def test_missing_or_empty_data_folder_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="does not exist"):
        discover(tmp_path / "nope")
    (tmp_path / "a-file").write_text("x")
    with pytest.raises(DatasetError, match=r"a-file is a file, not a folder \(expected"):
        discover(tmp_path / "a-file")
    with pytest.raises(DatasetError, match=r"no recordings under .*: expected maps/<rec>\.osm and recorded_trackfiles/<rec>/"):
        discover(tmp_path)
    assert isinstance(DatasetError("x"), ValueError)  # run_stage maps it to exit code 2


@needs_taf
def test_extra_files_beside_the_tracks_are_ignored(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    src = TAF / "recorded_trackfiles" / K729
    folder = tmp_path / "recorded_trackfiles" / K729
    folder.mkdir(parents=True)
    (tmp_path / "maps").mkdir()
    shutil.copy(TAF / "maps" / f"{K729}.osm", tmp_path / "maps")
    (tmp_path / "maps" / "README.txt").write_text("not a map\n")
    for name in ("meta_data.csv", "vehicle_tracks_019.csv"):
        shutil.copy(src / name, folder)
    extras = ["notes.txt", "vehicle_tracks_019.csv.bak", ".DS_Store", "019_background.png"]
    for name in extras:
        (folder / name).write_text("junk\n")
    (folder / "plots").mkdir()
    (tmp_path / "recorded_trackfiles" / "empty_folder").mkdir()
    with caplog.at_level("DEBUG", logger="iamp.datasets"):
        (ref,) = discover(tmp_path)
    assert sorted(p.name for p in ref.ignored_files) == sorted(extras)
    assert "ignored file: path=" in caplog.text
    rec = load_recording(tmp_path, K729)
    assert [s.id for s in rec.sequences] == ["019"]
    assert len(rec.report.ignored_files) == len(extras)
    assert rec.sequences[0].n_rows == len(read_raw(src / "vehicle_tracks_019.csv"))


def test_pedestrian_track_files_join_their_sequence(tmp_path: Path) -> None:
    vehicles = "\n".join([K733_HEADER, *good_rows_k733(track_id=1)]) + "\n"
    # INTERACTION pedestrian files: ids like P1, no psi_rad/length/width
    walkers = "track_id,frame_id,timestamp_ms,agent_type,x,y,vx,vy\n" + "".join(
        f"P1,{100 + k},{100 * k},pedestrian/bicycle,{0.13 * k:.2f},0.0,1.3,0.0\n" for k in range(5)
    )
    root = make_folder(tmp_path, {"vehicle_tracks_000.csv": vehicles, "pedestrian_tracks_000.csv": walkers})
    (seq,) = load_recording(root, "rec").sequences
    assert seq.tracks_by_type() == {AgentType.CAR: 1, AgentType.PEDESTRIAN: 1}
    walker = seq.track_id != 1
    assert np.all(seq.track_id[walker] == 1_000_000_001)
    np.testing.assert_allclose(seq.length_m[walker], 1.0)
    np.testing.assert_allclose(seq.yaw_rad[walker], 0.0, atol=1e-6)  # from the motion (east)


# --------------------------------------------------------------------------- inD format


def test_ind_fixture_loads() -> None:
    (ref,) = discover(IND_SMALL)
    assert (ref.name, ref.format) == ("01", "ind")
    assert [p.name for p in ref.ignored_files] == ["01_background.png"]
    rec = load_recording(IND_SMALL, "01", rule=RepairRule(repair_velocity=True))
    assert rec.map_path == IND_SMALL / "maps" / "01.osm"
    assert (rec.location_id, rec.frame_rate_hz) == ("4", 25.0)
    assert (rec.origin_lat_deg, rec.origin_lon_deg) == (50.78563, 6.12971)
    assert (rec.utm_origin_x_m, rec.utm_origin_y_m) == (296436.4, 5628685.0)
    assert rec.speed_limit_mps == pytest.approx(13.8889)
    (seq,) = rec.sequences
    assert seq.tracks_by_type() == {
        AgentType.CAR: 2, AgentType.TRUCK: 1, AgentType.PEDESTRIAN: 1, AgentType.BICYCLE: 1, AgentType.UNKNOWN: 1
    }
    assert seq.n_frames == 60
    np.testing.assert_array_equal(seq.stamp_ns, seq.frame_index * 40_000_000)  # 25 Hz
    # the deliberately bad rows of README.md, each with its line
    rep = rec.report
    for reason, line in (
        ("duplicate_frame", 8), ("missing_field", 23), ("non_numeric", 33), ("non_finite_position", 173), ("time_backwards", 229)
    ):
        p = rep.get(reason)
        assert p is not None and p.count == 1 and p.examples[0].line == line, reason
    assert rep.count("unknown_agent_type") == 10
    assert rep.get("yaw_from_motion").examples[0].line == 203
    assert rep.get("start_velocity_from_positions").examples[0].line == 53
    # heading degrees -> radians in (-pi, pi]
    assert seq.yaw_rad[seq.track_id == 4][0] == pytest.approx(-math.pi / 4)
    assert seq.yaw_rad[seq.track_id == 1][5] == pytest.approx(math.pi / 2)
    assert np.all(np.abs(seq.yaw_rad[seq.track_id == 3]) == pytest.approx(math.pi))
    # inD pedestrians have size 0: the default is used and counted
    np.testing.assert_allclose(seq.length_m[seq.track_id == 3], 1.0)
    assert rep.count("size_defaulted") == 59
    # frames iterate in order with views of the arrays
    frames = list(seq.frames())
    assert [f.frame_index for f in frames] == list(range(60))
    assert sum(len(f) for f in frames) == seq.n_rows
    assert np.all(np.diff(frames[0].track_id) > 0)


# --------------------------------------------------------------------------- kinematics


def test_derived_kinematics_exact_on_a_parabola() -> None:
    t = np.arange(20) * 0.1
    x = 2.0 + 3.0 * t + 0.5 * 1.5 * t**2
    y = -1.0 * t
    kin = derive_kinematics(t, x, y)
    np.testing.assert_allclose(kin.vx_mps[2:-2], 3.0 + 1.5 * t[2:-2], atol=1e-9)
    np.testing.assert_allclose(kin.vy_mps, -1.0, atol=1e-9)
    np.testing.assert_allclose(kin.ax_mps2, 1.5, atol=1e-6)
    assert np.isnan(derive_kinematics(t[:1], x[:1], y[:1]).vx_mps[0])
    np.testing.assert_allclose(derive_kinematics(t[:2], x[:2], y[:2]).vx_mps, (x[1] - x[0]) / 0.1)


def test_repair_fixes_zero_start_velocity_of_a_moving_track() -> None:
    t = np.arange(12) * 0.1
    x, y = 3.0 * t, 4.0 * t  # 5 m/s
    vx, vy = np.full(12, 3.0), np.full(12, 4.0)
    vx[:2] = vy[:2] = 0.0  # the tracker reports 0 at the start
    yaw = np.full(12, math.atan2(4.0, 3.0))
    yaw[0] = 0.0  # and a default yaw
    assert not repair_track(t, x, y, vx, vy, yaw).start_velocity.any()  # velocities only on request
    rule = RepairRule(repair_velocity=True)
    rep = repair_track(t, x, y, vx, vy, yaw, rule)
    assert rep.start_velocity.tolist() == [True, True] + [False] * 10
    np.testing.assert_allclose(rep.vx_mps, 3.0, atol=1e-9)
    np.testing.assert_allclose(rep.vy_mps, 4.0, atol=1e-9)
    assert rep.yaw_from_motion.tolist() == [True] + [False] * 11
    np.testing.assert_allclose(rep.yaw_rad, math.atan2(4.0, 3.0), atol=1e-9)
    # a standing object keeps its zero velocity; raw values elsewhere are kept
    still = repair_track(t, np.zeros(12), np.zeros(12), np.zeros(12), np.zeros(12), np.full(12, 1.0), rule)
    assert not still.start_velocity.any() and not still.yaw_from_motion.any()
    later = vx.copy()
    later[6] = 0.0  # not at the start: left alone
    assert repair_track(t, x, y, later, vy, yaw, rule).vx_mps[6] == 0.0


@needs_taf
def test_k733_zero_start_velocity_repaired_from_positions() -> None:
    rec = load_recording(TAF, K733, rule=RepairRule(repair_velocity=True))
    seq = rec.sequences[0]
    raw = [r for r in read_raw(TAF / "recorded_trackfiles" / K733 / "vehicle_tracks_000.csv") if r["track_id"] == "197"]
    assert float(raw[0]["vx"]) == 0.0 and float(raw[0]["psi_rad"]) == 0.0  # the quirk
    m = np.flatnonzero(seq.track_id == 197)
    first = m[np.argmin(seq.stamp_ns[m])]
    dx = float(raw[1]["x"]) - float(raw[0]["x"])
    dy = float(raw[1]["y"]) - float(raw[0]["y"])
    speed = math.hypot(seq.vx_mps[first], seq.vy_mps[first])
    assert 2.0 < speed < 8.0
    assert math.cos(math.atan2(seq.vy_mps[first], seq.vx_mps[first]) - math.atan2(dy, dx)) > 0.9
    assert math.cos(seq.yaw_rad[first] - math.atan2(dy, dx)) > 0.9
    assert any(e.line == 1548 for e in rec.report.get("start_velocity_from_positions").examples)


def test_repair_rule_rejects_inconsistent_thresholds() -> None:
    with pytest.raises(ValueError):
        RepairRule(zero_speed_mps=1.0, moving_speed_mps=0.5)


def test_jittered_stamps_keep_their_truth_and_accelerations():
    """The truth at t + k·step is the row within 20 ms of it, moved along the track to the exact time; exact stamps
    give their own rows, as before."""
    from stages.offline.truth import Track, future_positions, smoothed_acceleration

    rng = np.random.default_rng(0)
    t_ns = np.arange(60, dtype=np.int64) * 100_000_000
    jitter = rng.integers(-5_000_000, 5_000_001, t_ns.shape[0])
    jitter[0] = 0
    stamps = t_ns + jitter
    x = 8.0 * stamps / 1e9 + 0.5 * 1.0 * (stamps / 1e9) ** 2  # 8 m/s, accelerating at 1 m/s²
    xy = np.column_stack([x, np.zeros_like(x)])
    track = Track(stamps, xy, np.full(x.shape, 8.0), smoothed_acceleration(stamps, xy, 100_000_000, 11))
    fut = future_positions(track, 0, 400_000_000, 10)
    assert fut is not None
    t = np.arange(1, 11) * 0.4
    np.testing.assert_allclose(fut[:, 0], 8.0 * t + 0.5 * t**2, atol=0.02)
    assert np.isfinite(track.accel_mps2).sum() > 30, "the jitter does not cut the track into pieces too short to smooth"
    exact = Track(t_ns, np.column_stack([8.0 * t_ns / 1e9, np.zeros(60)]), np.full(60, 8.0), np.zeros(60))
    np.testing.assert_array_equal(future_positions(exact, 0, 400_000_000, 10), exact.xy[4:41:4])


def test_one_missing_frame_is_bridged_and_two_are_not():
    """A tracker's dropout of one frame cost the whole 4 s window of every instant before it; the truth at the missing
    time is now the line between its neighbours (200 ms apart), while a longer gap still leaves the time unknown."""
    from stages.offline.truth import Track, future_positions, future_run

    t_ns = np.arange(60, dtype=np.int64) * 100_000_000
    xy = np.column_stack([10.0 * t_ns / 1e9, np.zeros(60)])  # 10 m/s
    one = np.ones(60, dtype=bool)
    one[12] = False  # the frame at 1.2 s missing
    track = Track(t_ns[one], xy[one], np.full(59, 10.0), np.zeros(59))
    fut = future_positions(track, 0, 400_000_000, 10)
    assert fut is not None
    np.testing.assert_allclose(fut[:, 0], 10.0 * 0.4 * np.arange(1, 11), atol=1e-9)
    two = one.copy()
    two[13] = False  # 1.2 and 1.3 s missing: 300 ms between the rows around them
    gap = Track(t_ns[two], xy[two], np.full(58, 10.0), np.zeros(58))
    assert future_positions(gap, 0, 400_000_000, 10) is None
    assert future_run(gap, 0, 400_000_000, 10).shape == (2, 2)  # 0.4 and 0.8 s; 1.2 s lies in the gap
