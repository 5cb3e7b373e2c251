"""``iamp eval`` never stops on the data: what it leaves out is counted by reason, in the JSON and under the table.

Small in-process runs on the embedded K729 scenario; the failures are
stand-ins patched into the real cores (one frame of the corridors core, some
of the relations core, one instant of a predictor) and a sequence file that
cannot be read.
"""

from __future__ import annotations

import json
import shutil

import pytest

from stages import cli
from stages.corridors import CorridorBuilder
from stages.lib.datasets import DEFAULT_DATA_DIR, DEFAULT_RECORDING
from stages.offline.evaluation import EvalConfig, Evaluation, format_table
from stages.offline.report import write_report
from stages.relations import RelationExtractor

pytestmark = pytest.mark.skipif(
    not (DEFAULT_DATA_DIR / "maps").is_dir(), reason=f"embedded TAF-BW data not found at {DEFAULT_DATA_DIR}"
)

SEQUENCE = "019"  # 58 frames, up to four cars
MODES = ("cv", "corridor_cv")
FRAMES = 40
STRIDE_S = 0.8  # instants every 8th frame


def _config(**changes) -> EvalConfig:
    base = dict(recordings=(DEFAULT_RECORDING,), sequences=(SEQUENCE,), modes=MODES, stride_s=STRIDE_S,
                max_frames_per_sequence=FRAMES, progress=False)
    return EvalConfig(**{**base, **changes})


def _windows(report) -> dict[str, int]:
    return {mode: report["modes"][mode]["overall"]["windows"] for mode in MODES}


class _Failing:
    """Wraps a method: raises on the calls whose number (from 0) is in ``calls``, else calls through."""

    def __init__(self, method, calls):
        self.method, self.calls, self.n = method, set(calls), 0

    def __call__(self, *args, **kwargs):
        n, self.n = self.n, self.n + 1
        if n in self.calls:
            raise ValueError(f"stand-in failure on call {n}")
        return self.method(*args, **kwargs)


def test_core_failures_are_counted_and_the_evaluation_goes_on(monkeypatch):
    clean = Evaluation(_config()).run()
    assert clean["skipped"].get("prediction_error_corridor_cv", 0) == 0
    windows = _windows(clean)
    assert windows["cv"] == windows["corridor_cv"] > 0

    corridors = _Failing(CorridorBuilder.process, {FRAMES - 1})  # the last frame: not an instant, nothing after it
    relations = _Failing(RelationExtractor.process, {2, 5, 11})
    monkeypatch.setattr(CorridorBuilder, "process", lambda self, *a: corridors(self, *a))
    monkeypatch.setattr(RelationExtractor, "process", lambda self, *a, **k: relations(self, *a, **k))
    evaluation = Evaluation(_config())
    predictor = evaluation.predictors["corridor_cv"]
    predictor.process = _Failing(predictor.process, {1})  # the second instant
    report = evaluation.run()

    skipped = report["skipped"]
    assert skipped["corridors_error_frames"] == 1 and skipped["relations_error_frames"] == 3
    lost = skipped["prediction_error_corridor_cv"]
    assert lost > 0, "the failing instant's windows are counted"
    assert _windows(report) == {mode: n - lost for mode, n in windows.items()}, "every mode scored on the same windows"
    assert "stand-in failure on call 1" in report["skipped_examples"]["prediction_error_corridor_cv"]
    table = format_table(report)
    for reason in ("corridors_error_frames", "relations_error_frames", "prediction_error_corridor_cv", "no_full_future"):
        assert reason in table
    json.dumps(report, allow_nan=True)


def test_an_unreadable_sequence_is_skipped_and_counted(tmp_path, capsys):
    data = tmp_path / "taf-bw"
    shutil.copytree(DEFAULT_DATA_DIR, data)
    (data / "recorded_trackfiles" / DEFAULT_RECORDING / "vehicle_tracks_022.csv").write_text("")  # empty: no header row
    report = Evaluation(_config(data_dir=data, sequences=(SEQUENCE, "022"))).run()
    assert report["skipped"]["unreadable_sequences"] == 1
    assert "022" in report["skipped_examples"]["unreadable_sequences"]
    assert _windows(report)["cv"] > 0, "the readable sequence is still evaluated"

    out = tmp_path / "eval.json"
    code = cli.main(["eval", "--data", str(data), "--recording", DEFAULT_RECORDING, "--mode", "cv", "--max-frames", "20",
                     "--no-progress", "--json", str(out)])
    assert code == 0
    assert json.loads(out.read_text())["skipped"]["unreadable_sequences"] == 1
    assert "unreadable_sequences" in capsys.readouterr().out


