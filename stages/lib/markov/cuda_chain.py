"""The hybrid chain's whole run (``kernels.speed_priority_run``) as one CUDA kernel launch per frame (numba.cuda).

``speed_priority_run`` takes the arguments of ``kernels.speed_priority_run`` and returns what it returns: every step's
Υ(τ) (and Υ([0, τ])) with the leak past the window, the marginals, pruning with the pruned mass put back, and after
step k (where ``has_input[k]``) Γ = colnorm(diag(λ) Ψ) with λ the speed restriction's priority for the preference
``preferences[k]`` at the states holding mass, where not ``has_input[k]`` the identity.

One CUDA block per pair runs all K steps (the pairs are independent): its threads share out the pair's states, with
a barrier between the phases of a step. Per step:

1. sources: the leak past the window's end and Υ([0, τ])'s position marginal (scattered with atomic adds into the
   block's shared memory);
2. targets: p⁻ = Υ(τ) p gathered per target state from the stencil grouped by target (``gather_tables``), no atomics;
3. per (s, v) cell: the marginals, pruning, and whether the cell holds mass;
4. per (s, v) cell holding mass: λ_speed there (the interpolation of ``kernels.SpeedRestriction``), the priority
   r_α = min(m_α, q_α + carry) from the highest input down, Γ, and the renormalisation of the pruned mass.

The pair's state lives in global memory (``(B, N_s, M, N_v)`` float32, kept on the device between calls, with the
tables); its window (the rows and the velocity cells holding mass) moves with the mass, as the CPU kernel's does. The
arithmetic is the CPU kernel's, but the order of its sums is not (the gather sums a target's terms in table order,
the marginals' float64 sums come in by atomic adds in any order): positions agree with the CPU kernel to float32
rounding, under 1e-6 (tests/stages/test_markov_cuda_chain.py: on numba's CUDA simulator where there is no GPU, and on
the GPU where there is one; it passed on an H200).

Limits (``supports``): N_s <= 1024, N_v <= 128, M <= 32 inputs, J <= 16 speed profiles per pair.
"""

from __future__ import annotations

import math
import threading
import time
import warnings

import numpy as np

if not hasattr(np, "row_stack"):  # numba-cuda (0.30) registers an overload of np.row_stack, which numpy 2.5 removed;
    np.row_stack = np.vstack  # it was vstack's alias: give numba-cuda the name before it compiles (nothing else reads it)

try:  # numba.cuda imports without a GPU; ``available()`` asks whether there is one it can use
    import numba
    from numba import cuda

    _IMPORT_ERROR: str | None = None
except Exception as exc:  # noqa: BLE001 - any import failure: no CUDA chain
    numba = None
    cuda = None
    _IMPORT_ERROR = f"{type(exc).__name__}: {exc}"

MAX_S, MAX_V, MAX_IN, MAX_J = 1024, 128, 32, 16
#: threads per block (one block per pair); a multiple of 32
THREADS = 256


def unavailable_reason() -> str | None:
    """None where a CUDA GPU can run the kernel, else why not (in words)."""
    if cuda is None:
        return f"numba.cuda does not import ({_IMPORT_ERROR})"
    try:
        if not cuda.is_available():
            return "numba.cuda finds no CUDA GPU (driver, device or NVVM missing)"
    except Exception as exc:  # noqa: BLE001 - a broken CUDA setup is reported, not raised
        return f"numba.cuda: {type(exc).__name__}: {exc}"
    return None


def available() -> bool:
    return unavailable_reason() is None


def device_index(device: str) -> int:
    """The GPU index of "cuda" (0) or "cuda:N"; ValueError for anything else."""
    if device == "cuda":
        return 0
    head, _, tail = device.partition(":")
    if head != "cuda" or not tail.isdigit():
        raise ValueError(f"device = {device!r}: expected 'cuda' or 'cuda:N'")
    return int(tail)


def supports(n_s: int, n_v: int, n_in: int, n_j: int) -> bool:
    """Whether the kernel's fixed-size shared and local arrays hold a grid of this size."""
    return n_s <= MAX_S and n_v <= MAX_V and n_in <= MAX_IN and n_j <= MAX_J


