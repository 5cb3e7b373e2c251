"""Bus authentication ([bus.auth], Zenoh usrpwd) over real Zenoh sessions on loopback.

A run of ``launch.py`` with ``[bus.auth]`` (password from an environment
variable) and one node, the recorder (a raw sink on ``iamp/<run>/**``): a
session of this test with the run's credentials publishes into it and the
recorder acknowledges every message (its ``Progress``); sessions without
credentials and with a wrong password open, find no peer, and what they
publish never reaches the recorder (not in its MCAP file, which holds every
credentialed message), nor do they receive the run's traffic. The password
is on no process's command line; the config the nodes get is 0600 in a 0700
folder that is gone after the run. Bad ``[bus.auth]`` tables stop
``launch.py`` with exit 2 and a message that says what to fix.
"""

from __future__ import annotations

import json
import os
import re
import secrets
import signal
import stat
import subprocess
import sys
import threading
from pathlib import Path

import pytest

import bus_schemas as bs
from testkit.helpers import REPO, all_command_lines, endpoint, free_port, kill_all, python_env, wait_until
from stages.recorder.inspect import inspect
from stages.runtime.pipeline import PipelineError, load_pipeline
from stages.runtime import BusClient
from test_launch_run import Launch
from tests.integration.echo_stage import profiles_payload

RUN = "authrun"
PW_ENV = "IAMP_TEST_BUS_PASSWORD"


def _pipeline(tmp_path: Path, auth: str, port: int | None = None) -> Path:
    rec = tmp_path / "run.mcap"
    text = f"""name = "auth"
[bus]
run_id = "{RUN}"
listen = ["{endpoint(port) if port else 'tcp/127.0.0.1:0'}"]
{auth}
[[nodes]]
id = "recorder"
stage = "stages.recorder"
params = {{ path = "{rec}" }}
"""
    path = tmp_path / "auth.toml"
    path.write_text(text)
    return path


def _client_config(tmp_path: Path, name: str, user: str, password: str) -> str:
    path = tmp_path / f"{name}.json5"
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as f:
        json.dump({"transport": {"auth": {"usrpwd": {"user": user, "password": password}}}}, f)
    return str(path)


class Acks:
    """The recorder's Progress (``last_stamp_ns`` of the newest message it handled), seen through a session."""

    def __init__(self, bus: BusClient) -> None:
        self._lock = threading.Lock()
        self.last_stamp_ns = -1
        bus.subscribe(bs.keys.ack_key(RUN, "recorder"), self._on)

    def _on(self, _key: str, data: bytes) -> None:
        msg = bs.Progress.decode(data)
        with self._lock:
            self.last_stamp_ns = max(self.last_stamp_ns, msg.last_stamp_ns)

    def wait_for(self, stamp_index: int) -> None:
        want = 1_000_000_000 + stamp_index * 100_000_000
        wait_until(lambda: self.last_stamp_ns >= want, 30.0, f"the recorder's acknowledgement of stamp #{stamp_index} (last: {self.last_stamp_ns})")