def test_only_a_bad_command_line_or_configuration_stops_it(tmp_path, capsys):
    base = ["eval", "--recording", DEFAULT_RECORDING, "--mode", "cv", "--max-frames", "5", "--no-progress"]
    assert cli.main(base + ["--sequence", "999"]) == 2
    assert cli.main(base + ["--set", "no_such_parameter=1"]) == 2
    assert cli.main(["eval", "--data", str(tmp_path / "nothing"), "--no-progress"]) == 2
    assert cli.main(base + ["--recording", "nowhere"]) == 2
    err = capsys.readouterr().err
    assert "999" in err and "no_such_parameter" in err and "nowhere" in err
    import torch

    if not torch.cuda.is_available():  # was an AssertionError traceback from inside torch at the first frame
        assert cli.main(base + ["--mode", "baseline", "--backend", "torch", "--device", "cuda"]) == 2
        assert "no CUDA device here" in capsys.readouterr().err


def _rewrite_tracks(data, sequence: str, change) -> None:
    """Apply ``change(header, rows)`` to one sequence's track file (rows as lists of fields, in place)."""
    import csv

    path = data / "recorded_trackfiles" / DEFAULT_RECORDING / f"vehicle_tracks_{sequence}.csv"
    with path.open(newline="") as f:
        header, *body = list(csv.reader(f))
    change(header, body)
    with path.open("w", newline="") as f:
        csv.writer(f).writerows([header, *body])


