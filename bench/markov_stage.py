"""Benchmark of the markov_prediction core (baseline mode) per frame, by number of vehicle-corridor pairs.

Synthetic urban frames: B vehicles with one corridor each on parallel
straight lanes (speeds 0–15 m/s, a quarter of them standing), in platoons of
two where the second follows the first (so half the pairs carry the leader
restriction), plus one crossing conflict per 20 pairs (the second pass).
For B = 1, 10, 50, 200 (``--pairs``) it prints the median and p95 wall time
of ``MarkovPredictor.process`` (λ, propagation of K = 10 steps with the
interval matrix, grids and means) and the time per pair, on numpy/scipy,
torch on CPU and torch on CUDA when available. Per-frame cost should grow
about linearly with B. Prints figures, asserts nothing.

    python bench/markov_stage.py [--pairs 1,10,50,200] [--repeats 5] [--backends numpy,torch-cpu,torch-cuda]
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from pathlib import Path

import numpy as np

import bus_schemas as bs
from stages.markov_prediction import MarkovPredictionConfig, MarkovPredictor

STAMP = 1_000_000_000


def _header() -> bs.Header:
    return bs.Header(run_id="bench", frame_index=0, stamp_ns=STAMP, producer="bench")


def _corridor(cid: int, y0: float, vehicle_s: float, heading: float = 0.0, x0: float = 0.0) -> bs.Corridor:
    s = np.arange(0.0, 130.0, 0.5)
    return bs.Corridor(
        corridor_id=cid, lanelet_ids=np.array([1], np.int64), lanelet_start_s_m=np.array([0.0]),
        x_m=x0 + s * math.cos(heading), y_m=y0 + s * math.sin(heading), s_m=s, heading_rad=np.full(s.shape, heading),
        curvature_1pm=np.zeros(s.shape), width_m=np.full(s.shape, 3.5), extension_start_s_m=130.0,
        vehicle_s_m=vehicle_s, vehicle_d_m=0.0, speed_limit_mps=13.89,
    )


def _relation(track_id: int, cid: int, leader: int = -1, gap: float = math.nan, speed: float = math.nan,
              conflict: tuple[int, int, float, float] | None = None) -> bs.CorridorRelations:
    e, ei = np.zeros(0), np.zeros(0, np.int64)
    n = 1 if conflict else 0
    other_track, other_cid, s_star, other_s = conflict or (0, 0, 0.0, 0.0)
    f = lambda v: np.full(n, v, dtype=np.float64)  # noqa: E731
    return bs.CorridorRelations(
        track_id=track_id, corridor_id=cid, object_track_ids=ei, object_types=np.zeros(0, np.uint8), object_s_m=e,
        object_d_m=e, object_gap_m=e, object_speed_mps=e, leader_track_id=leader, leader_gap_m=gap, leader_speed_mps=speed,
        intersection_ids=ei, intersection_entry_s_m=e, intersection_exit_s_m=e, intersection_distance_m=e,
        intersection_entry_lanelet_ids=ei, conflict_track_ids=np.full(n, other_track, np.int64),
        conflict_corridor_ids=np.full(n, other_cid, np.int64), conflict_kinds=np.ones(n, np.uint8), conflict_s_m=f(s_star),
        conflict_other_s_m=f(other_s), conflict_x_m=f(0.0), conflict_y_m=f(0.0), conflict_distance_m=f(s_star - 5.0),
        conflict_other_distance_m=f(other_s - 5.0), conflict_other_speed_mps=f(5.0), conflict_time_s=f(3.0),
        conflict_other_time_s=f(2.0), conflict_priority=np.full(n, -1, np.int8), influencing_index=0 if n else -1,
        influencing_rule="priority_other" if n else "none",
    )


def scenario(n_pairs: int, seed: int = 0) -> tuple[bs.CorridorSet, bs.RelationSet]:
    rng = np.random.default_rng(seed)
    vehicles, relations = [], []
    for i in range(n_pairs):
        track = 100 + i
        lane_y = 4.0 * (i // 2)
        follower = i % 2 == 1
        speed = 0.0 if rng.uniform() < 0.25 else float(rng.uniform(1.0, 15.0))
        vehicle_s = 5.0 if follower else 5.0 + 20.0
        if i % 20 == 19 and i >= 2:  # a crossing road for every 20th pair
            corridor = _corridor(i, lane_y - 30.0, 5.0, heading=math.pi / 2, x0=40.0)
            relations.append(_relation(track, i))
        else:
            corridor = _corridor(i, lane_y, vehicle_s)
            if follower:
                relations.append(_relation(track, i, leader=track - 1, gap=20.0 - 4.5, speed=speed))
            elif i % 20 == 18 and i + 1 < n_pairs:
                relations.append(_relation(track, i, conflict=(track + 1, i + 1, 40.0 + 20.0, 30.0 + 4.0 * (i // 2))))
            else:
                relations.append(_relation(track, i))
        vehicles.append(bs.VehicleCorridors(
            track_id=track, agent_type=bs.AgentType.CAR, status=bs.MatchStatus.MATCHED, lanelet_id=1,
            match_distance_m=0.0, speed_mps=speed, corridors=(corridor,),
        ))
    header = _header()
    return (bs.CorridorSet(header=header, scene_id="bench", vehicles=tuple(vehicles)),
            bs.RelationSet(header=header, scene_id="bench", relations=tuple(relations)))


#: The backends ``--backends`` names (torch-cuda: skipped, said so, where there is no CUDA device).
BACKENDS = ("numpy", "torch-cpu", "torch-cuda")


def _backends(requested: list[str]) -> list[tuple[str, str, str]]:
    out = []
    for name in requested:
        if name == "numpy":
            out.append((name, "numpy", "cpu"))
        elif name == "torch-cpu":
            out.append((name, "torch", "cpu"))
        elif name == "torch-cuda":
            import torch

            if torch.cuda.is_available():
                out.append((name, "torch", "cuda"))
            else:
                print("torch-cuda: no CUDA device, skipped")
    return out


try:  # ``--pairs`` as bench/markov_kernel.py takes it; as a script, its folder is first on the module path
    from markov_kernel import parse_pairs
except ImportError:
    from bench.markov_kernel import parse_pairs


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--pairs", type=parse_pairs, default="1,10,50,200", help="comma-separated pairs per frame (default 1,10,50,200)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--backends", default=",".join(BACKENDS), help=f"comma-separated, among {', '.join(BACKENDS)} (default all)")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error(f"--repeats {args.repeats}: must be >= 1")
    backends = [b.strip() for b in args.backends.split(",") if b.strip()]
    unknown = [b for b in backends if b not in BACKENDS]
    if unknown or not backends:
        parser.error(f"--backends {args.backends}: " + (f"unknown {', '.join(unknown)}; " if unknown else "") + f"choose among {', '.join(BACKENDS)}")
    sizes = args.pairs
    try:
        import torch

        torch.set_num_threads(1)
        print(f"torch {torch.__version__}, threads 1, cuda {'yes: ' + torch.cuda.get_device_name(0) if torch.cuda.is_available() else 'no'}")
    except ImportError:
        pass
    reference = MarkovPredictor(MarkovPredictionConfig(corridor_weights="uniform", initial_box="measurement"))
    print(f"{'backend':<11} {'pairs':>5} {'frame ms p50':>13} {'p95':>8} {'ms/pair':>8}")
    for name, backend, device in _backends(backends):
        predictor = MarkovPredictor(MarkovPredictionConfig(backend=backend, device=device, corridor_weights="uniform", initial_box="measurement"), stencils=reference.stencils)
        per_pair = []
        for n in sizes:
            cs, rs = scenario(n)
            predictor.process(cs, rs)  # warm-up: lazy matrices, kernels
            times = []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                predictor.process(cs, rs)
                times.append((time.perf_counter() - t0) * 1e3)
            p50 = statistics.median(times)
            p95 = float(np.percentile(times, 95))
            per_pair.append(p50 / n)
            print(f"{name:<11} {n:>5d} {p50:>13.1f} {p95:>8.1f} {p50 / n:>8.2f}")
        if len(sizes) > 1:
            slope = np.polyfit(np.log(sizes), np.log([p * n for p, n in zip(per_pair, sizes)]), 1)[0]
            print(f"{name:<11} cost ~ pairs^{slope:.2f} over {sizes[0]}..{sizes[-1]} pairs")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