def test_protected_run_takes_only_credentialed_sessions(tmp_path, monkeypatch):
    password = "pw-" + secrets.token_hex(12)
    monkeypatch.setenv(PW_ENV, password)
    port = free_port()
    pipeline = _pipeline(tmp_path, f'[bus.auth]\nuser = "iamp"\npassword_env = "{PW_ENV}"', port)
    run = Launch(str(pipeline), cwd=tmp_path)
    sessions: list[BusClient] = []
    try:
        m = run.wait_line(r"^\[launch\] bus auth: usrpwd\(user=iamp, password from \$" + PW_ENV + r"\); every node gets --config (\S+) \(mode 0600\)")
        config = Path(m.group(1))
        run.wait_line(r"^\[launch\] all 1 nodes alive; starting sources")
        assert stat.S_IMODE(config.stat().st_mode) == 0o600
        assert stat.S_IMODE(config.parent.stat().st_mode) == 0o700
        for f in config.parent.iterdir():
            assert stat.S_IMODE(f.stat().st_mode) == 0o600, f
        assert not [c for c in all_command_lines() if password in c], "the bus password is on a command line"

        hub = [endpoint(port)]
        seen_by_intruders: list[str] = []
        intruders = {
            "none": BusClient(connect=hub),
            "wrong": BusClient(connect=hub, config_file=_client_config(tmp_path, "wrong", "iamp", password + "x")),
            "nouser": BusClient(connect=hub, config_file=_client_config(tmp_path, "nouser", "mallory", password)),
        }
        sessions += intruders.values()
        for bus in intruders.values():  # each gets its own puts back (local delivery): those are not the run's
            bus.subscribe(f"iamp/{RUN}/**", lambda key, _data: key.split("/")[2] in intruders or seen_by_intruders.append(key))
        good = BusClient(connect=hub, config_file=_client_config(tmp_path, "good", "iamp", password))
        sessions.append(good)
        # (with auth the hub is a router: the run's traffic goes through it, eclipse-zenoh/zenoh#2577)
        assert list(good.session.info.routers_zid()) + list(good.session.info.peers_zid()), f"the credentialed session has no link:\n{run.text()[-3000:]}"
        acks = Acks(good)
        publish, matched = good.publisher_with_matching(f"iamp/{RUN}/good/profiles")
        wait_until(matched, 30.0, "the recorder's subscription reaching the credentialed session")

        for name, bus in intruders.items():  # opened after their link attempt: refused
            assert list(bus.session.info.peers_zid()) + list(bus.session.info.routers_zid()) == [], f"session {name} got a link into the protected run"
            for i in range(1, 4):
                bus.put(f"iamp/{RUN}/{name}/profiles", profiles_payload(100 + i))
        for i in range(1, 4):
            publish(profiles_payload(i))
        acks.wait_for(3)
        for name, bus in intruders.items():  # later than the first good round trip, in case a link were slow
            bus.put(f"iamp/{RUN}/{name}/profiles", profiles_payload(200))
        publish(profiles_payload(4))
        acks.wait_for(4)
        assert seen_by_intruders == [], f"unauthenticated sessions received the run's traffic: {sorted(set(seen_by_intruders))[:5]}"

        run.proc.send_signal(signal.SIGINT)
        assert run.wait() == 0, run.text()[-4000:]
        assert not config.parent.exists(), "the private auth folder outlived the run"
    finally:
        for bus in sessions:
            bus.close()
        kill_all([run.proc])
    topics = {c["topic"]: c["count"] for c in inspect(str(tmp_path / "run.mcap"))["channels"]}
    assert topics.get(f"iamp/{RUN}/good/profiles") == 4, topics
    intruding = [t for t in topics if t.split("/")[2] in ("none", "wrong", "nouser")]
    assert intruding == [], f"messages of unauthenticated sessions were recorded: {intruding}"


def test_without_auth_the_same_intruder_gets_in(tmp_path):
    """The control for the test above: without [bus.auth] a session without credentials links and is recorded."""
    port = free_port()
    run = Launch(str(_pipeline(tmp_path, "", port)), cwd=tmp_path)
    intruder = None
    try:
        run.wait_line(r"^\[launch\] all 1 nodes alive; starting sources")
        assert "bus auth" not in run.text()
        intruder = BusClient(connect=[endpoint(port)])
        acks = Acks(intruder)
        publish, matched = intruder.publisher_with_matching(f"iamp/{RUN}/none/profiles")
        wait_until(matched, 30.0, "the recorder's subscription reaching the session")
        assert list(intruder.session.info.peers_zid())
        publish(profiles_payload(1))
        acks.wait_for(1)
        run.proc.send_signal(signal.SIGINT)
        assert run.wait() == 0, run.text()[-4000:]
    finally:
        if intruder is not None:
            intruder.close()
        kill_all([run.proc])
    topics = {c["topic"]: c["count"] for c in inspect(str(tmp_path / "run.mcap"))["channels"]}
    assert topics.get(f"iamp/{RUN}/none/profiles") == 1, topics


@pytest.mark.parametrize(
    "auth, message",
    [
        ('[bus.auth]\nuser = ""\npassword = "x"', r"\[bus.auth\] user must be a non-empty string"),
        ('[bus.auth]\nuser = "a:b"\npassword = "x"', r"must not contain ':'"),
        ('[bus.auth]\nuser = "iamp"', r"needs exactly one of password_env"),
        ('[bus.auth]\nuser = "iamp"\npassword = "x"\npassword_env = "X"', r"needs exactly one of password_env"),
        ('[bus.auth]\nuser = "iamp"\npassword = ""', r"password must be a non-empty string"),
        ('[bus.auth]\nuser = "iamp"\npassword_env = "IAMP_TEST_UNSET_PW"', r"set the environment variable IAMP_TEST_UNSET_PW"),
        ('[bus.auth]\nuser = "iamp"\npasswd = "x"', r"unknown key\(s\) in \[bus.auth\]: passwd"),
    ],
)
def test_bad_auth_tables_say_what_to_fix(tmp_path, monkeypatch, auth, message):
    monkeypatch.delenv("IAMP_TEST_UNSET_PW", raising=False)
    path = _pipeline(tmp_path, auth)
    with pytest.raises(PipelineError, match=message):
        load_pipeline(path)


