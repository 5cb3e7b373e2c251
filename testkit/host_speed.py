"""How fast this host runs the kinds of work the pipeline does, apart from the pipeline's own code.

The speed figures of ``bench/dense.py`` and ``bench/e2e_latency.py`` moved by
30–60 % from one session's host to the next with the same code (docs/performance.md,
"Where it stands" in the README). ``reference()`` times three fixed workloads that
do not depend on this project's code, so that a figure can be read against the
host that gave it: a change of code moves the benches' figures and not these; a
change of host moves both.

- ``python``: per-object work as a stage does it per vehicle and pair: small
  slotted dataclasses built and read, dict lookups, list appends, float
  arithmetic (20,000 objects).
- ``numpy``: small-array calls as a stage makes them per frame: ``np.interp``
  of 3,100 points on 10,000 knots, a cumulative sum, an ``einsum`` over a
  (31, 10, 100) batch, boolean masks (100 rounds).
- ``numba``: a compiled scatter-add of float32 8-lane rows into a 1.3 MB table
  through an index list, the memory pattern of the Markov chain's kernel
  (2,000,000 rows; skipped, None, without numba).
- ``numba_2t``: the same scatter on two threads at once, each into its own
  table (wall ms until both are done; None without numba). Alone it would
  take ``numba``; the ratio says how much of a second core the host gives
  (the chain kernel and the footprints run on two threads, and the streaming
  stages share the cores): session 31 saw the benches move 20–25 % within a
  morning while the single-thread figures moved ~10 %. Added in session 31,
  absent from earlier JSON; the three above are unchanged (``VERSION`` 1).

Each is run ``repeats`` times (the first run of the numba part compiles or loads
it first, untimed) and the median wall ms kept. The workloads are seeded and fixed:
change them and the figures of earlier sessions no longer compare (``VERSION``).

    python -m testkit.host_speed [--repeats 5]
"""

from __future__ import annotations

import argparse
import statistics
import threading
import time
from dataclasses import dataclass

import numpy as np

#: bumped whenever a workload changes: figures of another version do not compare
VERSION = 1

try:  # pragma: no cover - the numba part is skipped where numba does not import
    import numba
except Exception:  # noqa: BLE001
    numba = None


@dataclass(slots=True)
class _Item:
    key: int
    s_m: float
    v_mps: float
    weight: float


def _python_work() -> float:
    items = [_Item(i, 0.5 * i, 0.1 * (i % 97), 1.0 / (1 + i % 13)) for i in range(20_000)]
    by_key = {item.key: item for item in items}
    total, kept = 0.0, []
    for i in range(20_000):
        item = by_key[(i * 7919) % 20_000]
        x = item.s_m + item.v_mps * 0.4 - 0.5 * item.weight
        if x > 100.0:
            kept.append(item)
        total += x * item.weight
    return total + len(kept)


def _numpy_work(rng_state: tuple) -> float:
    xp, fp, q, pos, cells = rng_state
    total = 0.0
    for _ in range(100):
        y = np.interp(q, xp, fp)
        c = np.cumsum(y)
        m = np.einsum("bkl,bl->bk", pos, cells)
        mask = (pos.max(axis=1) > 0.01) & (cells > 0)
        total += float(c[-1]) + float(m.sum()) + int(mask.sum())
    return total


def _numpy_inputs() -> tuple:
    rng = np.random.default_rng(20261205)
    xp = np.cumsum(rng.uniform(0.1, 1.0, 10_000))
    fp = rng.normal(size=10_000)
    q = rng.uniform(xp[0], xp[-1], 3_100)
    pos = rng.random((31, 10, 100))
    cells = rng.random((31, 100))
    return xp, fp, q, pos, cells


if numba is not None:

    @numba.njit(cache=True, nogil=True)
    def _scatter_rows(table, rows, weights, src):  # pragma: no cover - compiled
        """table[rows[e]:rows[e] + 8] += weights[e] * src[e % src.shape[0]] for every entry e."""
        n_src = src.shape[0]
        for e in range(rows.shape[0]):
            r = rows[e]
            w = weights[e]
            s = src[e % n_src]
            for ln in range(8):
                table[r + ln] += w * s[ln]
        return table[0]


def _numba_inputs() -> tuple:
    rng = np.random.default_rng(20261205)
    table = np.zeros(320_000 + 8, np.float32)  # (the chain's (N_s, M, N_v, 8) state: 1.3 MB)
    # rows near each other as a stencil's targets lie, with jumps between sources
    base = np.repeat(rng.integers(0, 300_000 // 8, 200_000) * 8, 10)
    rows = (base + np.tile(np.arange(10) * 80, 200_000)).astype(np.int64) % 320_000
    weights = rng.random(rows.shape[0]).astype(np.float32)
    src = rng.random((1024, 8)).astype(np.float32)
    return table, rows, weights, src


def _two_at_once(table, rows, weights, src, tables: list | None = None) -> list:
    """``_scatter_rows`` on two threads at the same time, each into its own copy of ``table`` (numba releases the GIL);
    returns the two tables. ``tables``: the two tables to scatter into, made beforehand (``reference`` makes them
    once, so that the timing holds the scatters as ``numba_ms`` does, not the copies)."""
    tables = [table.copy(), table.copy()] if tables is None else tables
    threads = [threading.Thread(target=_scatter_rows, args=(t, rows, weights, src)) for t in tables]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return tables


def _timed(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return float(statistics.median(times))


def reference(repeats: int = 5) -> dict:
    """{"version", "python_ms", "numpy_ms", "numba_ms", "numba_2t_ms" (both None without numba), "repeats"}: the median
    wall ms of each workload over ``repeats`` runs on this host, now (other load on the machine shows in them, as in
    the benches)."""
    repeats = max(1, int(repeats))
    out = {"version": VERSION, "repeats": repeats, "python_ms": _timed(_python_work, repeats)}
    inputs = _numpy_inputs()
    out["numpy_ms"] = _timed(lambda: _numpy_work(inputs), repeats)
    if numba is None:
        out["numba_ms"] = out["numba_2t_ms"] = None
    else:
        table, rows, weights, src = _numba_inputs()
        _scatter_rows(table, rows[:8], weights[:8], src)  # compiled (or loaded from numba's cache) before the timing
        out["numba_ms"] = _timed(lambda: _scatter_rows(table, rows, weights, src), repeats)
        copies = [table.copy(), table.copy()]
        out["numba_2t_ms"] = _timed(lambda: _two_at_once(table, rows, weights, src, copies), repeats)
    return out


def line(ref: dict) -> str:
    """One printed line of ``reference()``'s figures."""
    numba_ms = "–" if ref.get("numba_ms") is None else f"{ref['numba_ms']:.1f}"
    two = "–" if ref.get("numba_2t_ms") is None else f"{ref['numba_2t_ms']:.1f}"
    return (f"host reference v{ref['version']} (testkit.host_speed, median of {ref['repeats']}): python {ref['python_ms']:.1f} ms, "
            f"numpy {ref['numpy_ms']:.1f} ms, numba {numba_ms} ms, numba on two threads at once {two} ms")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=5, help="runs of each workload (the median is kept)")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error("--repeats must be >= 1")
    print(line(reference(args.repeats)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
