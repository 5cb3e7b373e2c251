"""The viewer's comparison of two prediction modes and its selected-vehicle panel: pure parts (no viser).

Kept apart from ``model.py``/``scene.py`` on purpose (other work changes the
drawing of the scene): ``scene.py`` calls these from functions of their own
(``_draw_compare``, ``_draw_vehicle_panel``, ``_zoom_to_traffic``).

- ``OnlineMADE``: the running mADE of each mode from the lagged ground truth
  the viewer already keeps: once a frame lies a full horizon in the past,
  every vehicle that both modes predicted for it and that stayed in view for
  the whole horizon is scored: ADE_c = mean over the steps of the distance
  between corridor c's predicted mean and the true position at that step
  (linear in time between frames; a step whose mean is missing keeps the last
  finite mean), mADE = min over c (docs/method.md §9.5), averaged over the
  scored (frame, vehicle) windows. Both modes are scored on the same windows.
- ``vehicle_panel``: what the side panel shows for the selected vehicle:
  its corridors with P(route) (the predictions' probability; the intentions
  stage's belief and manoeuvre where it arrives), P(stop), the AR
  acceleration distributions of the next 4 s (``ar_image``: the input
  distribution λ(k) of each 0.4 s step as a heat row over -3 … 2 m/s², the
  paper's figure), and its true future once known (ADE of each corridor).
- ``stages_markdown``: the "Stages" panel: two short lines per node (its
  times, then its queue and counts) instead of an eight-column table that
  the narrow side panel squeezed into unreadable columns.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from bus_schemas import AccelerationProfiles, CorridorPredictions, IntentionBelief, Manoeuvre, NodeStats, TrackFrame

#: Colours of the compare view (RGB 0-255), as in the paper's comparison figure.
MODE_COLOURS: dict[str, tuple[int, int, int]] = {"hybrid": (30, 90, 255), "baseline": (230, 30, 30)}
OTHER_MODE_COLOUR = (255, 150, 0)
COMPARE_TRUTH_COLOUR = (0, 0, 0)


def mode_colour(mode: str) -> tuple[int, int, int]:
    return MODE_COLOURS.get(mode, OTHER_MODE_COLOUR)


# --------------------------------------------------------------------------- truth at the prediction steps


def truth_at(frames: list[TrackFrame], stamp_ns: int, times_s: np.ndarray) -> dict[int, np.ndarray]:
    """Where each track was at ``stamp_ns`` + each time of ``times_s``: {track_id: (K, 2)}, only tracks seen over the whole span.

    ``frames`` are the kept frames from ``stamp_ns`` on, oldest first; positions
    between two frames are interpolated linearly in time.
    """
    if not frames or not len(times_s):
        return {}
    t = np.array([(int(f.header.stamp_ns) - stamp_ns) / 1e9 for f in frames])
    paths: dict[int, list[tuple[float, float, float]]] = {}
    for ti, f in zip(t, frames):
        for tid, x, y in zip(f.track_ids, f.x_m, f.y_m):
            if math.isfinite(x) and math.isfinite(y):
                paths.setdefault(int(tid), []).append((ti, float(x), float(y)))
    want = np.asarray(times_s, dtype=float)
    out = {}
    for tid, rows in paths.items():
        a = np.asarray(rows)
        if a[0, 0] > 1e-6 or a[-1, 0] < want[-1] - 1e-6:
            continue  # not seen at the frame itself or gone before the horizon
        gaps = np.diff(a[:, 0])
        if len(gaps) and gaps.max() > 0.5:
            continue  # lost for a while: no trustworthy truth
        out[tid] = np.stack([np.interp(want, a[:, 0], a[:, 1]), np.interp(want, a[:, 0], a[:, 2])], axis=1)
    return out


def _fill_forward(means: np.ndarray) -> np.ndarray | None:
    out = means.copy()
    ok = np.all(np.isfinite(out), axis=1)
    if not ok.any():
        return None
    first = int(np.argmax(ok))
    out[:first] = out[first]
    for k in range(first + 1, len(out)):
        if not ok[k]:
            out[k] = out[k - 1]
    return out


def corridor_ades(pred: CorridorPredictions, track_id: int, truth: np.ndarray) -> dict[int, float]:
    """ADE of each of the vehicle's corridors against its true positions at the steps: {corridor_id: m}."""
    out = {}
    for p in pred.predictions:
        if p.track_id != track_id:
            continue
        means = _fill_forward(np.stack([p.mean_x_m, p.mean_y_m], axis=1).astype(float))
        if means is None or len(means) != len(truth):
            continue
        out[int(p.corridor_id)] = float(np.hypot(*(means - truth).T).mean())
    return out


