"""The runtime's own flags are a command line like any other: a bad one gives one "bad configuration" line (or a
usage error) and exit 2, for a stage, a tool and the launcher.

- A zenoh ``--config`` file zenoh cannot read, or an endpoint it refuses: before, a stage crashed (exit 1) with
  zenoh's traceback and then a second one from its shutdown (no stats publisher), and the launcher ended in a
  traceback.
- ``--queue-size``, ``--queue-mib``, ``--stamp-window-s``, ``--stats-period`` out of range, and ``--log-level``
  not one of logging's: before, taken as given (an unknown level silently meant INFO)."""

from __future__ import annotations

import re

import subprocess
import sys
from pathlib import Path

import pytest

from stages.lib.base import ConfigError
from stages.runtime import make_zenoh_config, open_session
from testkit.helpers import REPO, python_env

BAD_ENDPOINT = "tcp/999.1.1.1:80"  # no such address: zenoh refuses to listen on it


@pytest.fixture
def bad_config(tmp_path) -> Path:
    path = tmp_path / "zenoh.json5"
    path.write_text('{ mode: "hybrid" }\n')  # valid JSON5, not a zenoh mode
    return path


def test_make_zenoh_config_and_open_session_raise_config_errors(bad_config, tmp_path):
    with pytest.raises(ConfigError, match=r"^--config .*zenoh.json5: not a zenoh configuration zenoh can read: "):
        make_zenoh_config(config_file=str(bad_config))
    with pytest.raises(ConfigError, match=r"^--config .*missing.json5: not a zenoh configuration zenoh can read: "):
        make_zenoh_config(config_file=str(tmp_path / "missing.json5"))
    with pytest.raises(ConfigError, match=r"^cannot open the zenoh session \(mode peer, listen \['tcp/999.1.1.1:80'\]"):
        open_session(listen=[BAD_ENDPOINT])
    # an endpoint zenoh cannot even parse (a typo of the hub's address) was a zenoh traceback from the config
    for flag, kwargs in (("--listen", {"listen": ["garbage"]}), ("--connect", {"connect": ["127.0.0.1:7447"]})):
        with pytest.raises(ConfigError, match=rf"^{flag} \S+: not a zenoh endpoint \(expected <protocol>/<address>:<port>"):
            open_session(**kwargs)


@pytest.mark.parametrize("flag", ["config", "listen"])
def test_a_stage_with_a_bad_zenoh_config_or_endpoint_exits_2_with_one_line(flag, bad_config):
    extra = ["--config", str(bad_config)] if flag == "config" else ["--listen", BAD_ENDPOINT]
    done = subprocess.run([sys.executable, str(REPO / "tests" / "integration" / "echo_stage.py"), "--node-id", "echo", "--run-id", "badnet",
                           "--input", "profiles=src/profiles", *extra], cwd=REPO, env=python_env(), capture_output=True, text=True, timeout=120)
    out = done.stdout + done.stderr
    assert done.returncode == 2, out
    assert "bad configuration: " + ("--config " if flag == "config" else "cannot open the zenoh session") in out
    assert "Traceback" not in out and "AttributeError" not in out, out


