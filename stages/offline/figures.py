"""The evaluation's figures, drawn with matplotlib (Agg backend: no display needed).

Every function returns a ``matplotlib.figure.Figure`` (created directly,
never through pyplot, so no global figure state is kept) and ``save`` writes
it as PNG and SVG. Axes are in metres (maps) or in the units of the metric,
every figure has a title that says what and where, a legend for what is
drawn and a colour bar for what is shaded. Mode colours are the same in
every figure: hybrid blue, baseline red (the paper's), corridor_cv green,
cv grey.

Map figures (an instant of a recording, ``_Figure`` of the evaluation):

- ``grid_figure``: the paper's motion grid at 4 s — the fused grid of one
  mode at its last step as a heat map (log colour scale) over the car
  lanelets, the vehicles at t as boxes, the corridors of the scored vehicles;
- ``comparison_figure``: the paper's comparison of predicted means — per
  mode and corridor the probability-weighted mean positions over the horizon,
  opacity = the corridor's probability; the ground truth black;
- ``accel_figure``: the paper's acceleration-distribution figure — the 10
  input distributions of one car's AR profile as grey intensity, the AR
  output red, the true acceleration blue.

Report figures (from the ``--json`` dict): ``reliability_figure``,
``horizon_figure``, ``manoeuvre_figure``, ``timing_figure``.

Only the offline tools and bench scripts import this module (never a process
stage: tests/test_dependencies.py).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Iterable, Sequence

import matplotlib
import matplotlib.ticker

matplotlib.use("Agg")  # no display; before anything draws

import numpy as np  # noqa: E402
from matplotlib.collections import LineCollection, PolyCollection  # noqa: E402
from matplotlib.colors import LogNorm  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402

MODE_COLOURS = {"hybrid": "#1f5fbf", "baseline": "#d62728", "corridor_cv": "#2ca02c", "cv": "#7f7f7f"}
MODE_LABELS = {"hybrid": "hybrid-IAMP", "baseline": "baseline (rule-based IAMP)", "corridor_cv": "corridor CV", "cv": "Cartesian CV"}
LANELET_FACE = "#e4e4e4"
LANELET_EDGE = "#b0b0b0"
PNG_DPI = 100


def new_figure(size_in: tuple[float, float]) -> Figure:
    """A Figure (no pyplot state) with constrained layout."""
    return Figure(figsize=size_in, layout="constrained")


def mode_colour(mode: str) -> str:
    return MODE_COLOURS.get(mode, "#9467bd")


def mode_label(mode: str) -> str:
    return MODE_LABELS.get(mode, mode)


def save(fig: Figure, directory: Path, stem: str, formats: Sequence[str] = ("png", "svg"), dpi: int = PNG_DPI) -> list[Path]:
    """Write ``fig`` as ``directory/stem.<format>`` for each format; returns the paths."""
    directory.mkdir(parents=True, exist_ok=True)
    out = []
    for fmt in formats:
        path = directory / f"{stem}.{fmt}"
        fig.savefig(path, dpi=dpi, format=fmt, metadata={"Date": None} if fmt == "svg" else None)
        out.append(path)
    return out


# --------------------------------------------------------------------------- map figures


def _map_axes(fig: Figure, rect=None):
    ax = fig.add_subplot(111) if rect is None else fig.add_axes(rect)
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("x east (m)")
    ax.set_ylabel("y north (m)")
    ax.set_facecolor("white")
    return ax


def draw_lanelets(ax, polygons: Iterable[np.ndarray], face: str = LANELET_FACE, edge: str = LANELET_EDGE, zorder: float = 0) -> None:
    """Car lanelets as filled polygons (each (n, 2) in metres: left bound then right bound reversed)."""
    polys = [p for p in polygons if p.shape[0] >= 3]
    if polys:
        ax.add_collection(PolyCollection(polys, facecolors=face, edgecolors=edge, linewidths=0.4, zorder=zorder))


def road_polygons(road_map) -> list[np.ndarray]:
    """The car lanelets of a ``RoadMap`` as polygons."""
    if road_map is None:
        return []
    out = []
    for lanelet_id in road_map.lanelet_ids:
        info = road_map.lanelet(lanelet_id)
        out.append(np.vstack([info.left_bound_m, info.right_bound_m[::-1]]))
    return out


def vehicle_boxes(frame, track_ids: Iterable[int] | None = None) -> dict[int, np.ndarray]:
    """Oriented boxes (4, 2) of the vehicles of a TrackFrame (only ``track_ids`` when given)."""
    wanted = None if track_ids is None else set(int(t) for t in track_ids)
    out = {}
    for row, track_id in enumerate(frame.track_ids.tolist()):
        if wanted is not None and track_id not in wanted:
            continue
        x, y, yaw = float(frame.x_m[row]), float(frame.y_m[row]), float(frame.yaw_rad[row])
        length, width = float(frame.length_m[row]), float(frame.width_m[row])
        if not all(math.isfinite(v) for v in (x, y, yaw, length, width)):
            continue
        c, s = math.cos(yaw), math.sin(yaw)
        corners = np.array([(length / 2, width / 2), (length / 2, -width / 2), (-length / 2, -width / 2), (-length / 2, width / 2)])
        out[track_id] = np.column_stack([x + corners[:, 0] * c - corners[:, 1] * s, y + corners[:, 0] * s + corners[:, 1] * c])
    return out


def draw_boxes(ax, boxes: dict[int, np.ndarray], face, edge="black", zorder: float = 5, labels: bool = False) -> None:
    if not boxes:
        return
    ax.add_collection(PolyCollection(list(boxes.values()), facecolors=face, edgecolors=edge, linewidths=0.8, zorder=zorder))
    for b in boxes.values():  # a heading tick: centre to the front edge
        centre, front = b.mean(axis=0), 0.5 * (b[0] + b[1])
        ax.plot([centre[0], front[0]], [centre[1], front[1]], color=edge, lw=0.8, zorder=zorder + 0.1)
    if labels:
        for track_id, b in boxes.items():
            centre = b.mean(axis=0)
            ax.annotate(str(track_id), centre, xytext=(0, 6), textcoords="offset points", ha="center", fontsize=7.5, zorder=zorder + 0.2,
                        bbox=dict(boxstyle="round,pad=0.1", fc="white", ec="none", alpha=0.7))


def _extent(points: Sequence[np.ndarray], margin_m: float, min_size_m: float = 40.0) -> tuple[float, float, float, float]:
    allp = np.concatenate([np.asarray(p, float).reshape(-1, 2) for p in points if np.asarray(p).size])
    allp = allp[np.isfinite(allp).all(axis=1)]
    lo, hi = allp.min(axis=0) - margin_m, allp.max(axis=0) + margin_m
    centre, half = 0.5 * (lo + hi), np.maximum(0.5 * (hi - lo), 0.5 * min_size_m)
    return float(centre[0] - half[0]), float(centre[0] + half[0]), float(centre[1] - half[1]), float(centre[1] + half[1])


def _fit(fig: Figure, ax, x0: float, x1: float, y0: float, y1: float, extra_width_in: float, map_height_in: float = 5.6) -> None:
    """Set the map window, widened so that its aspect lies in [0.7, 1.6] (width / height), and size the figure to it (no
    empty bands beside an equal-aspect map)."""
    dx, dy = x1 - x0, y1 - y0
    if dx / dy > 1.6:
        grow = (dx / 1.6 - dy) / 2
        y0, y1 = y0 - grow, y1 + grow
    elif dx / dy < 0.7:
        grow = (dy * 0.7 - dx) / 2
        x0, x1 = x0 - grow, x1 + grow
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    fig.set_size_inches(map_height_in * (x1 - x0) / (y1 - y0) + extra_width_in, map_height_in + 1.3)


def _instant_title(fig_data) -> str:
    return f"{fig_data.recording} sequence {fig_data.sequence}, t = {fig_data.stamp_ns * 1e-9:.1f} s ({fig_data.n_windows} scored vehicles)"


def grid_figure(fig_data, mode: str, *, min_value: float = 1e-4) -> Figure:
    """The motion grid of ``mode`` at the last prediction step over the map (module docstring)."""
    prediction = fig_data.predictions[mode]
    step = prediction.step_times_s.shape[0] - 1
    t_last = float(prediction.step_times_s[step])
    fig = Figure(figsize=(7.6, 6.4), layout="constrained")
    ax = _map_axes(fig)
    road = fig_data.scene_maps.get(fig_data.scene).road_map
    draw_lanelets(ax, road_polygons(road))
    gf = prediction.grid_frame
    cells, values = prediction.fused_grid.step(step, gf.n_cells)
    keep = values >= min_value
    pts = [np.array(list(fig_data.starts.values()))] + list(fig_data.truths.values())
    x0, x1, y0, y1 = _extent(pts, 12.0)
    mappable = None
    if np.any(keep):
        rows, cols = np.divmod(cells[keep], gf.n_cols)
        r0, r1, c0, c1 = rows.min(), rows.max() + 1, cols.min(), cols.max() + 1
        dense = np.full((r1 - r0, c1 - c0), np.nan)
        dense[rows - r0, cols - c0] = values[keep]
        extent = (gf.origin_x_m + c0 * gf.cell_m, gf.origin_x_m + c1 * gf.cell_m, gf.origin_y_m + r0 * gf.cell_m, gf.origin_y_m + r1 * gf.cell_m)
        vmax = max(float(values[keep].max()), min_value * 10)
        mappable = ax.imshow(np.ma.masked_invalid(dense), origin="lower", extent=extent, cmap="YlOrRd",
                             norm=LogNorm(vmin=min_value, vmax=vmax), interpolation="nearest", zorder=2, alpha=0.95)
        x0, x1 = min(x0, extent[0] - 3), max(x1, extent[1] + 3)
        y0, y1 = min(y0, extent[2] - 3), max(y1, extent[3] + 3)
    corridors = []
    if fig_data.corridor_set is not None:
        for vehicle in fig_data.corridor_set.vehicles:
            if vehicle.track_id in fig_data.truths:
                corridors += [np.column_stack([c.x_m, c.y_m]) for c in vehicle.corridors]
    if corridors:
        ax.add_collection(LineCollection(corridors, colors="#3b6ea8", linewidths=0.8, linestyles=(0, (4, 3)), alpha=0.8, zorder=3))
    scored = vehicle_boxes(fig_data.frame, fig_data.truths) if fig_data.frame is not None else {}
    others = {}
    if fig_data.frame is not None:
        others = {t: b for t, b in vehicle_boxes(fig_data.frame).items() if t not in scored and _inside(b, (x0, x1, y0, y1))}
    draw_boxes(ax, others, face=(0.6, 0.6, 0.6, 0.3), edge="#707070", zorder=4)
    draw_boxes(ax, scored, face=(0.25, 0.4, 0.75, 0.3), edge="#1a2f6b", zorder=5, labels=True)
    _fit(fig, ax, x0, x1, y0, y1, extra_width_in=2.2 if mappable is not None else 1.0)
    if mappable is not None:
        bar = fig.colorbar(mappable, ax=ax, shrink=1.0, pad=0.02)
        bar.set_label(f"P(a vehicle centre in the {gf.cell_m:g} m cell) at t + {t_last:.1f} s (log scale)")
    handles = [
        Patch(facecolor=LANELET_FACE, edgecolor=LANELET_EDGE, label="car lanelets"),
        Line2D([], [], color="#3b6ea8", lw=0.8, ls=(0, (4, 3)), label="corridors of the scored vehicles"),
        Patch(facecolor=(0.25, 0.4, 0.75, 0.3), edgecolor="#1a2f6b", label="scored vehicle at t (id)"),
        Patch(facecolor=(0.6, 0.6, 0.6, 0.3), edgecolor="#707070", label="other vehicle at t"),
    ]
    ax.legend(handles=handles, loc="upper left", fontsize=8, framealpha=0.9)
    ax.set_title(f"Motion grid at {t_last:.1f} s, {mode_label(mode)}\n{_instant_title(fig_data)}", fontsize=10)
    return fig


def _inside(box: np.ndarray, window) -> bool:
    x0, x1, y0, y1 = window
    c = box.mean(axis=0)
    return x0 <= c[0] <= x1 and y0 <= c[1] <= y1


def comparison_figure(fig_data, modes: Sequence[str]) -> Figure:
    """Predicted mean positions over the horizon of ``modes`` against the ground truth (module docstring)."""
    fig = Figure(figsize=(7.6, 6.4), layout="constrained")
    ax = _map_axes(fig)
    road = fig_data.scene_maps.get(fig_data.scene).road_map
    draw_lanelets(ax, road_polygons(road))
    pts = [np.array(list(fig_data.starts.values()))] + list(fig_data.truths.values())
    for rank, mode in enumerate(reversed(modes)):  # the first mode (hybrid) on top; the ones below wider, so that both show
        width = 1.4 + 1.2 * (len(modes) - 1 - rank)
        prediction = fig_data.predictions[mode]
        colour = matplotlib.colors.to_rgb(mode_colour(mode))
        for b, pair in enumerate(prediction.pairs):
            if pair.track_id not in fig_data.truths:
                continue
            means = prediction.mean_xy_m[b]
            ok = np.isfinite(means).all(axis=1)
            if not ok.any():
                continue
            line = np.vstack([np.array(fig_data.starts[pair.track_id])[None], means[ok]])
            alpha = 0.15 + 0.85 * float(min(max(pair.probability, 0.0), 1.0))
            ax.plot(line[:, 0], line[:, 1], "-", color=colour, alpha=alpha, lw=width, zorder=4 + rank * 0.1, solid_capstyle="round")
            ax.plot(means[ok, 0], means[ok, 1], "o", color=colour, alpha=alpha, ms=1.5 + width, mec="none", zorder=4 + rank * 0.1)
            pts.append(means[ok])
    for track_id, truth in fig_data.truths.items():
        line = np.vstack([np.array(fig_data.starts[track_id])[None], truth])
        ax.plot(line[:, 0], line[:, 1], "-", color="black", lw=1.2, zorder=5)
        ax.plot(truth[:, 0], truth[:, 1], "o", color="black", ms=2.4, zorder=5)
    boxes = vehicle_boxes(fig_data.frame, fig_data.truths) if fig_data.frame is not None else {}
    draw_boxes(ax, boxes, face="none", edge="#555555", zorder=3, labels=True)
    _fit(fig, ax, *_extent(pts, 6.0), extra_width_in=1.0)
    handles = [Line2D([], [], color=mode_colour(m), marker="o", ms=3, lw=1.4 + 1.2 * i,
                      label=f"{mode_label(m)}: mADE {fig_data.scores.get(m, {}).get('mADE_m', float('nan')):.2f} m,"
                            f" mFDE {fig_data.scores.get(m, {}).get('mFDE_m', float('nan')):.2f} m") for i, m in enumerate(modes)]
    handles += [Line2D([], [], color="black", marker="o", ms=3, lw=1.2, label="ground truth"),
                Patch(facecolor="none", edgecolor="#555555", label="vehicle at t (id)"),
                Patch(facecolor=LANELET_FACE, edgecolor=LANELET_EDGE, label="car lanelets")]
    ax.legend(handles=handles, loc="upper left", fontsize=8, framealpha=0.9,
              title="mean positions every 0.4 s to 4 s; opacity = corridor probability", title_fontsize=8)
    ax.set_title(f"Predicted means vs ground truth, {' vs '.join(mode_label(m) for m in modes)}\n{_instant_title(fig_data)}", fontsize=10)
    return fig


def accel_figure(example: dict[str, Any]) -> Figure:
    """The paper's acceleration-distribution figure for one car (module docstring)."""
    edges, probs, step_s, chunk_s = example["edges"], example["probs"], example["step_s"], example["chunk_s"]
    n = example["ar"].shape[0]
    fig = Figure(figsize=(7.0, 3.8), layout="constrained")
    ax = fig.add_subplot(111)
    t_edges = np.arange(probs.shape[0] + 1) * chunk_s
    mesh = ax.pcolormesh(t_edges, edges, probs.T, cmap="Greys", vmin=0.0, vmax=max(float(probs.max()), 1e-9), shading="flat")
    t = np.arange(1, n + 1) * step_s
    ax.plot(t, example["ar"], color="#d62728", lw=1.6, label="AR model output $y_t$")
    ax.plot(t, example["true"], color="#1f5fbf", lw=1.6, label="true acceleration")
    lo, hi = min(float(edges[0]), -3.0), max(float(edges[-1]), 2.0)
    ax.set_ylim(lo, hi)
    ax.set_xlim(0.0, max(float(t_edges[-1]), n * step_s))
    ax.axhline(0.0, color="#888888", lw=0.5)
    ax.set_xlabel("time after the instant (s)")
    ax.set_ylabel("acceleration (m/s²)")
    bar = fig.colorbar(mesh, ax=ax, pad=0.02)
    bar.set_label(f"P(acceleration cell) per {chunk_s:g} s step")
    ax.legend(loc="upper right", fontsize=8, framealpha=0.9)
    err = float(np.abs(example["ar"] - example["true"]).mean())
    ax.set_title(f"AR acceleration distributions, {example['recording']} sequence {example['sequence']} car {example['track_id']},"
                 f" t = {example['stamp_ns'] * 1e-9:.1f} s\n{probs.shape[0]} distributions (grey), mean |AR − true| {err:.2f} m/s²", fontsize=10)
    return fig


