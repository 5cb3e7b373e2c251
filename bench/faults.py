"""Faults during a recorded streaming run: kill -9 each processing stage once, then the recorder.

Run 1: ``python launch.py --speed 1 --no-viewer --record faults.mcap --stop-after S``
on the embedded scenario (K729, sequence 013, real time). Once the source
plays, each processing stage (corridors, relations, intentions, ar_inference,
markov_prediction) is killed with SIGKILL once, ``--spacing`` seconds apart
(its pid from the launcher's ``node up: ... pid=N`` line, checked against
``/proc/<pid>/cmdline``); the launcher restarts it (``restart = true``). From
the MCAP (``log_time`` is the recorder's receive time, wall clock) per kill:

- ``next_grid_s``: kill to the next MotionGrid of any frame;
- ``recovery_s``: kill to the first MotionGrid of a frame published after the
  kill (one the restarted stage had to handle): the target is <= 2 s;
- ``restart_s``: kill to the restarted node's ``node up`` line;
- ``frames_lost``: TrackFrames recorded between this kill and the next
  without a MotionGrid.

Run 2: the same run, the recorder killed with SIGKILL ``--recorder-kill-s``
after the source started. Printed: chunks, whether the file reads as
truncated, the last TrackFrame frame index (and stamp) in the file vs. the
recording time the source was at when killed, the seconds of data lost;
where the launcher restarts the recorder into ``NAME.001.mcap`` (and so
on), the frames each part holds and those lost between the parts.

Timings are printed, not judged; asserts nothing.

    python bench/faults.py [--speed 1] [--first-kill-s 10] [--spacing 15] [--recorder-kill-s 15] [--json OUT] [--keep DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import bus_schemas as bs
from stages.recorder.inspect import ReadReport, read_messages
from stages.lib.base import check_output_arg

REPO = Path(__file__).resolve().parents[1]
STAGES = ("corridors", "relations", "intentions", "ar_inference", "markov_prediction")
NODE_UP = re.compile(r"^\[(?P<node>[a-z_]+)\] .*node up: stage=(?P<stage>\S+) .*pid=(?P<pid>\d+)")
STARTING = re.compile(r"^\[launch\] all \d+ nodes alive; starting sources")


class Launch:
    """launch.py as a child; every output line kept with its wall-clock arrival time."""

    def __init__(self, args: list[str], cwd: Path, run_id: str) -> None:
        self.lines: list[tuple[float, str]] = []
        self._lock = threading.Lock()
        self.proc = subprocess.Popen(
            [sys.executable, str(REPO / "launch.py"), "--no-viewer", "--recording", "k729_2022-03-16", "--run-id", run_id, *args],
            cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True,
        )
        threading.Thread(target=self._pump, daemon=True).start()

    def _pump(self) -> None:
        for line in self.proc.stdout:
            with self._lock:
                self.lines.append((time.time(), line.rstrip("\n")))

    def snapshot(self) -> list[tuple[float, str]]:
        with self._lock:
            return list(self.lines)

    def wait_for(self, rx: re.Pattern, timeout_s: float, after: float = 0.0) -> tuple[float, re.Match]:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for t, line in self.snapshot():
                if t >= after and (m := rx.search(line)):
                    return t, m
            if self.proc.poll() is not None:
                break
            time.sleep(0.05)
        raise RuntimeError(f"no launcher line matching {rx.pattern!r}; last lines:\n" + "\n".join(l for _, l in self.snapshot()[-30:]))

    def pid_of(self, node: str) -> int | None:
        pid = None
        for _, line in self.snapshot():
            m = NODE_UP.search(line)
            if m and m.group("node") == node:
                pid = int(m.group("pid"))
        return pid

    def up_after(self, node: str, t0: float) -> float | None:
        for t, line in self.snapshot():
            m = NODE_UP.search(line)
            if t > t0 and m and m.group("node") == node:
                return t
        return None

    def wait(self, timeout_s: float) -> int:
        try:
            return self.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.send_signal(signal.SIGINT)
            try:
                return self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                return self.proc.wait()

    def text(self) -> str:
        return "\n".join(l for _, l in self.snapshot())


def kill9(pid: int, stage: str) -> None:
    """SIGKILL ``pid`` after checking it runs ``stage`` (never a stranger's process)."""
    cmdline = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    if f"-m {stage}" not in cmdline:
        raise RuntimeError(f"pid {pid} runs {cmdline!r}, not {stage}")
    os.kill(pid, signal.SIGKILL)


def read_run(path: Path, run_id: str) -> dict:
    report = ReadReport()
    frames: dict[int, tuple[int, int]] = {}  # frame_index -> (log_time_ns, stamp_ns)
    grids: dict[int, int] = {}  # frame_index -> log_time_ns
    for m in read_messages(str(path), report):
        if not m.topic.startswith(f"iamp/{run_id}/"):
            continue
        if m.schema == bs.TrackFrame.SCHEMA:
            h = bs.TrackFrame.decode(m.data).header
            frames[h.frame_index] = (m.log_time_ns, h.stamp_ns)
        elif m.schema == bs.MotionGrid.SCHEMA:
            h = bs.MotionGrid.decode(m.data).header
            grids.setdefault(h.frame_index, m.log_time_ns)
    return {"frames": frames, "grids": grids, "truncated": report.truncated, "error": report.error, "chunks": report.chunks,
            "messages": report.messages}


def stage_kills(args, work: Path) -> dict:
    mcap = work / "faults.mcap"
    run_id = "faults"
    stop_after = args.first_kill_s + args.spacing * len(STAGES) + 5
    launch = Launch(["--speed", str(args.speed), "--record", str(mcap), "--overwrite", "--stop-after", f"{stop_after:g}"], work, run_id)
    kills = []
    try:
        t_play, _ = launch.wait_for(STARTING, 180)
        for k, node in enumerate(STAGES):
            due = t_play + args.first_kill_s + k * args.spacing
            while time.time() < due:
                time.sleep(0.02)
            pid = launch.pid_of(node)
            if pid is None:
                raise RuntimeError(f"no pid for {node}")
            t_kill = time.time()
            kill9(pid, f"stages.{node}")
            kills.append({"node": node, "pid": pid, "t_kill": t_kill, "at_s": round(t_kill - t_play, 2)})
            print(f"   killed {node} (pid {pid}) at {t_kill - t_play:.1f} s", flush=True)
        code = launch.wait(stop_after + 120)
    finally:
        if launch.proc.poll() is None:
            launch.proc.kill()
    (work / "faults.launch.log").write_text(launch.text())
    rec = read_run(mcap, run_id)
    frames, grids = rec["frames"], rec["grids"]
    grid_times = sorted(grids.values())
    for k, kill in enumerate(kills):
        kn = int(kill["t_kill"] * 1e9)
        end = int(kills[k + 1]["t_kill"] * 1e9) if k + 1 < len(kills) else None
        nxt = next((t for t in grid_times if t > kn), None)
        post = [grids[i] for i, (ft, _) in frames.items() if ft > kn and i in grids]
        up = launch.up_after(kill["node"], kill["t_kill"])
        window = [i for i, (ft, _) in frames.items() if ft >= kn and (end is None or ft < end)]
        kill["next_grid_s"] = round((nxt - kn) / 1e9, 3) if nxt else None
        kill["recovery_s"] = round((min(post) - kn) / 1e9, 3) if post else None
        kill["restart_s"] = round(up - kill["t_kill"], 2) if up else None
        kill["frames_lost"] = sum(1 for i in window if i not in grids)
        kill["frames_in_window"] = len(window)
    first_kill = int(kills[0]["t_kill"] * 1e9) if kills else None
    before = [i for i, (ft, _) in frames.items() if first_kill is None or ft < first_kill]
    return {"exit_code": code, "track_frames": len(frames), "motion_grids": len(grids), "kills": kills,
            "frames_lost_before_kills": sum(1 for i in before if i not in grids),
            "restarts": [l for _, l in launch.snapshot() if "restarting" in l or "died" in l]}


def recorder_kill(args, work: Path) -> dict:
    mcap = work / "recorder_kill.mcap"
    run_id = "faultsrec"
    launch = Launch(["--speed", str(args.speed), "--record", str(mcap), "--overwrite", "--stop-after", f"{args.recorder_kill_s + 20:g}"], work, run_id)
    try:
        t_play, _ = launch.wait_for(STARTING, 180)
        while time.time() < t_play + args.recorder_kill_s:
            time.sleep(0.02)
        pid = launch.pid_of("recorder")
        t_kill = time.time()
        kill9(pid, "stages.recorder")
        print(f"   killed recorder (pid {pid}) at {t_kill - t_play:.1f} s", flush=True)
        code = launch.wait(120)
    finally:
        if launch.proc.poll() is None:
            launch.proc.kill()
    (work / "recorder_kill.launch.log").write_text(launch.text())
    rec = read_run(mcap, run_id)
    frames = rec["frames"]
    kn = int(t_kill * 1e9)
    last = max(frames) if frames else None
    first_t = min(t for t, _ in frames.values()) if frames else None
    # the frame the source was at when the recorder died: recording time elapsed since frame 0, at the playing speed
    at_kill = None
    if frames:
        f0_log, f0_stamp = frames[min(frames)]
        at_kill = (kn - f0_log) * args.speed / 1e9
    # a launcher that restarts the recorder goes on in NAME.001.mcap, ...: frames between the parts are lost
    parts = []
    for part in sorted(mcap.parent.glob(f"{mcap.stem}.[0-9][0-9][0-9].mcap")):
        pr = read_run(part, run_id)
        pf = pr["frames"]
        parts.append({"path": part.name, "truncated": pr["truncated"], "messages": pr["messages"],
                      "first_frame_index": min(pf) if pf else None, "last_frame_index": max(pf) if pf else None,
                      "first_frame_log_s_after_kill": round((pf[min(pf)][0] - kn) / 1e9, 2) if pf else None})
    gap = None
    if parts and parts[0]["first_frame_index"] is not None and last is not None:
        gap = parts[0]["first_frame_index"] - last - 1
    return {
        "parts": parts, "frames_between_parts": gap,
        "exit_code": code, "pid": pid, "killed_at_s": round(t_kill - t_play, 2), "file_bytes": mcap.stat().st_size if mcap.exists() else 0,
        "truncated": rec["truncated"], "error": rec["error"], "chunks": rec["chunks"], "messages": rec["messages"],
        "last_frame_index": last, "last_frame_stamp_s": round(frames[last][1] / 1e9, 2) if last is not None else None,
        "recording_s_at_kill": round(at_kill, 2) if at_kill is not None else None,
        "lost_s": round((kn - max(t for t, _ in frames.values())) / 1e9, 2) if frames else None,
        "first_frame_log_s_after_play": round(first_t / 1e9 - t_play, 2) if first_t else None,
        "launcher_lines": [l for _, l in launch.snapshot() if l.startswith("[launch]") and "recorder" in l],
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--speed", type=float, default=1.0, help="playback speed (default 1: real time)")
    p.add_argument("--first-kill-s", type=float, default=10.0, help="first kill this long after the source starts (default 10)")
    p.add_argument("--spacing", type=float, default=15.0, help="seconds between kills (default 15)")
    p.add_argument("--recorder-kill-s", type=float, default=15.0, help="recorder killed this long after the source starts (default 15)")
    p.add_argument("--skip-stages", action="store_true", help="only the recorder run")
    p.add_argument("--skip-recorder", action="store_true", help="only the stage kills")
    p.add_argument("--json", type=Path, default=None)
    p.add_argument("--keep", type=Path, default=None, help="keep MCAP files and launcher logs here")
    args = p.parse_args(argv)
    check_output_arg(p, args.json, "--json")  # before the work: a bad path must not cost the run
    out: dict = {}
    with tempfile.TemporaryDirectory(prefix="iamp-faults-") as tmp:
        work = args.keep or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        if not args.skip_stages:
            print("== run 1: kill -9 each processing stage once", flush=True)
            out["stages"] = s = stage_kills(args, work)
            print(f"launcher exit {s['exit_code']}; TrackFrames {s['track_frames']}, MotionGrids {s['motion_grids']}, "
                  f"frames lost before the first kill {s['frames_lost_before_kills']}")
            head = f"{'stage':<18} {'killed_at_s':>11} {'restart_s':>9} {'next_grid_s':>11} {'recovery_s':>10} {'frames_lost':>11} {'of':>5}"
            print(head)
            print("-" * len(head))
            fmt = lambda v: "-" if v is None else f"{v:g}"  # noqa: E731
            for k in s["kills"]:
                print(f"{k['node']:<18} {k['at_s']:>11.1f} {fmt(k['restart_s']):>9} {fmt(k['next_grid_s']):>11} {fmt(k['recovery_s']):>10}"
                      f" {k['frames_lost']:>11d} {k['frames_in_window']:>5d}")
            print("target: recovery_s <= 2")
        if not args.skip_recorder:
            print("== run 2: kill -9 the recorder", flush=True)
            out["recorder"] = r = recorder_kill(args, work)
            print(f"launcher exit {r['exit_code']}; recorder killed {r['killed_at_s']} s after the source started "
                  f"(recording time ~{r['recording_s_at_kill']} s)")
            print(f"file: {r['file_bytes']} bytes, {r['chunks']} chunks, {r['messages']} messages, truncated={r['truncated']} ({r['error']})")
            print(f"reads up to TrackFrame {r['last_frame_index']} (stamp {r['last_frame_stamp_s']} s); "
                  f"last frame received {r['lost_s']} s before the kill")
            for part in r["parts"]:
                print(f"continued in {part['path']}: frames {part['first_frame_index']}..{part['last_frame_index']} "
                      f"(first {part['first_frame_log_s_after_kill']} s after the kill), truncated={part['truncated']}")
            if r["frames_between_parts"] is not None:
                print(f"frames lost between the torn file and its continuation: {r['frames_between_parts']}")
            for line in r["launcher_lines"]:
                print(f"   {line}")
        if args.json is not None:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps(out, indent=2) + "\n")
            print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