@pytest.mark.parametrize("endpoint, message", [(BAD_ENDPOINT, "cannot open the zenoh session"), ("garbage", "--listen garbage: not a zenoh endpoint")])
def test_the_launcher_with_a_bad_hub_endpoint_exits_2_with_one_line(endpoint, message):
    done = subprocess.run([sys.executable, str(REPO / "launch.py"), "--listen", endpoint, "--no-viewer", "--stop-after", "1"], cwd=REPO,
                          env=python_env(), capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr
    assert f"launch.py: {message}" in done.stderr and "Traceback" not in done.stderr, done.stderr


@pytest.mark.parametrize("flags, message", [
    (["--queue-size", "0"], "--queue-size 0: must be >= 1"),
    (["--queue-mib", "nan"], "--queue-mib nan: must be a finite number > 0"),
    (["--stats-period", "0"], "--stats-period 0.0: must be a finite number > 0"),
    (["--stamp-window-s", "-1"], "--stamp-window-s -1.0: must be a finite number > 0"),
    (["--max-age-s", "-0.5"], "--max-age-s -0.5: must be a finite number >= 0 (0: inputs are not bounded in age)"),
    (["--max-age-s", "inf"], "--max-age-s inf: must be a finite number >= 0 (0: inputs are not bounded in age)"),
])
def test_the_runtime_s_numeric_flags_are_checked(flags, message):
    """Out of range they were taken as given: a queue of 0 or fewer messages, NodeStats on every loop (period 0)."""
    from stages.runtime.args import build_parser, check_runtime_args
    from tests.integration.echo_stage import SPEC

    parser = build_parser(SPEC)
    check_runtime_args(parser.parse_args([]))  # the defaults pass
    with pytest.raises(ConfigError, match="^" + re.escape(message) + "$"):
        check_runtime_args(parser.parse_args(flags))


def test_a_stage_s_log_level_is_one_of_logging_s_and_a_bad_one_is_a_usage_error():
    """An unknown level used to fall back to INFO without a word."""
    from stages.runtime.args import build_parser
    from tests.integration.echo_stage import SPEC

    parser = build_parser(SPEC)
    assert parser.parse_args(["--log-level", "debug"]).log_level == "DEBUG"
    done = subprocess.run([sys.executable, str(REPO / "tests" / "integration" / "echo_stage.py"), "--node-id", "echo", "--run-id", "badnet",
                           "--input", "profiles=src/profiles", "--queue-size", "0"], cwd=REPO, env=python_env(), capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 2 and "bad configuration: --queue-size 0: must be >= 1" in done.stderr, done.stderr
    done = subprocess.run([sys.executable, str(REPO / "launch.py"), "--log-level", "verbose", "--check"], cwd=REPO, env=python_env(),
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and "argument --log-level: invalid choice: 'VERBOSE'" in done.stderr, done.stderr


def test_the_launcher_s_time_flags_must_be_finite_and_positive():
    """``--stop-after nan`` used to run without end (no comparison with NaN is true) and ``--startup-timeout -1`` to
    end the run at once as if no node had come up."""
    cases = {
        ("--stop-after", "nan"): "--stop-after nan: must be a finite number of seconds > 0",
        ("--stop-after", "0"): "--stop-after 0.0: must be a finite number of seconds > 0",
        ("--startup-timeout", "-1"): "--startup-timeout -1.0: must be a finite number of seconds > 0",
        ("--restart-reset-s", "nan"): "--max-restarts and --restart-reset-s must be >= 0 (and finite)",
    }
    procs = {flags: subprocess.Popen([sys.executable, str(REPO / "launch.py"), *flags, "--no-viewer"], cwd=REPO, env=python_env(),
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for flags in cases}
    for flags, proc in procs.items():
        _, err = proc.communicate(timeout=120)
        assert proc.returncode == 2 and f"launch.py: {cases[flags]}" in err, (flags, err)


def test_a_node_that_fails_at_start_stops_the_run_without_tracebacks_from_the_others(tmp_path):
    """The launcher stops the nodes that have not come up yet (still importing) with SIGTERM, not SIGINT: SIGINT made
    each of them print a KeyboardInterrupt traceback from the module it was importing, pages below the one line that
    said what was wrong."""
    # (a recorder path that cannot be written no longer starts any node: the launcher's preflight refuses it, below;
    # nor a missing ar_inference model or spread table: preflight too. A weights file that is a whole zip archive but
    # no model passes preflight and fails in the node's start)
    import zipfile

    bad = tmp_path / "not_a_model.pt"
    with zipfile.ZipFile(bad, "w") as z:
        z.writestr("hello.txt", "a zip archive, not weights")
    done = subprocess.run([sys.executable, str(REPO / "launch.py"), "--set", f'ar_inference.model="{bad}"',
                           "--no-viewer", "--stop-after", "5", "--run-id", "badrec"], cwd=tmp_path, env=python_env(), capture_output=True,
                          text=True, timeout=180)
    out = done.stdout + done.stderr
    assert done.returncode == 2, out[-3000:]
    assert "[ar_inference]" in out and "bad configuration: " in out, out[-3000:]
    assert "[launch] run ended: exit code 2" in out
    assert "Traceback" not in out and "KeyboardInterrupt" not in out, out[-3000:]
    # the spread table that is not there: refused before any node starts, in one line
    done = subprocess.run([sys.executable, str(REPO / "launch.py"), "--set", 'markov_prediction.spread_calibration="/nonexistent/spread.json"',
                           "--no-viewer", "--stop-after", "5", "--run-id", "badrec"], cwd=tmp_path, env=python_env(), capture_output=True,
                          text=True, timeout=180)
    assert done.returncode == 2 and "node markov_prediction: spread_calibration = '/nonexistent/spread.json': cannot read" in done.stderr
    assert "[markov_prediction]" not in done.stdout, done.stdout[-2000:]


def _launch(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(REPO / "launch.py"), *args], cwd=cwd, env=python_env(), capture_output=True, text=True, timeout=180)


def test_the_launcher_refuses_to_record_over_a_file_before_any_node_starts(tmp_path):
    """``--record`` naming an existing recording emptied it as the recorder started (the run's exit code was 0, or 2
    after the damage), and ``replay --record`` of the replayed file itself replayed an empty file."""
    from stages.recorder import McapRecorder, RecorderConfig

    rec = tmp_path / "keep.mcap"
    with McapRecorder(RecorderConfig(path=str(rec)), "demo") as r:
        r.handle("iamp/demo/source/scene", b"x", 1)
    before = rec.read_bytes()
    for args, message in (
        (("--record", str(rec)), "exists: a recording is never replaced unless asked"),
        (("--record", str(rec), "--check"), "exists: a recording is never replaced unless asked"),
        (("replay", "--var", f"FILE={rec}", "--record", str(rec), "--overwrite"), "the file node source replays: choose another --record path"),
        (("--record", str(tmp_path / "new.mcap"), "--recording", "nosuch"), "no recording 'nosuch' under"),
        (("--record", str(tmp_path / "new.mcap"), "--recording", "nosuch", "--check"), "no recording 'nosuch' under"),
        (("replay", "--var", f"FILE={tmp_path / 'nosuch.mcap'}", "--check"), "nosuch.mcap: no such file"),
        (("--record", "/proc/iamp-no-such-folder/run.mcap"), "node recorder (--record): path /proc/iamp-no-such-folder/run.mcap: cannot create the folder"),
        (("--record", "/proc/iamp-no-such-folder/run.mcap"), ": record elsewhere (launch.py --record FILE.mcap) or not at all (--no-record)"),
        ((str(rec),), "not a text file, so not a pipeline TOML file"),
        ((str(tmp_path),), "is a folder; expected a pipeline TOML file"),
    ):
        done = _launch(*args, "--no-viewer", "--stop-after", "5", cwd=tmp_path)
        out = done.stdout + done.stderr
        assert done.returncode == 2 and message in done.stderr, (args, out[-2000:])
        assert "node up" not in out and "Traceback" not in out and len(done.stderr.strip().splitlines()) == 1, (args, out[-2000:])
        assert rec.read_bytes() == before
    assert not (tmp_path / "new.mcap").exists()


def test_the_launcher_s_speed_flag_sets_a_replay_s_speed(tmp_path):
    from stages.recorder import McapRecorder, RecorderConfig

    rec = tmp_path / "r.mcap"
    with McapRecorder(RecorderConfig(path=str(rec)), "demo") as r:
        r.handle("iamp/demo/source/scene", b"x", 1)
    done = _launch("replay", "--var", f"FILE={rec}", "--speed", "max", "--describe", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert '"speed": "max"' in done.stdout, done.stdout[-2000:]
    done = _launch("replay", "--var", f"FILE={rec}", "--speed", "2", "--describe", cwd=tmp_path)
    assert done.returncode == 0 and '"speed": 2.0' in done.stdout, done.stdout[-2000:] + done.stderr


def test_a_node_without_any_link_to_its_connect_endpoint_says_so(tmp_path):
    """`iamp record --connect` to a port where nothing listens (or a router that refuses its credentials) logged `node
    up` and recorded only its own stats, without a word."""
    import signal as _signal
    import time as _time

    from testkit.helpers import free_port

    port = free_port()  # nothing listens there
    proc = subprocess.Popen([sys.executable, "-m", "stages.cli", "record", str(tmp_path / "r.mcap"), "--run-id", "demo",
                             "--connect", f"tcp/127.0.0.1:{port}"], cwd=tmp_path, env=python_env(), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    lines = []
    try:
        deadline = _time.monotonic() + 60
        while _time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
            if "no link after" in line:
                break
    finally:
        proc.send_signal(_signal.SIGINT)
        try:
            proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
    assert any(f"no link after 5 s to --connect tcp/127.0.0.1:{port}" in ln for ln in lines), "".join(lines)


def test_linger_keeps_the_run_up_after_the_source_finished(tmp_path):
    """A replay's viewer went away the moment the replay ended (at --speed max, within seconds): --linger keeps every
    node up until Ctrl-C or --stop-after."""
    from stages.recorder import McapRecorder, RecorderConfig

    rec = tmp_path / "r.mcap"
    with McapRecorder(RecorderConfig(path=str(rec)), "demo") as r:
        r.handle("iamp/demo/source/scene", b"x", 1)  # one message: the replay ends at once
        r.handle("iamp/demo/source/other", b"y", 2)
    done = _launch("replay", "--var", f"FILE={rec}", "--speed", "max", "--no-viewer", "--record", str(tmp_path / "again.mcap"), "--linger",
                   "--stop-after", "5", cwd=tmp_path)  # the two-message replay ends within a second of its start
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-2000:]
    out = done.stdout
    assert "all sources finished; --linger" in out and out.index("all sources finished") < out.index("--stop-after 5 s reached"), out[-3000:]