def gather_tables(ptr: np.ndarray, v_to: np.ndarray, offset: np.ndarray, weight: np.ndarray, n_in: int, n_v: int):
    """``kernels.stencil_tables``' entries regrouped by target row (α, j′): ``tptr`` ((M·N_v + 1,) int32, the entries
    of target row α·N_v + j′ are tptr[r]:tptr[r + 1]), their source velocity cells ``tv`` and s-offsets ``td``
    (int32) and ``tw`` (float32), in (offset, source velocity) order."""
    n_rows = n_in * n_v
    counts = np.diff(np.asarray(ptr, dtype=np.int64))
    src = np.repeat(np.arange(n_rows, dtype=np.int64), counts)
    a = src // n_v
    v_src = src % n_v
    target = a * n_v + np.asarray(v_to, dtype=np.int64)
    order = np.lexsort((v_src, np.asarray(offset, dtype=np.int64), target))
    tptr = np.zeros(n_rows + 1, np.int64)
    np.add.at(tptr, target + 1, 1)
    return (np.cumsum(tptr).astype(np.int32), v_src[order].astype(np.int32), np.asarray(offset)[order].astype(np.int32),
            np.asarray(weight, dtype=np.float32)[order])


if cuda is not None:
    _f32 = numba.float32
    _f64 = numba.float64

    @cuda.jit(device=True, inline=True)
    def _speed_values(b, l, vi, xp, fp, start, bucket, inv_h, cell_s, v_c, a_c, w32, tau, n_query, m, count):  # pragma: no cover - compiled
        """λ_speed (M,) at the state (b, s-cell l, v-cell vi) into ``m``: ``kernels._speed_fill``'s loop body, ported
        (a CUDA kernel cannot call a CPU-compiled function). One plain-Python body compiled for both targets was tried
        (session 23): it cost the CPU's fill 43 % (``SpeedRestriction.full()`` of 50 pairs 17.8 -> 25.5 ms), so the
        CPU keeps its hand-inlined loop; tests/stages/test_markov_cuda_chain.py binds the two."""
        n_in = a_c.shape[0]
        n_j = fp.shape[0]
        total = _f32(0.0)
        for jj in range(n_j):
            total += w32[jj]
        a0 = a_c[0]
        inv_da = (n_in - 1) / (a_c[n_in - 1] - a_c[0]) if n_in > 1 else 0.0
        lo = start[b]
        n = start[b + 1] - lo
        v = v_c[vi]
        x = cell_s[b, l] + v * tau
        if math.isnan(x):
            j = -2
        elif x > xp[lo + n - 1]:
            j = n
        elif x < xp[lo]:
            j = -1
        else:
            k = int((x - xp[lo]) * inv_h[lo])
            k = min(max(k, 0), n - 1)
            j = bucket[lo + k]
            while j > 0 and xp[lo + j] > x:
                j -= 1
            while j + 1 < n and xp[lo + j + 1] <= x:
                j += 1
        inner = j >= 0 and j < n - 1 and xp[lo + j] != x
        dx, rdx, off = 1.0, 0.0, 0.0
        if inner:
            dx = xp[lo + j + 1] - xp[lo + j]
            rdx = 1.0 / dx
            off = x - xp[lo + j]
        c_min = n_in
        for jj in range(n_j):
            if inner:
                y0 = fp[jj, lo + j]
                y1 = fp[jj, lo + j + 1]
                if n <= n_query:
                    slope = (y1 - y0) * rdx
                else:
                    slope = (y1 - y0) / dx
                val = slope * off + y0
                if math.isnan(val):
                    val = slope * (x - xp[lo + j + 1]) + y1
                    if math.isnan(val) and y0 == y1:
                        val = y0
            elif j == -2:
                val = x
            elif j == -1:
                val = fp[jj, lo]
            elif j >= n - 1:
                val = fp[jj, lo + n - 1]
            else:
                val = fp[jj, lo + j]
            threshold = (val - v) / tau
            g = (threshold - a0) * inv_da
            if g < 0.0:
                c = 0
            elif g >= n_in:
                c = n_in
            else:
                c = int(g) + 1
            while c > 0 and not (a_c[c - 1] <= threshold):
                c -= 1
            while c < n_in and a_c[c] <= threshold:
                c += 1
            count[jj] = c
            c_min = min(c_min, c)
        for a in range(n_in):
            if a < c_min:
                m[a] = total
            else:
                acc = _f32(0.0)
                for jj in range(n_j):
                    if a < count[jj]:
                        acc += w32[jj]
                m[a] = acc

    @cuda.jit(device=True, inline=True)
    def _state_at(idx, first, n_in, v_lo, n_w):  # pragma: no cover - compiled
        """The (s, α, v) of the ``idx``-th state of rows from ``first``, each row its M inputs × the v-cells
        [v_lo, v_lo + n_w) (the order the block's threads share the window's states out in)."""
        width = n_in * n_w
        rem = idx % width
        return first + idx // width, rem // n_w, v_lo + rem % n_w

    @cuda.jit(cache=True)
    def _chain_kernel(inp, vel0, pos0, outside0, n_steps, tptr, tv, td, tw, ptr, offset, weight, iptr, ioffset, iweight, n_d,
                      dv_lo, dv_hi, with_interval, threshold, psi, prefs, has_input, forbid, xp, fp, start, bucket, inv_h, cell_s, v_c, a_c,
                      w32, tau, cur, nxt, mark, positions, velocities, ipositions, outsides, ioutsides, pruned,
                      totals):  # pragma: no cover - compiled
        b = cuda.blockIdx.x
        tid = cuda.threadIdx.x
        nt = cuda.blockDim.x
        n_in = inp.shape[1]
        n_v = vel0.shape[1]
        n_s = pos0.shape[1]
        n_query = n_v * n_s
        pos_sh = cuda.shared.array(MAX_S, numba.float64)
        ipos_sh = cuda.shared.array(MAX_S, numba.float64)
        vel_sh = cuda.shared.array(MAX_V, numba.float64)
        acc_sh = cuda.shared.array(4, numba.float64)  # leaked, interval leaked, kept, total
        f_sh = cuda.shared.array(2, numba.float32)  # outside, factor
        win = cuda.shared.array(8, numba.int32)  # rows first, last; new first, new last; v-cells low, high; new low, high
        m = cuda.local.array(MAX_IN, numba.float32)
        lam = cuda.local.array(MAX_IN, numba.float32)
        ratio = cuda.local.array(MAX_IN, numba.float32)
        x_in = cuda.local.array(MAX_IN, numba.float32)
        count = cuda.local.array(MAX_J, numba.int64)
        zero = _f32(0.0)
        if tid == 0:
            first, last, v_lo, v_hi = -1, -1, n_v, -1
            for s in range(n_s):
                if pos0[b, s] > 0:
                    if first < 0:
                        first = s
                    last = s
            for v in range(n_v):
                if vel0[b, v] > 0:
                    v_lo = min(v_lo, v)
                    v_hi = v
            if v_hi < 0:
                first, last = -1, -1
            win[0] = first
            win[1] = last
            win[4] = v_lo
            win[5] = v_hi
            f_sh[0] = outside0[b]
        cuda.syncthreads()
        first = win[0]
        last = win[1]
        if first >= 0:  # the state's rows [first, last], in each the v-cells [v_lo, v_hi] (the others are never read)
            v_lo = win[4]
            n_w = win[5] - v_lo + 1
            width = n_in * n_w
            for idx in range(tid, (last - first + 1) * width, nt):
                s, a, v = _state_at(idx, first, n_in, v_lo, n_w)
                cur[b, s, a, v] = (pos0[b, s] * inp[b, a]) * vel0[b, v]
        for k in range(n_steps):
            cuda.syncthreads()
            first = win[0]
            last = win[1]
            if first < 0:  # no mass left in the window
                for t in range(tid, n_s, nt):
                    positions[b, k, t] = zero
                    if with_interval:
                        ipositions[b, k, t] = zero
                for v in range(tid, n_v, nt):
                    velocities[b, k, v] = zero
                if tid == 0:
                    outsides[b, k] = f_sh[0]
                    ioutsides[b, k] = f_sh[0]
                    pruned[b, k] = zero
                continue
            hi = min(last + n_d, n_s)
            v_lo = win[4]
            v_hi = win[5]
            n_w = v_hi - v_lo + 1
            width = n_in * n_w
            t_lo = max(v_lo + dv_lo, 0)  # the v-cells p⁻ may reach
            n_tw = min(v_hi + dv_hi, n_v - 1) - t_lo + 1
            t_width = n_in * n_tw
            for t in range(tid, n_s, nt):
                pos_sh[t] = 0.0
                ipos_sh[t] = 0.0
            for v in range(tid, n_v, nt):
                vel_sh[v] = 0.0
            if tid == 0:
                acc_sh[0] = 0.0
                acc_sh[1] = 0.0
                acc_sh[2] = 0.0
                win[2] = n_s
                win[3] = -1
                win[6] = n_v
                win[7] = -1
            cuda.syncthreads()
            # 1. sources: the leak past the window's end, Υ([0, τ])'s marginal
            leak = 0.0
            ileak = 0.0
            for idx in range(tid, (last - first + 1) * width, nt):
                s, a, v = _state_at(idx, first, n_in, v_lo, n_w)
                r = a * n_v + v
                x = cur[b, s, a, v]
                if x == zero:
                    continue
                if s + n_d > n_s:
                    for e in range(ptr[r], ptr[r + 1]):
                        if s + offset[e] >= n_s:
                            leak += _f64(weight[e] * x)
                if with_interval:
                    for e in range(iptr[r], iptr[r + 1]):
                        t = s + ioffset[e]
                        if t < n_s:
                            cuda.atomic.add(ipos_sh, t, _f64(iweight[e] * x))
                        else:
                            ileak += _f64(iweight[e] * x)
            if leak != 0.0:
                cuda.atomic.add(acc_sh, 0, leak)
            if ileak != 0.0:
                cuda.atomic.add(acc_sh, 1, ileak)
            # 2. targets: p⁻ = Υ(τ) p, gathered
            for idx in range(tid, (hi - first) * t_width, nt):
                t = first + idx // t_width
                rem = idx % t_width
                a = rem // n_tw
                vt = t_lo + rem % n_tw
                acc = zero
                for e in range(tptr[a * n_v + vt], tptr[a * n_v + vt + 1]):
                    s = t - td[e]
                    vs = tv[e]
                    if s >= first and s <= last and vs >= v_lo and vs <= v_hi:
                        acc += tw[e] * cur[b, s, a, vs]
                nxt[b, t, a, vt] = acc
            cuda.syncthreads()
            # 3. per (s, v) cell: marginals, pruning, mass
            kept = 0.0
            for idx in range(tid, (hi - first) * n_tw, nt):
                t = first + idx // n_tw
                v = t_lo + idx % n_tw
                cell = 0.0
                cell_kept = 0.0
                hit = False
                for a in range(n_in):
                    x = nxt[b, t, a, v]
                    cell += x
                    y = x if x >= threshold else zero
                    nxt[b, t, a, v] = y
                    cell_kept += y
                    hit = hit or y > zero
                if cell != 0.0:
                    cuda.atomic.add(pos_sh, t, cell)
                    cuda.atomic.add(vel_sh, v, cell)
                kept += cell_kept
                mark[b, t, v] = 1 if hit else 0
                if hit:
                    cuda.atomic.min(win, 2, t)
                    cuda.atomic.max(win, 3, t)
                    cuda.atomic.min(win, 6, v)
                    cuda.atomic.max(win, 7, v)
            if kept != 0.0:
                cuda.atomic.add(acc_sh, 2, kept)
            cuda.syncthreads()
            for t in range(tid, n_s, nt):
                inside = t >= first and t < hi
                positions[b, k, t] = _f32(pos_sh[t]) if inside else zero
                if with_interval:
                    ipositions[b, k, t] = _f32(ipos_sh[t]) if inside else zero
            for v in range(tid, n_v, nt):
                velocities[b, k, v] = _f32(vel_sh[v])
            if tid == 0:
                if with_interval:
                    ioutsides[b, k] = f_sh[0] + _f32(acc_sh[1])
                f_sh[0] = f_sh[0] + _f32(acc_sh[0])
                outsides[b, k] = f_sh[0]
                before = zero
                for t in range(first, hi):
                    before += _f32(pos_sh[t])
                kept32 = _f32(acc_sh[2])
                f_sh[1] = before / (kept32 if kept32 > zero else _f32(1.0))
                pruned[b, k] = max(before - kept32, zero)
                if win[3] >= 0:
                    win[0] = win[2]
                    win[1] = win[3]
                    win[4] = win[6]
                    win[5] = win[7]
                else:
                    win[0] = -1
                    win[1] = -1
            cuda.syncthreads()
            new_first = win[0]
            new_last = win[1]
            factor = f_sh[1]
            if new_first < 0:
                continue
            v_lo = win[4]
            n_w = win[5] - v_lo + 1
            width = n_in * n_w
            # 4. the input transition: the identity, or Γ at the cells holding mass
            if not has_input[k]:
                for idx in range(tid, (new_last - new_first + 1) * width, nt):
                    t, a, v = _state_at(idx, new_first, n_in, v_lo, n_w)
                    cur[b, t, a, v] = nxt[b, t, a, v] * factor
                continue
            for idx in range(tid, (new_last - new_first + 1) * n_w, nt):
                t = new_first + idx // n_w
                v = v_lo + idx % n_w
                if mark[b, t, v] == 0:
                    for a in range(n_in):
                        cur[b, t, a, v] = zero
                    continue
                _speed_values(b, t, v, xp, fp, start, bucket, inv_h, cell_s, v_c, a_c, w32, tau, n_query, m, count)
                carry = zero
                top = m[0]
                for i in range(n_in):
                    alpha = n_in - 1 - i
                    mm = m[alpha]
                    top = max(top, mm)
                    want = carry + prefs[k, b, alpha]
                    r = min(mm, want)
                    lam[alpha] = r
                    carry = want - r
                if top <= forbid:
                    for a in range(n_in):
                        lam[a] = zero
                    lam[0] = _f32(1.0)
                for j in range(n_in):
                    x_in[j] = nxt[b, t, j, v]
                for j in range(n_in):
                    z = zero
                    for a in range(n_in):
                        z += lam[a] * psi[a, j]
                    ratio[j] = x_in[j] / z if z > zero else zero
                for a in range(n_in):
                    acc = zero
                    for j in range(n_in):
                        acc += psi[a, j] * ratio[j]
                    cur[b, t, a, v] = lam[a] * acc * factor
        cuda.syncthreads()
        first = win[0]
        last = win[1]
        total = 0.0
        if first >= 0:
            v_lo = win[4]
            n_w = win[5] - v_lo + 1
            width = n_in * n_w
            for idx in range(tid, (last - first + 1) * width, nt):
                s, a, v = _state_at(idx, first, n_in, v_lo, n_w)
                total += cur[b, s, a, v]
        if tid == 0:
            acc_sh[3] = 0.0
        cuda.syncthreads()
        if total != 0.0:
            cuda.atomic.add(acc_sh, 3, total)
        cuda.syncthreads()
        if tid == 0:
            totals[b] = acc_sh[3]