def test_jittered_stamps_give_the_same_windows_and_the_loader_s_findings_are_shown(tmp_path, capsys):
    """A tracker whose stamps jitter by a few ms (not every recording has its stamps at exactly k·100 ms): with the
    truth matched within 1 ms, ±5 ms left 0 of the windows to score; one corrupt stamp (ms beyond any array of ns)
    ended the whole evaluation in an OverflowError; and what the loader skipped or repaired was never shown."""
    import random

    data = tmp_path / "taf-bw"
    shutil.copytree(DEFAULT_DATA_DIR, data)
    clean = Evaluation(_config(data_dir=data)).run()
    rng = random.Random(0)

    def jitter(header, rows):
        t, vx = header.index("timestamp_ms"), header.index("vx")
        for i, r in enumerate(rows):
            r[t] = str(int(r[t]) + rng.randint(-5, 5))
            if i % 7 == 3:
                r[vx] = ""  # an empty measured field: derived from the positions, the row kept
        rows[len(rows) // 2][t] = "99999999999999"  # one corrupt stamp

    _rewrite_tracks(data, SEQUENCE, jitter)
    report = Evaluation(_config(data_dir=data)).run()
    assert _windows(report)["cv"] >= _windows(clean)["cv"] - 3 > 0, (_windows(report), _windows(clean))
    for mode in MODES:
        assert report["modes"][mode]["overall"]["mADE_m"] == pytest.approx(clean["modes"][mode]["overall"]["mADE_m"], rel=0.1)
    problems = report["load_report"][DEFAULT_RECORDING]["problems"]
    assert problems["time_out_of_range"]["count"] == 1 and problems["time_out_of_range"]["action"] == "skipped"
    assert problems["velocity_nan_from_positions"]["count"] > 0 and "missing_field" not in problems
    table = format_table(report)
    assert "time_out_of_range" in table and "what the loader found" in table
    assert "load_report" in clean and not clean["load_report"][DEFAULT_RECORDING]["problems"].get("time_out_of_range")


def test_a_recording_without_its_map_is_counted_and_the_others_are_evaluated(tmp_path):
    """One recording of a data folder without `maps/<name>.osm` ended `iamp eval` with exit 2, the others unscored."""
    data = tmp_path / "taf-bw"
    shutil.copytree(DEFAULT_DATA_DIR, data)
    shutil.copytree(data / "recorded_trackfiles" / DEFAULT_RECORDING, data / "recorded_trackfiles" / "k729_copy")
    report = Evaluation(_config(data_dir=data, recordings=(DEFAULT_RECORDING, "k729_copy"))).run()
    assert report["skipped"]["recordings_without_map"] == 1 and "k729_copy" in report["skipped_examples"]["recordings_without_map"]
    assert report["recordings"] == [DEFAULT_RECORDING] and _windows(report)["cv"] > 0
    with pytest.raises(ValueError, match="k729_copy has no map"):  # alone: the command line named the wrong data
        Evaluation(_config(data_dir=data, recordings=("k729_copy",))).run()


def test_calibrate_with_no_window_writes_nothing_and_says_why(tmp_path, capsys):
    """With no window (a header-only track file) `iamp calibrate` wrote a table of σ 0, which makes every grid a
    point, and exited 0."""
    data = tmp_path / "taf-bw"
    shutil.copytree(DEFAULT_DATA_DIR, data)
    path = data / "recorded_trackfiles" / DEFAULT_RECORDING / f"vehicle_tracks_{SEQUENCE}.csv"
    path.write_text(path.read_text().splitlines()[0] + "\n")  # the header only
    out = tmp_path / "spread.json"
    code = cli.main(["calibrate", "--data", str(data), "--recording", DEFAULT_RECORDING, "--sequence", SEQUENCE, "--mode", "cv",
                     "--out", str(out), "--no-progress"])
    assert code == 2 and not out.exists()
    assert "no window to fit the spread on (unreadable_sequences 1)" in capsys.readouterr().err


def test_what_the_stages_flag_is_counted_in_the_report(tmp_path):
    """A track id that two cars use at once (a tracker's re-used id) makes the corridors stage restart the track at
    each jump; on the bus that is counted in NodeStats, and `iamp eval` now counts it too (it showed nothing)."""
    data = tmp_path / "taf-bw"
    shutil.copytree(DEFAULT_DATA_DIR, data)

    def clash(header, rows):
        tid, x, t = header.index("track_id"), header.index("x"), header.index("timestamp_ms")
        first, second = "5711", "5720"  # two cars of the sequence, both there from 1.3 s to 4.4 s
        moved = set()
        for i, r in enumerate(rows):  # the second car's rows moved 40 m and given the first car's id
            if r[tid] == second:
                r[tid], r[x] = first, str(float(r[x]) + 40.0)
                moved.add(i)
        # in time order, the two cars' rows of a frame in turns first (the loader keeps the first row of a track and frame)
        order = sorted(range(len(rows)), key=lambda i: (int(rows[i][t]), (i in moved) == (int(rows[i][t]) // 100 % 2 == 0)))
        rows[:] = [rows[i] for i in order]

        rows[len(rows) // 2][t] = "99999999999999"  # and one corrupt stamp: a row the loader leaves out

    _rewrite_tracks(data, SEQUENCE, clash)
    evaluation = Evaluation(_config(data_dir=data))
    report = evaluation.run()
    issues = report["stage_issues"]
    assert issues.get("corridors:position_jump", {}).get("count", 0) > 0, issues
    assert "corridors:position_jump" in format_table(report)
    # the report (`iamp eval --report`) shows both, and every reason it skipped has its first occurrence
    text = write_report(evaluation, report, tmp_path / "rep", "iamp eval ...", formats=("png",), dpi=20).read_text()
    assert f"| {DEFAULT_RECORDING} | skipped | time_out_of_range | 1 | " in text
    assert f"| corridors:position_jump | {issues['corridors:position_jump']['count']:,} | agent " in text
    skipped = text[text.index("| reason | count | first occurrence |"):].splitlines()[2:]
    skipped = skipped[: next(i for i, line in enumerate(skipped) if not line.startswith("|"))]
    assert {line.split(" | ")[0].strip("| ") for line in skipped} == set(report["skipped"]) >= {"no_full_future"}
    assert all(line.rstrip(" |").split(" | ")[-1].strip() for line in skipped), "a reason without its first occurrence"
    assert "stamp_ns" in report["skipped_examples"]["no_full_future"]