@dataclass
class ModeScore:
    windows: int = 0
    made_sum: float = 0.0

    @property
    def made(self) -> float:
        return self.made_sum / self.windows if self.windows else math.nan


@dataclass
class OnlineMADE:
    """Running mADE per mode on the (frame, vehicle) windows both modes predicted (module docstring)."""

    scores: dict[str, ModeScore] = field(default_factory=dict)
    evaluated: set[int] = field(default_factory=set)
    frames_scored: int = 0

    def score(self, stamp_ns: int, a: CorridorPredictions, b: CorridorPredictions, frames: list[TrackFrame]) -> int:
        """Score one frame whose truth is complete (``frames`` from ``stamp_ns`` on); returns the windows added. Each stamp once."""
        if stamp_ns in self.evaluated:
            return 0
        self.evaluated.add(stamp_ns)
        if len(self.evaluated) > 4096:
            self.evaluated = set(sorted(self.evaluated)[-2048:])
        times = np.asarray(a.step_times_s, dtype=float)
        if not len(times) or not np.allclose(times, np.asarray(b.step_times_s, dtype=float)):
            return 0
        truth = truth_at(frames, stamp_ns, times)
        both = {p.track_id for p in a.predictions} & {p.track_id for p in b.predictions} & set(truth)
        added = 0
        for tid in sorted(both):
            ades = [corridor_ades(m, tid, truth[tid]) for m in (a, b)]
            if not all(ades):
                continue
            for msg, ade in zip((a, b), ades):
                s = self.scores.setdefault(msg.mode, ModeScore())
                s.windows += 1
                s.made_sum += min(ade.values())
            added += 1
        if added:
            self.frames_scored += 1
        return added

    def line(self) -> str:
        if not self.scores:
            return "running mADE: waiting for the first frames whose 4 s future is known"
        parts = [f"<span style='color:rgb{mode_colour(m)}'>■</span> **{m}** {s.made:.2f} m" for m, s in sorted(self.scores.items())]
        n = max(s.windows for s in self.scores.values())
        return "running mADE " + " · ".join(parts) + f" ({n} vehicle windows of {self.frames_scored} frames, the same for both)"


# --------------------------------------------------------------------------- the selected vehicle


def ar_image(probs: np.ndarray, *, cell_px: int = 14) -> np.ndarray:
    """The AR input distributions (k steps × m acceleration cells) as an RGB heat image: one row per 0.4 s step, top = first."""
    p = np.clip(np.nan_to_num(np.asarray(probs, dtype=float)), 0.0, 1.0)
    if p.ndim != 2 or not p.size:
        return np.full((cell_px, cell_px, 3), 255, np.uint8)
    t = p / max(p.max(axis=1, keepdims=True).max(), 1e-9)
    white, blue = np.array([255.0, 255.0, 255.0]), np.array([20.0, 60.0, 200.0])
    rgb = (white[None, None, :] * (1 - t[..., None]) + blue[None, None, :] * t[..., None]).round().astype(np.uint8)
    img = np.repeat(np.repeat(rgb, cell_px, axis=0), cell_px, axis=1)
    img[::cell_px, :, :] = 200  # a light line between the steps
    return img


