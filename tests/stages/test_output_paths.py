"""A command checks where it will write before it starts (``stages.lib.base.check_output``): a bad ``--json``,
``--figures``, ``--report`` or ``--out`` used to end ``iamp eval`` (minutes on K733), ``iamp train`` or ``iamp calibrate``
in a traceback after the work, which was lost."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from stages import cli
from stages.lib.base import ConfigError, check_output

UNCREATABLE = "/proc/iamp-no-such-folder"  # /proc takes no new folders, even for root


def test_check_output_creates_the_folder_and_refuses_what_cannot_be_written(tmp_path):
    check_output(tmp_path / "a" / "b" / "report.json", "--json")
    assert (tmp_path / "a" / "b").is_dir() and not (tmp_path / "a" / "b" / "report.json").exists()
    check_output(tmp_path / "figs", "--figures", folder=True)
    assert (tmp_path / "figs").is_dir()
    check_output(None, "--json")
    with pytest.raises(ConfigError, match=r"^--json .*: is a folder; expected a file name$"):
        check_output(tmp_path / "figs", "--json")
    (tmp_path / "plain").write_text("x")
    with pytest.raises(ConfigError, match=r"^--figures .*plain: is a file, not a folder$"):
        check_output(tmp_path / "plain", "--figures", folder=True)
    # found by a new-user probe: a bench ran its minutes and then failed writing its --json
    if Path("/sys").is_dir():  # a folder root may "write" by its rights (os.access) where no file can be made
        with pytest.raises(ConfigError, match=r"^--json /sys/x.json: (cannot write in the folder /sys|the folder /sys is not writable)"):
            check_output("/sys/x.json", "--json")
    (tmp_path / "kept.json").write_text("{}")
    (tmp_path / "kept.json").chmod(0o444)
    if not os.access(tmp_path / "kept.json", os.W_OK):  # (root may write it anyway: then there is nothing to refuse)
        with pytest.raises(ConfigError, match=r"kept.json: the file exists and is not writable$"):
            check_output(tmp_path / "kept.json", "--json")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "figs", "kept.json", "plain"]  # no probe file left behind
    with pytest.raises(ConfigError, match=r"^--out .*: cannot create the folder /proc/iamp-no-such-folder \("):
        check_output(f"{UNCREATABLE}/m.pt", "--out")


@pytest.mark.parametrize("argv, message", [
    (["eval", "--json", f"{UNCREATABLE}/r.json"], "iamp eval: error: --json"),
    (["eval", "--figures", UNCREATABLE], "iamp eval: error: --figures"),
    (["eval", "--report", UNCREATABLE], "iamp eval: error: --report"),
    (["train", "--out", f"{UNCREATABLE}/m.pt"], "iamp train: error: --out"),
    (["train", "--json", f"{UNCREATABLE}/t.json"], "iamp train: error: --json"),
    (["calibrate", "--out", f"{UNCREATABLE}/s.json"], "iamp calibrate: error: --out"),
    (["signals", "--data", "d", "--recording", "r", "--json", f"{UNCREATABLE}/s.json"], "iamp signals: --json"),
    (["signals", "--data", "d", "--recording", "r", "--figure", f"{UNCREATABLE}/s.png"], "iamp signals: --figure"),
    (["data", "superimpose", "--data", "d", "--recording", "r", "--vehicles", "6", "--out", UNCREATABLE], "iamp data superimpose: --out"),
])
def test_a_bad_output_path_stops_the_command_before_its_work(argv, message, capsys):
    assert cli.main([*argv] if argv[0] in ("data", "signals") else [*argv, "--no-progress"]) == 2
    out, err = capsys.readouterr()
    assert err.startswith(message) and "cannot create the folder /proc/iamp-no-such-folder" in err and "Traceback" not in err
    assert out == ""  # nothing ran: no table, no training report, no fit


def test_the_long_benches_refuse_a_bad_json_path_before_their_work():
    """The benches that run for minutes check ``--json`` (and window_errors ``--windows``) right after parsing
    (``check_output_arg``): a usage error, exit 2, nothing measured."""
    import subprocess
    import sys
    from pathlib import Path

    repo = Path(__file__).resolve().parents[2]
    runs = {name: [f"bench/{name}.py", *extra] for name, extra in (
        ("dense", ["--json", f"{UNCREATABLE}/d.json"]), ("e2e_latency", ["--json", f"{UNCREATABLE}/e.json"]),
        ("generalisation", ["--json", f"{UNCREATABLE}/g.json"]), ("window_errors", ["--windows", f"{UNCREATABLE}/w.jsonl"]),
        ("frame_phases", ["--json", f"{UNCREATABLE}/f.json"]))}
    procs = {name: subprocess.Popen([sys.executable, *argv], cwd=repo, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for name, argv in runs.items()}
    for name, proc in procs.items():
        out, err = proc.communicate(timeout=120)
        assert proc.returncode == 2, (name, err[-2000:])
        assert f"{name}.py: error: --" in err and "cannot create the folder /proc/iamp-no-such-folder" in err, (name, err)
        assert "Traceback" not in err, (name, err)


def test_the_recorder_names_its_path_parameter_when_the_folder_cannot_be_made(tmp_path):
    """It said only "[Errno 2] No such file or directory: '/proc/...'"."""
    from stages.recorder.core import McapRecorder, RecorderConfig

    with pytest.raises(ConfigError, match=r"^path /proc/iamp-no-such-folder/run\.mcap: cannot create the folder /proc/iamp-no-such-folder \("):
        McapRecorder(RecorderConfig(path=f"{UNCREATABLE}/run.mcap"), run_id="badpath")
    with pytest.raises(ConfigError, match=r"^path .*: is a folder; expected a file name$"):
        McapRecorder(RecorderConfig(path=str(tmp_path)), run_id="badpath")


def test_atomic_write_replaces_whole_or_not_at_all(tmp_path):
    """``atomic_write``: the file appears only when the block ends, a failure leaves the old contents and no
    temporary file, folders are made, and a new file gets the permissions any new file gets (not a temporary
    file's 0600: model weights and tables are read by other users' stages)."""
    import os
    import stat

    from stages.lib.base import atomic_write

    path = tmp_path / "deep" / "table.json"
    with atomic_write(path) as handle:
        handle.write(b"old")
        assert not path.exists()  # not before the block ends
    assert path.read_bytes() == b"old"
    with pytest.raises(RuntimeError, match="mid-write"):
        with atomic_write(path) as handle:
            handle.write(b"half")
            raise RuntimeError("mid-write")
    assert path.read_bytes() == b"old" and sorted(p.name for p in path.parent.iterdir()) == ["table.json"]
    umask = os.umask(0)
    os.umask(umask)
    (tmp_path / "plain").write_bytes(b"x")
    assert stat.S_IMODE(path.stat().st_mode) == stat.S_IMODE((tmp_path / "plain").stat().st_mode) == 0o666 & ~umask