# --------------------------------------------------------------------------- report figures


_SPLITS = (("overall", "all cars"), ("slow", "start speed ≤ 2 m/s"), ("fast", "start speed > 2 m/s"))


def reliability_figure(report: dict[str, Any]) -> Figure:
    """Observed coverage of the highest-probability regions against their nominal level, per mode and speed split."""
    fig = Figure(figsize=(11.0, 4.3), layout="constrained")
    axes = fig.subplots(1, 3, sharey=True)
    for ax, (split, title) in zip(axes, _SPLITS):
        ax.plot([0, 1], [0, 1], color="#999999", lw=0.8, ls="--", label="calibrated (observed = nominal)")
        for mode, res in report["modes"].items():
            cal = res.get("calibration")
            if not cal:
                continue
            ax.plot(cal["levels"], cal[split]["coverage"], "o-", color=mode_colour(mode), ms=3.5, lw=1.4, label=mode_label(mode))
        ax.axvline(0.5, color="#dddddd", lw=0.6, zorder=0)
        ax.axvline(0.9, color="#dddddd", lw=0.6, zorder=0)
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1)
        ax.grid(alpha=0.3)
        ax.set_xlabel("nominal level of the region")
        first = next(iter(report["modes"].values()))
        ax.set_title(f"{title} ({first['calibration'][split]['steps'] if 'calibration' in first else 0} steps)", fontsize=10)
    axes[0].set_ylabel("share of true positions inside")
    axes[0].legend(loc="upper left", fontsize=8)
    fig.suptitle("Reliability of the motion grids: highest-probability regions (centre-point grids, 0.4–4 s)", fontsize=10)
    return fig