def vehicle_panel(track_id: int, pred: CorridorPredictions | None, belief: IntentionBelief | None, profiles: AccelerationProfiles | None,
                  truth: np.ndarray | None, truth_complete: bool) -> tuple[str, np.ndarray | None]:
    """Markdown for the selected vehicle and the AR heat image of its most probable corridor (None when no profile)."""
    lines = [f"**vehicle {track_id}**"]
    vb = next((v for v in belief.vehicles if v.track_id == track_id), None) if belief is not None else None
    beliefs = {c.corridor_id: c for c in vb.corridors} if vb is not None else {}
    if vb is not None:
        lines.append(f"P(stop) **{vb.p_stop:.2f}** · expected: {Manoeuvre(int(vb.expected_manoeuvre)).name.lower().replace('_', ' ')}"
                     + (f" · {vb.intersection_distance_m:.0f} m to the junction" if math.isfinite(vb.intersection_distance_m) else ""))
    mine = [p for p in pred.predictions if p.track_id == track_id] if pred is not None else []
    ades = corridor_ades(pred, track_id, truth) if (pred is not None and truth is not None and truth_complete) else {}
    if mine:
        rows = ["| corridor | P(route) | route | P(stop) | ADE vs truth |", "|:--|--:|:--|--:|--:|"]
        for p in sorted(mine, key=lambda p: -p.probability):
            b = beliefs.get(p.corridor_id)
            route = Manoeuvre(int(b.manoeuvre)).name.lower().replace("_", " ") if b is not None else "-"
            p_stop = f"{b.p_stop:.2f}" if b is not None else "-"
            ade = f"{ades[p.corridor_id]:.2f} m" if p.corridor_id in ades else "-"
            rows.append(f"| {p.corridor_id & 0xFFFF:04x} | {p.probability:.2f} | {route} | {p_stop} | {ade} |")
        lines.append("\n".join(rows))
    else:
        lines.append("no predictions for this vehicle in the shown frame")
    if truth is not None and truth_complete:
        lines.append(f"true future (4 s): known, drawn black · travelled {float(np.hypot(*np.diff(truth, axis=0).T).sum()):.1f} m"
                     + (f" · best corridor ADE {min(ades.values()):.2f} m" if ades else ""))
    else:
        lines.append("true future: not known yet (turn on ground truth: the view lags 4 s)")
    image = None
    if profiles is not None and mine:
        by_pair = profiles.by_pair()
        best = max(mine, key=lambda p: p.probability)
        prof = by_pair.get((track_id, best.corridor_id)) or next((by_pair[k] for k in by_pair if k[0] == track_id), None)
        if prof is not None:
            edges = np.asarray(profiles.input_edges_mps2, dtype=float)
            image = ar_image(prof.input_probs)
            mean = ", ".join(f"{m:+.1f}" for m in np.asarray(prof.chunk_mean_mps2)[:10])
            lines.append(f"AR acceleration distributions, corridor {prof.corridor_id & 0xFFFF:04x}: rows 0 … {len(prof.input_probs) - 1} "
                         f"(0.4 s each, next 4 s, top first), columns {edges[0]:+.1f} … {edges[-1]:+.1f} m/s² in {len(edges) - 1} cells; "
                         f"chunk means {mean} m/s²")
    elif profiles is None:
        lines.append("AR acceleration distributions: none (the pipeline binds no acceleration_profiles)")
    return "\n\n".join(lines), image


STAGES_LEGEND = ("ms: processing per input set, p50/p95 · e2e: end to end, source publish to this node's publish, p50/p95 "
                 "(– when unknown: an old recording) · lat: receive time minus stamp, p50 (– when stamps are recording time) · "
                 "q: queue · iss: issues · err: decode + core errors · drop: queue + join drops")


def stages_markdown(stats: dict[str, NodeStats], silent_s: dict[str, float], plausible_latency_ms: float) -> str:
    """The "Stages" panel: per node (sorted) two lines, then the legend.

    ``**node** · 1.5/3 ms · e2e 22/48 ms`` and ``lat 2 ms · q 0 · iss 0 ·
    err 0 · drop 0`` (errors and drops in bold when not 0); a node in
    ``silent_s`` (seconds since its last stats) says ``**silent N s**``
    after its name. ``lat`` is "–" when it is not below
    ``plausible_latency_ms`` (recording time against the wall clock).
    """
    blocks = []
    for node_id in sorted(stats):
        st = stats[node_id]
        cn = st.counters
        name = f"**{node_id}**" + (f" · **silent {silent_s[node_id]:.0f} s**" if node_id in silent_s else "")
        e2e = f"{st.e2e_ms_p50:.0f}/{st.e2e_ms_p95:.0f} ms" if math.isfinite(st.e2e_ms_p50) and math.isfinite(st.e2e_ms_p95) else "–"
        lat = f"{st.latency_ms_p50:.0f} ms" if 0 < st.latency_ms_p50 < plausible_latency_ms else "–"
        err = cn.get("decode_errors", 0) + cn.get("core_errors", 0)
        drop = cn.get("queue_drops", 0) + cn.get("join_drops", 0)
        blocks.append(
            f"{name} · {st.proc_ms_p50:.1f}/{st.proc_ms_p95:.0f} ms · e2e {e2e}<br>"
            f"lat {lat} · q {st.queue_depth} · iss {cn.get('issues', 0)} · "
            + (f"**err {err}**" if err else "err 0") + " · " + (f"**drop {drop}**" if drop else "drop 0")
        )
    return "\n\n".join(blocks + [STAGES_LEGEND])