def _layout(arrays) -> tuple[list[int], int]:
    """Byte offsets (16-byte aligned) of the arrays packed one after the other, and the total size."""
    offsets, end = [], 0
    for arr in arrays:
        offsets.append(end)
        end += (arr.nbytes + 15) // 16 * 16
    return offsets, max(end, 16)


class _DeviceCache:
    """Per GPU, kept between calls: the stencil tables (per tables object, held so that its id is not reused), the
    scratch state, and the staging buffers (pinned host and device memory for the packed inputs and outputs), grown
    when a call needs more, never shrunk. One transfer each way per call: on a virtualised host each CUDA call costs
    tens of microseconds."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.tables: dict[int, tuple] = {}
        self.scratch: dict[tuple, tuple] = {}
        self.buffers: dict[str, tuple] = {}

    def buffer(self, name: str, nbytes: int) -> tuple:
        """(pinned host, device) byte buffers of at least ``nbytes``."""
        held = self.buffers.get(name)
        if held is None or held[0].shape[0] < nbytes:
            size = max(nbytes, 2 * (held[0].shape[0] if held is not None else 0), 1 << 16)
            held = self.buffers[name] = (cuda.pinned_array(size, np.uint8), cuda.device_array(size, np.uint8))
        return held


_caches: dict[int, _DeviceCache] = {}


def _cache(index: int) -> _DeviceCache:
    c = _caches.get(index)
    if c is None:
        c = _caches[index] = _DeviceCache()
    return c


def _views(buffer, offsets, arrays):
    """Views of the byte ``buffer`` (host or device) with the arrays' dtypes and shapes at ``offsets``."""
    return [buffer[o:o + a.nbytes].view(a.dtype).reshape(a.shape) for o, a in zip(offsets, arrays)]