def horizon_figure(report: dict[str, Any]) -> Figure:
    """Mean displacement error of the mADE corridor against the prediction horizon, per mode and speed split."""
    fig = Figure(figsize=(10.5, 3.6), layout="constrained")
    axes = fig.subplots(1, 3, sharey=True)
    for ax, (split, title) in zip(axes, _SPLITS):
        windows = 0
        for mode, res in report["modes"].items():
            e = res.get("error_by_step_m")
            if not e:
                continue
            windows = e[split]["windows"]
            ax.plot(e["t_s"], e[split]["mean"], "o-", color=mode_colour(mode), ms=3, lw=1.4, label=mode_label(mode))
        ax.set_xlabel("prediction horizon (s)")
        ax.set_xlim(0, 4.2)
        ax.set_xticks([0, 1, 2, 3, 4])
        ax.grid(alpha=0.3)
        ax.set_title(f"{title} ({windows} windows)", fontsize=10)
    axes[0].set_ylabel("mean displacement error (m)")
    axes[0].set_ylim(bottom=0)
    axes[0].legend(loc="upper left", fontsize=8)
    fig.suptitle("Error against horizon (the corridor with the smallest ADE, as mADE)", fontsize=10)
    return fig


def manoeuvre_figure(report: dict[str, Any]) -> Figure:
    """mADE, along-track bias and cross-track RMS at 4 s by manoeuvre class of the true future, per mode."""
    modes = report["modes"]
    first = next(iter(modes.values()))
    classes = list(first.get("by_manoeuvre", {}))
    fig = Figure(figsize=(11.5, 4.3), layout="constrained")
    axes = fig.subplots(1, 3)
    x = np.arange(len(classes))
    width = 0.8 / max(len(modes), 1)
    short = {"accelerates": "accel.", "keeps_speed": "keeps"}
    labels = [f"{short.get(c, c)}\n({first['by_manoeuvre'][c]['windows']})" for c in classes]
    for i, (mode, res) in enumerate(modes.items()):
        off = (i - (len(modes) - 1) / 2) * width
        made = [res["by_manoeuvre"][c]["mADE_m"] for c in classes]
        along = [res.get("along_track_m", {}).get("by_manoeuvre", {}).get(c, {}).get("4s", {}).get("mean", float("nan")) for c in classes]
        cross = [res.get("cross_track_m", {}).get("by_manoeuvre", {}).get(c, {}).get("4s", {}).get("rms", float("nan")) for c in classes]
        for ax, vals in zip(axes, (made, along, cross)):
            ax.bar(x + off, np.nan_to_num(np.asarray(vals, float)), width, color=mode_colour(mode), label=mode_label(mode))
    titles = ("mADE (m)", "along-track bias at 4 s (m, + = ahead of the truth)", "cross-track RMS at 4 s (m)")
    for ax, title in zip(axes, titles):
        ax.set_xticks(x)
        ax.set_xticklabels(labels, fontsize=8)
        ax.set_xlabel("manoeuvre of the true future (windows)", fontsize=8)
        ax.set_ylabel(title.split(" (")[0] + " (m)", fontsize=8)
        ax.set_title(title, fontsize=10)
        ax.axhline(0.0, color="black", lw=0.6)
        ax.grid(axis="y", alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=len(labels), fontsize=8)
    fig.suptitle("Error by manoeuvre class of the true future", fontsize=10)
    return fig