def test_auth_given_as_a_string_is_refused(tmp_path):
    path = tmp_path / "p.toml"
    path.write_text(f'[bus]\nrun_id = "{RUN}"\nauth = "iamp:x"\n[[nodes]]\nid = "recorder"\nstage = "stages.recorder"\n')
    with pytest.raises(PipelineError, match=r"\[bus\] auth must be a table"):
        load_pipeline(path)


def test_launcher_exits_2_on_empty_user_and_describe_hides_the_password(tmp_path, monkeypatch):
    bad = _pipeline(tmp_path, '[bus.auth]\nuser = ""\npassword_env = "X"')
    proc = subprocess.run([sys.executable, str(REPO / "launch.py"), str(bad), "--check"], cwd=tmp_path, env=python_env(), capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert "[bus.auth] user must be a non-empty string" in proc.stderr
    good = _pipeline(tmp_path, '[bus.auth]\nuser = "iamp"\npassword = "s3cret-in-file"')
    proc = subprocess.run([sys.executable, str(REPO / "launch.py"), str(good), "--describe"], cwd=tmp_path, env=python_env(), capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "auth=usrpwd(user=iamp, password from the pipeline file)" in proc.stdout
    assert "s3cret-in-file" not in proc.stdout + proc.stderr


def _auth_router(tmp_path: Path, port: int, user: str, password: str) -> BusClient:
    """A Zenoh router on ``port`` that takes ``user``/``password`` (its dictionary in a 0600 file), as one on another host would."""
    dictionary = tmp_path / "router-users.txt"
    fd = os.open(dictionary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(f"{user}:{password}\n")
    config = tmp_path / "router.json5"
    fd = os.open(config, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as f:
        json.dump({"transport": {"auth": {"usrpwd": {"dictionary_file": str(dictionary)}}}}, f)
    return BusClient(mode="router", listen=[endpoint(port)], config_file=str(config))


def test_a_client_refused_by_an_auth_router_gets_one_line_that_says_what_to_fix(tmp_path):
    """Before, zenoh's own text: 'Unable to connect to any of [Single(tcp/...)]!  at /root/.cargo/git/checkouts/zenoh-.../
    orchestrator.rs:447.', the same for a wrong password, no credentials and nothing listening."""
    from stages.lib.base import ConfigError
    from stages.runtime import open_session

    password = "pw-" + secrets.token_hex(12)
    port = free_port()
    hub = [endpoint(port)]
    wrong = _client_config(tmp_path, "wrong", "iamp", password + "x")
    json5_without = tmp_path / "plain.json5"
    json5_without.write_text('{ mode: "client" }\n')
    with _auth_router(tmp_path, port, "iamp", password):
        cases = {
            "wrong": (wrong, [f"refused this session: the user/password in --config {wrong} (transport/auth/usrpwd, user 'iamp')"]),
            "none": (None, ["refused this session: this session has no credentials: give --config FILE", "usrpwd"]),
            "no usrpwd": (str(json5_without), [f"refused this session: --config {json5_without} has no transport/auth/usrpwd user and password"]),
        }
        for name, (config, wanted) in cases.items():
            with pytest.raises(ConfigError) as err:
                open_session("client", hub, config_file=config)
            text = str(err.value)
            assert text.startswith(f"cannot join the bus: the router at --connect {hub[0]} "), (name, text)
            for want in wanted:
                assert want in text, (name, text)
            assert "\n" not in text and ".rs:" not in text and ".cargo" not in text, (name, text)
            assert password not in text and password + "x" not in text
        # a stage (a node started by hand, as README says) exits 2 with that one line, no Rust path, no traceback
        done = subprocess.run([sys.executable, str(REPO / "tests" / "integration" / "echo_stage.py"), "--node-id", "echo", "--run-id", RUN,
                               "--input", "profiles=src/profiles", "--mode", "client", "--connect", hub[0], "--config", wrong],
                              cwd=REPO, env=python_env(), capture_output=True, text=True, timeout=120)
    out = done.stdout + done.stderr
    assert done.returncode == 2, out
    lines = [line for line in out.splitlines() if "bad configuration:" in line]
    assert len(lines) == 1 and f"the user/password in --config {wrong}" in lines[0], out
    assert ".rs:" not in out and ".cargo" not in out and "Traceback" not in out, out
    dead = endpoint(free_port())
    with pytest.raises(ConfigError, match=r"^cannot join the bus: nothing listens at --connect " + re.escape(dead) + ": start the launcher or router there"):
        open_session("client", [dead], config_file=wrong)


@pytest.mark.parametrize("how, mode, warned", [("password", 0o644, True), ("password", 0o640, True), ("password", 0o600, False),
                                               ("password_env", 0o644, False)])
def test_a_literal_password_in_a_file_others_can_read_gets_one_warning(tmp_path, monkeypatch, how, mode, warned):
    monkeypatch.setenv(PW_ENV, "pw-from-env")
    auth = '[bus.auth]\nuser = "iamp"\n' + ('password = "s3cret-in-file"' if how == "password" else f'password_env = "{PW_ENV}"')
    path = _pipeline(tmp_path, auth)
    os.chmod(path, mode)
    found = [w for w in load_pipeline(path).warnings if "bus password" in w]
    assert len(found) == int(warned), found
    proc = subprocess.run([sys.executable, str(REPO / "launch.py"), str(path), "--check"], cwd=tmp_path, env=python_env(), capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr  # a warning, not a stop
    lines = [line for line in proc.stdout.splitlines() if "bus password" in line]
    assert len(lines) == int(warned), proc.stdout
    if warned:
        assert lines[0].startswith(f"[launch] warning: {path} holds the bus password") and f"(mode {mode:04o})" in lines[0], lines[0]
        assert f"chmod 600 {path}" in lines[0] and "password_env" in lines[0], lines[0]
    assert "s3cret-in-file" not in proc.stdout + proc.stderr


def test_with_auth_a_remote_router_is_joined_by_the_hub_and_the_nodes_stay_on_the_hub(tmp_path, monkeypatch):
    """[bus.auth] and --connect to a remote router: the launcher says what it does in one line, the nodes get the hub
    alone (a client links to one router only), the hub links to the remote router, and a session on the remote router
    with the run's credentials reaches the run's recorder through the two routers."""
    password = "pw-" + secrets.token_hex(12)
    monkeypatch.setenv(PW_ENV, password)
    hub_port, far_port = free_port(), free_port()
    far = endpoint(far_port)
    pipeline = _pipeline(tmp_path, f'[bus.auth]\nuser = "iamp"\npassword_env = "{PW_ENV}"', hub_port)
    sessions: list[BusClient] = [_auth_router(tmp_path, far_port, "iamp", password)]
    run = Launch(str(pipeline), "--connect", far, cwd=tmp_path)
    try:
        line = run.wait_line(r"^\[launch\] bus auth with --connect " + re.escape(far) + r": the nodes are Zenoh clients").string
        assert "join the hub alone" in line and "must accept the run's [bus.auth] user and password" in line, line
        run.wait_line(r"^\[launch\] all 1 nodes alive; starting sources")
        run.wait_line(r"^\[launch\] hub linked to --connect " + re.escape(far) + "$")
        recorder = [c for c in all_command_lines() if "stages.recorder" in c and f"--run-id {RUN}" in c]
        assert recorder and all(f"--connect {endpoint(hub_port)}" in c and far not in c for c in recorder), recorder

        remote = BusClient(mode="client", connect=[far], config_file=_client_config(tmp_path, "remote", "iamp", password))
        sessions.append(remote)
        acks = Acks(remote)
        publish, matched = remote.publisher_with_matching(f"iamp/{RUN}/remote/profiles")
        wait_until(matched, 30.0, "the recorder's subscription reaching a session on the remote router")
        for i in range(1, 4):
            publish(profiles_payload(i))
        acks.wait_for(3)
        run.proc.send_signal(signal.SIGINT)
        assert run.wait() == 0, run.text()[-4000:]
    finally:
        for bus in reversed(sessions):
            bus.close()
        kill_all([run.proc])
    assert "warning: no link" not in run.text(), run.text()[-4000:]
    topics = {c["topic"]: c["count"] for c in inspect(str(tmp_path / "run.mcap"))["channels"]}
    assert topics.get(f"iamp/{RUN}/remote/profiles") == 3, topics
