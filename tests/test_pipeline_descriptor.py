"""Pipeline descriptors: good and bad fixture files, with the exact error text."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from stages.runtime.pipeline import PipelineError, load_pipeline

REPO = Path(__file__).resolve().parents[1]
FIX = REPO / "tests" / "fixtures" / "pipelines"


def test_good_fixture_resolves_vars_and_ports():
    p = load_pipeline(FIX / "good.toml")
    assert p.run_id == "fixture"
    src = p.node("source")
    assert src.config.speed == 2.0  # "${SPEED}" took the variable's type
    assert [n.id for n in p.topo_order()] == ["source", "recorder"]
    assert p.output_key("source", "track_frame") == "iamp/fixture/source/track_frame"


def test_a_variable_from_the_command_line_replaces_the_file_s_and_a_misspelt_one_stops_the_load():
    assert load_pipeline(FIX / "good.toml", variables={"SPEED": 3.0}).node("source").config.speed == 3.0
    # a --var the pipeline neither declares nor uses would be ignored: a run without the model (MODLE=...) the user meant
    with pytest.raises(PipelineError, match=r"good.toml: no variable SPEDE in this pipeline \(--var\); its variables: SPEED$"):
        load_pipeline(FIX / "good.toml", variables={"SPEDE": 3.0})
    r = subprocess.run([sys.executable, str(REPO / "launch.py"), "--var", "MODLE=weights.pt", "--check"], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 2
    assert "hybrid.toml: no variable MODLE in this pipeline (--var); its variables: MODEL, SPEED" in r.stderr


def test_overrides_apply_and_are_type_checked():
    p = load_pipeline(FIX / "good.toml", overrides={"source": {"speed": "max"}})
    assert p.node("source").config.speed == "max"
    with pytest.raises(PipelineError, match=r"node source: parameter speed = \[1\] should be float \| str"):
        load_pipeline(FIX / "good.toml", overrides={"source": {"speed": [1]}})
    with pytest.raises(PipelineError) as ei:
        load_pipeline(FIX / "good.toml", overrides={"nosuch": {"a": 1}})
    assert "--set names unknown node(s) nosuch; nodes: source, recorder" in str(ei.value)


@pytest.mark.parametrize(
    "name, message",
    [
        ("unknown_stage.toml", "node source: unknown stage 'stages.no_such_stage'"),
        ("unknown_param.toml", "node source: unknown parameter(s) sped; known: "),
        ("duplicate_id.toml", "node source: duplicate node id 'source'"),
        ("unknown_var.toml", "unknown variable ${FAST}; defined: (none)"),
        ("unknown_node_key.toml", "node source: unknown key(s) parms; known: "),
    ],
)
def test_bad_fixtures_name_node_and_problem(name, message):
    with pytest.raises(PipelineError) as ei:
        load_pipeline(FIX / name)
    assert message in str(ei.value)
    assert str(FIX / name) in str(ei.value)


def _write(tmp_path: Path, text: str) -> Path:
    f = tmp_path / "p.toml"
    f.write_text(text)
    return f


def test_input_bound_to_missing_node_or_output_or_other_schema(tmp_path):
    base = '[[nodes]]\nid = "source"\nstage = "stages.tracks_source"\n[[nodes]]\nid = "corridors"\nstage = "stages.corridors"\n'
    f = _write(tmp_path, base + 'inputs = { track_frame = "src/track_frame", scene = "source/scene" }\n')
    with pytest.raises(PipelineError, match=r"node corridors: input track_frame = 'src/track_frame': does node 'src' exist\? nodes: source, corridors"):
        load_pipeline(f)
    f = _write(tmp_path, base + 'inputs = { track_frame = "source/frames", scene = "source/scene" }\n')
    with pytest.raises(PipelineError, match=r"does node source declare output 'frames'\? it has: scene, track_frame"):
        load_pipeline(f)
    f = _write(tmp_path, base + 'inputs = { track_frame = "source/scene", scene = "source/scene" }\n')
    with pytest.raises(PipelineError, match=r"node corridors: input track_frame wants iamp.TrackFrame but source/scene carries iamp.SceneInfo"):
        load_pipeline(f)
    f = _write(tmp_path, base + 'inputs = { scene = "source/scene" }\n')
    with pytest.raises(PipelineError, match=r"node corridors: input port\(s\) track_frame not connected"):
        load_pipeline(f)
    f = _write(tmp_path, base + 'inputs = { frames = "source/track_frame" }\n')
    with pytest.raises(PipelineError, match=r"stage stages.corridors has no input port 'frames'"):
        load_pipeline(f)


def test_external_outputs_are_declared_with_their_schema(tmp_path):
    f = _write(
        tmp_path,
        '[external]\n"tracker/track_frame" = "iamp.SceneInfo"\n"tracker/scene" = "iamp.SceneInfo"\n'
        '[[nodes]]\nid = "corridors"\nstage = "stages.corridors"\ninputs = { track_frame = "tracker/track_frame", scene = "tracker/scene" }\n',
    )
    with pytest.raises(PipelineError, match="wants iamp.TrackFrame but external tracker/track_frame carries iamp.SceneInfo"):
        load_pipeline(f)


@pytest.mark.parametrize("pipeline", sorted((REPO / "stages" / "pipelines").glob("*.toml")), ids=lambda p: p.name)
def test_shipped_pipelines_are_valid(pipeline, tmp_path, capsys):
    """``launch.py PIPELINE --check`` of every shipped pipeline, in process (the launcher's own exit codes through a
    process are test_launcher_check_and_describe_exit_codes's)."""
    from stages.runtime.launcher import main

    extra = []
    if pipeline.name == "replay.toml":  # --check also checks that the file to replay is a recording
        from stages.recorder import McapRecorder, RecorderConfig

        rec = tmp_path / "run.mcap"
        with McapRecorder(RecorderConfig(path=str(rec)), "t1") as r:
            r.handle("iamp/t1/source/scene", b"not an envelope", 1)  # recorded without schema: a recording all the same
        extra = ["--var", f"FILE={rec}"]
    code = main([str(pipeline), "--check", *extra])
    out, err = capsys.readouterr()
    assert code == 0, err + out
    assert "is valid" in out


@pytest.mark.parametrize("name, n", [("sharded", 2), ("sharded4", 4)])
def test_sharded_pipelines_cover_every_shard_once_and_fuse_them_all(name, n):
    pipeline = load_pipeline(REPO / "stages" / "pipelines" / f"{name}.toml")
    shards = {d.id: d.params["shard"] for d in pipeline.nodes if d.stage == "stages.markov_prediction"}
    assert sorted(shards.values()) == sorted(f"{i}/{n}" for i in range(n))
    fusion = pipeline.node("grid_fusion").inputs
    assert {fusion[f"grid_{i}"].split("/")[0] for i in range(n)} == set(shards)
    assert {fusion[f"predictions_{i}"].split("/")[0] for i in range(n)} == set(shards)
    shard_of = {v: k for k, v in shards.items()}
    for i in range(n):  # grid_i and predictions_i come from the same shard
        assert fusion[f"grid_{i}"].split("/")[0] == fusion[f"predictions_{i}"].split("/")[0]
    assert all(d.queue_size == 16 for d in pipeline.nodes if d.id in shard_of.values())


def test_launcher_check_and_describe_exit_codes():
    r = subprocess.run([sys.executable, str(REPO / "launch.py"), str(FIX / "unknown_param.toml"), "--check"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    assert "unknown parameter(s) sped" in r.stderr
    r = subprocess.run([sys.executable, str(REPO / "launch.py"), str(FIX / "good.toml"), "--describe"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "out track_frame    -> iamp/fixture/source/track_frame  [iamp.TrackFrame v2]" in r.stdout
    r = subprocess.run([sys.executable, str(REPO / "launch.py"), "--stop-after", "0", "--check"], capture_output=True, text=True, timeout=120)
    assert r.returncode in (0, 2)
    r = subprocess.run([sys.executable, str(REPO / "launch.py"), "no/such/file.toml"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "pipeline file no/such/file.toml does not exist" in r.stderr


def test_ar_inference_and_markov_prediction_must_share_the_input_cells():
    hybrid = Path(__file__).resolve().parents[1] / "stages" / "pipelines" / "hybrid.toml"
    with pytest.raises(PipelineError, match=r"markov_prediction: input acceleration_profiles.*n_inputs = 12 here but 10 in ar_inference"):
        load_pipeline(hybrid, overrides={"markov_prediction": {"n_inputs": 12}})
    p = load_pipeline(hybrid, overrides={"markov_prediction": {"n_inputs": 12, "input_max_mps2": 3.0},
                                         "ar_inference": {"n_inputs": 12, "input_max_mps2": 3.0}})
    ar = p.node("ar_inference").config
    assert p.node("markov_prediction").config.input_cells() == {k: getattr(ar, k) for k in ("input_min_mps2", "input_max_mps2", "n_inputs")} == {
        "input_min_mps2": -3.0, "input_max_mps2": 3.0, "n_inputs": 12}


def test_grids_are_calibrated_by_default_and_raw_on_request(capsys):
    """Every markov_prediction node (the two shards of ``sharded`` too) makes calibrated grids by default (the shipped
    spread table and the online spread); ``launch.py --raw-grids`` turns both off on every one, ``--calibrated-grids``
    names the default for a pipeline file that sets otherwise, a ``--set`` of either key still wins, the two flags
    exclude each other, and a pipeline without the stage is a usage error. The stage's configs are the ones
    validated, so a key the stage did not know would fail here."""
    from stages.runtime.launcher import build_parser, main, make_editor

    def markov(name: str, *flags: str) -> dict:
        args = build_parser().parse_args([name, *flags, "--no-record"])
        pipeline = load_pipeline(REPO / "stages" / "pipelines" / f"{name}.toml", edit=make_editor(args))
        return {n.id: n.config for n in pipeline.nodes if n.stage == "stages.markov_prediction"}

    for name, nodes in (("hybrid", {"markov_prediction"}), ("sharded", {"markov_0", "markov_1"})):
        for flags in ((), ("--calibrated-grids",)):
            found = markov(name, *flags)
            assert set(found) == nodes and all(c.spread_calibration == "shipped" and c.spread_online for c in found.values())
        raw = markov(name, "--raw-grids")
        assert set(raw) == nodes and all(c.spread_calibration == "" and not c.spread_online for c in raw.values())
    assert main(["--raw-grids", "--set", "markov_prediction.spread_online=true", "--describe"]) == 0
    out = capsys.readouterr().out
    assert '"spread_calibration": "", "spread_online": true' in out
    with pytest.raises(SystemExit) as stop:
        build_parser().parse_args(["--raw-grids", "--calibrated-grids"])
    assert stop.value.code == 2 and "not allowed with argument" in capsys.readouterr().err
    for flag in ("--calibrated-grids", "--raw-grids"):
        assert main(["replay", "--var", "FILE=/nonexistent.mcap", flag, "--check"]) == 2
        assert f"{flag}: the pipeline has no markov_prediction node" in capsys.readouterr().err


def test_shipped_pipelines_with_a_dataset_source_play_the_default_pipelines_recording():
    """sharded and sharded4 played the dataset player's own default (K729) while hybrid.toml, the default pipeline, plays
    K733; live.toml's stand-in tracker command did too. baseline.toml says in its first line that it plays K729."""
    pipelines = REPO / "stages" / "pipelines"
    default = load_pipeline(pipelines / "hybrid.toml").node("source").params["recording"]
    assert default == "k733_2018-05-02"
    for name in ("sharded", "sharded4", "compare", "inline", "pipelined"):
        sources = [n for n in load_pipeline(pipelines / f"{name}.toml").nodes if n.stage == "stages.tracks_source"]
        assert [n.params.get("recording") for n in sources] == [default], name
    stand_in = [line for line in (pipelines / "live.toml").read_text().splitlines() if "-m stages.tracks_source" in line]
    assert stand_in and all(f"--set recording={default}" in line for line in stand_in), stand_in


def test_the_launcher_says_how_many_recorded_frames_got_a_motion_grid():
    """A 12-minute soak at 4x lost 15.7 % of its frames to markov_prediction's queue; the launcher exited 0 saying
    nothing of it, and `iamp inspect` only checks the track frames' continuity."""
    from stages.runtime.launcher import predicted_line

    counts = {"iamp/r/source/track_frame": 200, "iamp/r/source/scene": 1, "iamp/r/hybrid/motion_grid": 150, "iamp/r/baseline/motion_grid": 200}
    assert predicted_line(counts) == ("predicted: 200 track frames recorded, MotionGrids of baseline 200 (100.0%), hybrid 150 (75.0%);"
                                      " up to 50 frames without one: the nodes' queue_drops, stale_drops and join_drops above say where,"
                                      " or a node that restarted or lost its inputs (its 'restarting' and 'no input for' lines)")
    fused = predicted_line({"iamp/r/source/track_frame": 10, "iamp/r/grid_fusion/motion_grid": 10, "iamp/r/markov_0/motion_grid": 10})
    assert fused.endswith("; grid_fusion publishes a frame with a shard missing too: its shard_missing says how many")
    assert predicted_line({"iamp/r/source/track_frame": 10, "iamp/r/markov_prediction/motion_grid": 10}).endswith("markov_prediction 10 (100.0%)")
    assert predicted_line({"iamp/r/source/scene": 1}) == "" and predicted_line({"iamp/r/source/track_frame": 5}) == ""


def test_check_refuses_a_model_that_is_no_whole_weights_file(tmp_path, capsys):
    """`launch.py --check --var MODEL=trunc.pt` said the pipeline was valid; the node then failed at start."""
    from stages.runtime.launcher import main

    shipped = REPO / "stages" / "lib" / "ar" / "weights" / "ar_taf_bw.pt"
    cut = tmp_path / "cut.pt"
    cut.write_bytes(shipped.read_bytes()[:2000])
    for model, says in ((cut, "not a whole weights file"), (tmp_path, "is a folder"), (tmp_path / "none.pt", "no such weights file")):
        assert main(["--check", "--var", f"MODEL={model}"]) == 2
        assert f"node ar_inference: model = '{model}': {says}" in capsys.readouterr().err
    assert main(["--check", "--var", f"MODEL={shipped}"]) == 0


def test_the_live_pipeline_bounds_its_stages_inputs_in_age_and_max_age_s_is_checked(tmp_path):
    """A live tracker's frames come whether or not the stages keep up (a probe's 200 vehicles fell 14 s behind):
    live.toml gives every processing stage ``max_age_s``, which reaches the stage as ``--max-age-s``; the replay and
    dataset pipelines, which count every frame, have none. A bad value, or one on a node that is not a processing
    stage, stops the load naming the node."""
    from stages.runtime import launcher

    live = load_pipeline(REPO / "stages" / "pipelines" / "live.toml")
    processing = ("corridors", "relations", "intentions", "ar_inference", "markov_prediction")
    assert {n.id: n.max_age_s for n in live.nodes if n.max_age_s} == dict.fromkeys(processing, 0.5)
    run = launcher.Launcher(live, "tcp/127.0.0.1:1", launcher.build_parser().parse_args(["live", "--no-viewer"]))
    for node in live.nodes:
        cmd = run.command(node)
        assert (cmd[cmd.index("--max-age-s") + 1] == "0.5") if node.id in processing else "--max-age-s" not in cmd, node.id
    assert "max_age_s=0.5" in live.describe()
    assert not any(n.max_age_s for n in load_pipeline(REPO / "stages" / "pipelines" / "replay.toml").nodes)
    # the dataset pipelines too, at real time (a new user's probe: at 72 vehicles the stages upstream of
    # markov_prediction fell 7-13 s behind through their 256-frame queues, its joins of a frame's inputs timed out, and 4 %
    # of the frames got a grid); at --speed max (paced by the acks) every frame is handled, none skipped for its age
    for name in ("hybrid", "baseline", "inline", "pipelined", "compare", "sharded", "sharded4"):
        path = REPO / "stages" / "pipelines" / f"{name}.toml"
        nodes = load_pipeline(path).nodes
        assert {n.id for n in nodes if n.max_age_s == 0.5} == {n.id for n in nodes if n.stage in {
            f"stages.{s}" for s in processing + ("markov_prediction",)}}, name
        for speed, bounded in ((None, True), ("4", True), ("max", False)):
            ns = launcher.build_parser().parse_args([name] + (["--speed", speed] if speed else []))
            p = load_pipeline(path, edit=launcher.make_editor(ns))
            run = launcher.Launcher(p, "tcp/127.0.0.1:1", ns)
            assert any("--max-age-s" in run.command(n) for n in p.nodes) == bounded, (name, speed)
    base = '[[nodes]]\nid = "source"\nstage = "stages.tracks_source"\n[[nodes]]\nid = "corridors"\nstage = "stages.corridors"\n' \
           'inputs = { track_frame = "source/track_frame", scene = "source/scene" }\n'
    for value in ("0", "-1.5", '"fast"', "nan"):
        with pytest.raises(PipelineError, match=r"node corridors: 'max_age_s' must be a number of seconds > 0"):
            load_pipeline(_write(tmp_path, base + f"max_age_s = {value}\n"))
    with pytest.raises(PipelineError, match=r"node recorder: 'max_age_s' applies to processing stages only \(stage stages.recorder is a raw_sink\)"):
        load_pipeline(_write(tmp_path, base + '[[nodes]]\nid = "recorder"\nstage = "stages.recorder"\nmax_age_s = 1.0\n'))


SHARDED = (REPO / "stages" / "pipelines" / "sharded.toml").read_text()


@pytest.mark.parametrize("old, new, message", [
    # a copy-paste slip: two shards "0/2" ran with half the vehicles never predicted, every line of the run clean
    ('shard = "1/2"', 'shard = "0/2"', r'node grid_fusion: grid_1 comes from markov_1, whose shard is "0/2": bind shard i'),
    ('shard = "0/2"', 'shard = "0/3"', r"node grid_fusion: its shards count 2 and 3 shards in all: give them one n"),
    (', grid_1 = "markov_1/motion_grid", predictions_1 = "markov_1/corridor_predictions"', "",
     r"node grid_fusion: shard\(s\) 1/2 not bound \(grid_i, predictions_i\): the vehicles of a shard not bound are never predicted"),
    ('predictions_1 = "markov_1/corridor_predictions"', 'predictions_1 = "markov_0/corridor_predictions"',
     r"node grid_fusion: grid_1 and predictions_1 come from markov_0 and markov_1: bind both to one shard's outputs"),
    ('params = { mode = "hybrid", corridor_weights = "intentions", shard = "1/2" }',
     'params = { mode = "baseline", corridor_weights = "intentions", shard = "1/2" }',
     r"node grid_fusion: shards markov_0 and markov_1 differ in .*mode .*'hybrid' / 'baseline'.*: the shards of one grid must be alike"),
    ('shard = "1/2"', 'shard = ""', r'node grid_fusion: grid_1 comes from markov_1, which has no shard: set shard = "1/N" on it'),
])
def test_shards_of_one_grid_add_up_to_every_vehicle_once(tmp_path, old, new, message):
    """Found by a new-user probe: these sharding slips passed ``--check`` and ran without a warning anywhere."""
    assert old in SHARDED
    with pytest.raises(PipelineError, match=message):
        load_pipeline(_write(tmp_path, SHARDED.replace(old, new, 1)))


def test_a_shard_run_elsewhere_counts_by_its_port(tmp_path):
    """A shard the pipeline does not start (``[external]``, README "Spreading stages over machines") is known only by
    the ports it is bound to: the local ones are checked, and the external one fills its index."""
    start = SHARDED.index('[[nodes]]\nid = "markov_1"')
    end = SHARDED.index("[[nodes]]", start + 1)
    text = SHARDED[:start] + SHARDED[end:]
    text = text.replace("[bus]", '[external]\n"markov_1/motion_grid" = "iamp.MotionGrid"\n'
                                 '"markov_1/corridor_predictions" = "iamp.CorridorPredictions"\n\n[bus]', 1)
    assert len(load_pipeline(_write(tmp_path, text)).nodes) == 9
    with pytest.raises(PipelineError, match=r'grid_0 comes from markov_0, whose shard is "1/2"'):  # the external one's index
        load_pipeline(_write(tmp_path, text.replace('shard = "0/2"', 'shard = "1/2"')))
    with pytest.raises(PipelineError, match=r"grid_2 comes from markov_0, a shard of 2: 2 shards go on grid_0 .. grid_1"):
        load_pipeline(_write(tmp_path, text.replace('grid_0 = "markov_0/motion_grid", predictions_0 = "markov_0/corridor_predictions"',
                                                    'grid_2 = "markov_0/motion_grid", predictions_2 = "markov_0/corridor_predictions"')))


def test_shards_may_differ_in_how_they_run(tmp_path):
    """Threads (and backend, device) say how a shard runs, not what it predicts: a shard on a bigger machine may use more."""
    text = SHARDED.replace('shard = "1/2" }', 'shard = "1/2", kernel_threads = 4 }', 1)
    assert "kernel_threads = 4" in text
    assert load_pipeline(_write(tmp_path, text)).node("markov_1").config.kernel_threads == 4


def test_observers_run_at_a_lower_cpu_priority_and_nice_is_checked(tmp_path):
    """The viewer and the Foxglove bridge decode and draw every frame; on 2 cores at 18 vehicles the viewer alone, with
    no page open, cost the MotionGrid about 4 ms at p50 (bench/e2e_latency.py --viewer). Their stages default to
    ``nice = 10`` (``StageSpec.nice_default``), which reaches the node as ``--nice`` and lowers the priority of the
    process itself, so they take CPU the prediction stages leave; a pipeline's ``nice`` overrides it, and a bad value
    stops the load naming the node."""
    from stages.runtime import launcher

    hybrid = load_pipeline(REPO / "stages" / "pipelines" / "hybrid.toml")
    assert {n.id: n.nice for n in hybrid.nodes if n.nice} == {"viewer": 10}
    assert "nice=10" in hybrid.describe()
    run = launcher.Launcher(hybrid, "tcp/127.0.0.1:1", launcher.build_parser().parse_args(["hybrid"]))
    for node in hybrid.nodes:
        cmd = run.command(node)
        assert cmd[cmd.index("--nice") + 1] == ("10" if node.id == "viewer" else "0"), node.id
    base = '[[nodes]]\nid = "source"\nstage = "stages.tracks_source"\n[[nodes]]\nid = "viewer"\nstage = "stages.viewer"\n' \
           'inputs = { track_frame = "source/track_frame", scene = "source/scene" }\n'
    assert load_pipeline(_write(tmp_path, base + "nice = 0\n")).node("viewer").nice == 0
    assert load_pipeline(_write(tmp_path, base + "nice = 19\n")).node("viewer").nice == 19
    for value in ("-1", "20", "2.5", '"low"', "true"):
        with pytest.raises(PipelineError, match=r"node viewer: 'nice' must be an integer from 0 \(as started\) to 19"):
            load_pipeline(_write(tmp_path, base + f"nice = {value}\n"))
    # the node applies it to its own process, before any thread starts (checked in a child: niceness only goes up)
    code = ("import os; from stages.viewer.__main__ import SPEC; from stages.runtime.args import start_stage; "
            "before = os.nice(0); start = start_stage(SPEC, {argv!r}, bindings=False); print(before, os.nice(0))")
    for argv, want in (([], 10), (["--nice", "3"], 3), (["--nice", "0"], 0)):
        out = subprocess.run([sys.executable, "-c", code.format(argv=argv)], cwd=REPO, capture_output=True, text=True, timeout=120)
        before, after = map(int, out.stdout.split())
        assert after - before == want, (argv, out.stdout, out.stderr[-2000:])
    bad = subprocess.run([sys.executable, "-m", "stages.viewer", "--nice", "20"], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "--nice 20: must be 0 (as started) to 19" in bad.stdout + bad.stderr


@pytest.mark.parametrize("sets, message", [
    (["markov_prediction.n_steps=12"], "a table for n_steps = 10; fit one for 12 steps with `iamp calibrate`, or set spread_calibration"),
    (["markov_prediction.backend=\"torch\"", "markov_prediction.device=\"cuda\""], "node markov_prediction: device = 'cuda': no CUDA device here"),
    (["markov_prediction.backend=\"cuda\""], "node markov_prediction: backend = 'cuda': "),
    (["ar_inference.device=\"cuda\""], "node ar_inference: device = 'cuda': no CUDA device here"),
])
def test_check_refuses_what_would_stop_a_node_at_its_start(sets, message):
    """``launch.py --check`` called these valid, and the node stopped at its start seconds later (a new user's probe):
    a horizon the shipped spread table was not fitted for, and a GPU on a machine without one."""
    import torch

    if "cuda" in " ".join(sets) and torch.cuda.is_available():
        pytest.skip("a CUDA device is here")
    r = subprocess.run([sys.executable, str(REPO / "launch.py"), "--check", *(a for s in sets for a in ("--set", s))],
                       cwd=REPO, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and message in r.stderr, r.stdout + r.stderr