def speed_priority_run(state, outside0, tables, n_steps, with_interval, threshold, psi, restriction, preferences, has_input,
                       forbid_threshold, device: str = "cuda", threads: int | None = None, timings: dict | None = None):
    """``kernels.speed_priority_run`` on a CUDA GPU (``device`` "cuda" or "cuda:N"): the same arguments (a
    ``kernels.SpeedRestriction`` as ``restriction``) and outputs, one kernel launch, one packed transfer each way.
    ``threads`` per block (a multiple of 32; None: ``THREADS``, read at the call). ``timings`` (a dict): where the call's time goes, in ms, written into it:
    ``host_prepare`` (arguments, caches, packing), ``launch`` (the host's launch call), ``h2d``, ``kernel``, ``d2h`` (CUDA
    events on the stream), ``host_total`` (the whole call's wall time)."""
    t_start = time.perf_counter()
    threads = THREADS if threads is None else int(threads)
    index = device_index(device)
    ptr, v_to, offset, weight, iptr, ioffset, iweight = tables
    inp, vel0, pos0 = (np.ascontiguousarray(a, dtype=np.float32) for a in state)
    n_b, n_in = inp.shape
    n_steps = int(n_steps)
    n_s, n_v = pos0.shape[1], vel0.shape[1]
    xp, fp, start, bucket, inv_h, cell_s, v_c, a_c, w32, tau = restriction._args
    if not supports(n_s, n_v, n_in, fp.shape[0]):
        raise ValueError(f"cuda_chain: a grid of {n_s} s-cells, {n_v} v-cells, {n_in} inputs and {fp.shape[0]} speed profiles is"
                         f" past the kernel's limits ({MAX_S}, {MAX_V}, {MAX_IN}, {MAX_J})")
    f32 = np.float32
    # the outputs (zero-size ones get one element: the kernel is compiled for their dimensions)
    outputs = [np.empty(shape, dtype) for shape, dtype in (
        ((n_b, n_steps, n_s), f32), ((n_b, n_steps, n_v), f32), ((n_b, n_steps, n_s) if with_interval else (1, 1, 1), f32),
        ((n_b, n_steps), f32), ((n_b, n_steps), f32), ((n_b, n_steps), f32), ((n_b,), np.float64))]
    if n_b == 0 or n_steps == 0:
        for arr in outputs:
            arr[...] = 0
        pos, vel, ipos, out, iout, pruned, totals = outputs
        return pos, vel, (ipos if with_interval else None), out, (iout if with_interval else None), pruned, totals
    inputs = [inp, vel0, pos0, np.ascontiguousarray(outside0, dtype=f32).reshape(n_b), np.ascontiguousarray(psi, dtype=f32),
              np.ascontiguousarray(preferences, dtype=f32).reshape(n_steps, n_b, n_in), np.ascontiguousarray(has_input, dtype=np.bool_),
              *(np.ascontiguousarray(a) for a in (xp, fp, start, bucket, inv_h, cell_s, v_c, a_c, w32))]
    cache = _cache(index)
    with cache.lock, cuda.gpus[index]:
        held = cache.tables.get(id(ptr))
        if held is None or held[0] is not ptr:
            n_d = 1
            if offset.shape[0]:
                n_d = max(n_d, int(np.max(offset)) + 1)
            if ioffset.shape[0]:
                n_d = max(n_d, int(np.max(ioffset)) + 1)
            v_src = np.repeat(np.arange(n_in * n_v, dtype=np.int64) % n_v, np.diff(np.asarray(ptr, dtype=np.int64)))
            dv = np.asarray(v_to, dtype=np.int64) - v_src
            dv_range = (int(min(dv.min(), 0)), int(max(dv.max(), 0))) if dv.size else (0, 0)
            on_device = tuple(cuda.to_device(np.ascontiguousarray(a)) for a in (
                *gather_tables(ptr, v_to, offset, weight, n_in, n_v), np.asarray(ptr, np.int32), np.asarray(offset, np.int32),
                np.asarray(weight, f32), np.asarray(iptr, np.int32), np.asarray(ioffset, np.int32), np.asarray(iweight, f32)))
            held = cache.tables[id(ptr)] = (ptr, n_d, dv_range, on_device)
        _, n_d, dv_range, dev_tables = held
        shape = (n_s, n_in, n_v)
        scratch = cache.scratch.get(shape)
        if scratch is None or scratch[0].shape[0] < n_b:
            rows = max(n_b, 2 * (scratch[0].shape[0] if scratch is not None else 0), 16)
            scratch = cache.scratch[shape] = (cuda.device_array((rows, n_s, n_in, n_v), f32), cuda.device_array((rows, n_s, n_in, n_v), f32),
                                              cuda.device_array((rows, n_s, n_v), np.uint8))
        cur, nxt, mark = scratch
        in_off, in_size = _layout(inputs)
        out_off, out_size = _layout(outputs)
        host_in, dev_in = cache.buffer("in", in_size)
        host_out, dev_out = cache.buffer("out", out_size)
        for view, arr in zip(_views(host_in, in_off, inputs), inputs):
            view[...] = arr
        stream = cuda.stream()
        events = [cuda.event() for _ in range(4)] if timings is not None else None

        def record(i: int) -> None:  # the i-th timing event, on the stream (with ``timings`` only)
            if events:
                events[i].record(stream)

        t_ready = time.perf_counter()
        record(0)
        dev_in[:in_size].copy_to_device(host_in[:in_size], stream=stream)
        record(1)
        (d_inp, d_vel0, d_pos0, d_out0, d_psi, d_prefs, d_has, d_xp, d_fp, d_start, d_bucket, d_inv_h, d_cell_s, d_v_c, d_a_c,
         d_w32) = _views(dev_in, in_off, inputs)
        with warnings.catch_warnings():  # a frame of few pairs is a small grid: numba's occupancy warning says nothing here
            warnings.filterwarnings("ignore", message=".*under-utilization.*")
            _chain_kernel[n_b, int(threads), stream](
                d_inp, d_vel0, d_pos0, d_out0, n_steps, *dev_tables, int(n_d), *dv_range, bool(with_interval), f32(threshold), d_psi, d_prefs,
                d_has, f32(forbid_threshold), d_xp, d_fp, d_start, d_bucket, d_inv_h, d_cell_s, d_v_c, d_a_c, d_w32, float(tau),
                cur, nxt, mark, *_views(dev_out, out_off, outputs))
        t_launched = time.perf_counter()
        record(2)
        dev_out[:out_size].copy_to_host(host_out[:out_size], stream=stream)
        record(3)
        stream.synchronize()
        for arr, view in zip(outputs, _views(host_out, out_off, outputs)):
            arr[...] = view
    if timings is not None:
        timings.update(host_prepare=1e3 * (t_ready - t_start), launch=1e3 * (t_launched - t_ready),
                       h2d=events[0].elapsed_time(events[1]), kernel=events[1].elapsed_time(events[2]),
                       d2h=events[2].elapsed_time(events[3]), host_total=1e3 * (time.perf_counter() - t_start))
    pos, vel, ipos, out, iout, pruned, totals = outputs
    return pos, vel, (ipos if with_interval else None), out, (iout if with_interval else None), pruned, totals