def timing_figure(frame_ms: dict[str, Sequence[float]], vehicles: dict[str, Sequence[int]], ar_ms_median: float | None = None) -> Figure:
    """Compute time of one prediction frame against the vehicles predicted in it, per mode (points and medians)."""
    fig = Figure(figsize=(7.2, 4.4), layout="constrained")
    ax = fig.add_subplot(111)
    rng = np.random.default_rng(0)
    for mode, ms in frame_ms.items():
        ms, n = np.asarray(ms, float), np.asarray(vehicles.get(mode, []), float)
        if ms.size == 0 or ms.size != n.size:
            continue
        colour = mode_colour(mode)
        ax.scatter(n + rng.uniform(-0.2, 0.2, n.size), ms, s=6, color=colour, alpha=0.35, lw=0)
        counts = np.unique(n)
        med = [float(np.median(ms[n == c])) for c in counts]
        ax.plot(counts, med, "o-", color=colour, ms=3.5, lw=1.6, label=f"{mode_label(mode)} (median {np.median(ms):.1f} ms)")
    ax.set_yscale("log")
    ax.xaxis.set_major_locator(matplotlib.ticker.MaxNLocator(integer=True))
    ax.set_xlabel("vehicles predicted in the frame")
    ax.set_ylabel("prediction time per frame (ms, log)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8, loc="upper left", title="line: median per vehicle count; dots: frames", title_fontsize=8)
    note = f"\nhybrid's AR inference not included (median {ar_ms_median:.1f} ms per frame)" if ar_ms_median is not None else ""
    ax.set_title("Compute time per frame against vehicles (MarkovPredictor.process, grid included)" + note, fontsize=10)
    return fig


__all__ = [
    "MODE_COLOURS", "accel_figure", "comparison_figure", "draw_boxes", "draw_lanelets", "grid_figure", "horizon_figure",
    "manoeuvre_figure", "mode_colour", "mode_label", "reliability_figure", "road_polygons", "save", "timing_figure", "vehicle_boxes",
]


def signal_map_figure(smap, road_map, title: str) -> Figure:
    """The map with the KML lanes (``stages.lib.maps.signals.SignalMap``) and the matched stop lines coloured by signal group."""
    fig = new_figure((11, 10))
    fig.set_dpi(110)
    ax = fig.add_subplot()
    for lid in road_map.lanelet_ids:
        info = road_map.lanelet(lid)
        poly = np.vstack([info.left_bound_m, info.right_bound_m[::-1]])
        ax.fill(poly[:, 0], poly[:, 1], color="0.9", ec="0.6", lw=0.4, zorder=1)
        c = info.centreline.points_m
        ax.plot(c[:, 0], c[:, 1], color="0.75", lw=0.5, zorder=2)
    cmap = matplotlib.colormaps["tab20"]
    groups = smap.signal_groups
    colour = {g: cmap(i % 20) for i, g in enumerate(groups)}
    for lane in smap.lanes:
        p = lane.points_m
        style = dict(color="0.35", lw=0.9, zorder=3) if lane.matched else dict(color="tab:red", lw=0.9, ls="--", zorder=3)
        ax.plot(p[:, 0], p[:, 1], **style)
        ax.annotate(f"{lane.lane_id}", p[0], fontsize=6, color=style["color"], zorder=6)
    for lane in smap.matched:
        if not lane.signalised or lane.stop_lanelet_id is None:
            continue
        info = road_map.lanelet(lane.stop_lanelet_id)
        c = info.centreline
        xy = c.to_xy(lane.stop_s_m)[0]
        h = float(c.heading_at(lane.stop_s_m))
        half = 0.5 * info.width_m
        nx, ny = -math.sin(h) * half, math.cos(h) * half
        gs = lane.signal_groups
        for k, g in enumerate(gs):  # a lane with two groups: the line split in two colours
            a, b = -1 + 2 * k / len(gs), -1 + 2 * (k + 1) / len(gs)
            ax.plot([xy[0] + a * nx, xy[0] + b * nx], [xy[1] + a * ny, xy[1] + b * ny], color=colour[g], lw=4, solid_capstyle="butt", zorder=5)
        ax.annotate("g" + "/".join(str(g) for g in gs), (xy[0] + nx, xy[1] + ny), fontsize=7, zorder=7,
                    xytext=(2, 2), textcoords="offset points")
    handles = [Line2D([], [], color=colour[g], lw=4, label=f"group {g}") for g in groups]
    handles += [Line2D([], [], color="0.35", lw=1, label="KML lane (matched)"),
                Line2D([], [], color="tab:red", lw=1, ls="--", label="KML lane (unmatched)")]
    ax.legend(handles=handles, fontsize=7, loc="upper left", ncol=2)
    allp = np.vstack([road_map.lanelet(x).centreline.points_m for x in road_map.lanelet_ids])
    lo, hi = allp.min(axis=0) - 10, allp.max(axis=0) + 10
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_xlabel("x east (m)")
    ax.set_ylabel("y north (m)")
    ax.set_title(title, fontsize=9)
    return fig
