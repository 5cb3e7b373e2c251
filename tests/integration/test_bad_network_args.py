"""A zenoh ``--config`` file zenoh cannot read, or an endpoint it refuses, is a bad command line: one "bad
configuration" line and exit 2, for a stage, a tool and the launcher. Before, a stage crashed (exit 1) with zenoh's
traceback and then a second one from its shutdown (no stats publisher), and the launcher ended in a traceback."""

from __future__ import annotations

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


@pytest.mark.parametrize("flag", ["config", "listen"])
def test_a_stage_with_a_bad_zenoh_config_or_endpoint_exits_2_with_one_line(flag, bad_config):
    extra = ["--config", str(bad_config)] if flag == "config" else ["--listen", BAD_ENDPOINT]
    done = subprocess.run([sys.executable, str(REPO / "tests" / "integration" / "echo_stage.py"), "--node-id", "echo", "--run-id", "badnet",
                           "--input", "profiles=src/profiles", *extra], cwd=REPO, env=python_env(), capture_output=True, text=True, timeout=120)
    out = done.stdout + done.stderr
    assert done.returncode == 2, out
    assert "bad configuration: " + ("--config " if flag == "config" else "cannot open the zenoh session") in out
    assert "Traceback" not in out and "AttributeError" not in out, out


def test_the_launcher_with_a_bad_hub_endpoint_exits_2_with_one_line():
    done = subprocess.run([sys.executable, str(REPO / "launch.py"), "--listen", BAD_ENDPOINT, "--no-viewer", "--stop-after", "1"], cwd=REPO,
                          env=python_env(), capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr
    assert "launch.py: cannot open the zenoh session" in done.stderr and "Traceback" not in done.stderr, done.stderr