def warm_up(device: str = "cuda") -> None:
    """Compile the kernel now (numba compiles it on first launch), on a one-pair, one-step grid."""
    from stages.lib.markov import MarkovGridConfig, TransitionKind, build_stencils, initial_state, kernels, psi_matrix

    config = MarkovGridConfig(v_max_mps=4.0, n_s_cells=8, n_steps=1, n_state_samples=2, n_input_samples=2, n_sub_times=2)
    st = build_stencils(config)
    tables = (*kernels.stencil_tables(st.kernel(TransitionKind.TIME_POINT)), *kernels.collapsed_tables(st.kernel(TransitionKind.TIME_INTERVAL)))
    p0 = initial_state(config, s_m=np.array([1.0]), v_mps=np.array([1.0]), half_width_s_m=0.5, half_width_v_mps=0.5,
                       input_probs=np.full((1, config.n_inputs), 1.0 / config.n_inputs))
    restriction = kernels.SpeedRestriction([np.array([0.0, 100.0])], [np.full((1, 2), 5.0)], config.s_edges_m()[None, : config.n_s_cells],
                                           config.v_centres_mps(), config.input_centres_mps2(), np.array([1.0]), config.tau_s)
    speed_priority_run((p0.input_probs, p0.velocity_probs, p0.position_probs), np.zeros(1, np.float32), tables, 1, True, 0.0,
                       psi_matrix(config.input_centres_mps2()), restriction, np.ones((1, 1, config.n_inputs), np.float32), [True], 0.0,
                       device=device, threads=32)
