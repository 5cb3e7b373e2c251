"""numpy's element rules for one float, compiled with numba where it is importable: for kernels that must give what
the numpy code they replace gives, bit for bit.

- `clip`: ``np.clip(x, lo, hi)``: NaN stays NaN, a tie keeps x (``np.clip(-0.0, 0.0, 1.0)`` is −0.0);
- `maximum`, `minimum`: ``np.maximum(a, b)``, ``np.minimum(a, b)`` on float64 arrays: NaN propagates, a tie gives b
  (``np.maximum(-0.0, 0.0)`` is 0.0: numpy's SIMD loops);
- `pairwise_sum`: ``np.sum`` of ``a[lo : lo + n]``, float64, n <= ``PAIRWISE_BLOCK`` (128): numpy's pairwise
  summation within one block (a plain loop below 8 terms, else 8 interleaved partial sums), the same bits (longer
  sums split into halves in numpy: the callers take numpy there);
- `interp`: ``np.interp(x, xp, fp)`` of one x on ``xp[a : a + n]``, ``fp[a : a + n]`` (``xp`` strictly increasing,
  n >= 2): numpy's cases (left and right values, exact hits, the slope formula and its NaN fallbacks).

Without numba they are the same functions in Python (slow, but the kernels' callers take their numpy paths then).

numba's on-disk cache of a kernel that calls these does not notice edits of this file: each such module holds this
file's digest (``NUMPY_RULES_SHA256``), which a test compares, so that an edit here also edits (and so renews the
cache of) every kernel module using it.
"""

from __future__ import annotations

try:  # pragma: no cover - exercised where numba is missing only
    import numba
except Exception:  # noqa: BLE001
    numba = None


def clip(x, lo, hi):
    if x != x:
        return x
    r = x if x >= lo else lo
    return r if r <= hi else hi


def maximum(a, b):
    if a != a:
        return a
    return a if a > b else b


def minimum(a, b):
    if a != a:
        return a
    return a if a < b else b


PAIRWISE_BLOCK = 128


def pairwise_sum(a, lo, n):
    if n < 8:
        res = 0.0
        for i in range(n):
            res += a[lo + i]
        return res
    r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
    r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
    i = 8
    while i < n - (n % 8):
        r0 += a[lo + i]
        r1 += a[lo + i + 1]
        r2 += a[lo + i + 2]
        r3 += a[lo + i + 3]
        r4 += a[lo + i + 4]
        r5 += a[lo + i + 5]
        r6 += a[lo + i + 6]
        r7 += a[lo + i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


def interp(x, xp, fp, a, n):
    if x != x:
        return x
    last = a + n - 1
    if x > xp[last]:
        return fp[last]
    if x < xp[a]:
        return fp[a]
    lo = a
    hi = last
    while hi - lo > 1:  # xp[lo] <= x < xp[hi], or x == xp[last]
        mid = lo + ((hi - lo) >> 1)
        if xp[mid] <= x:
            lo = mid
        else:
            hi = mid
    j = last if x >= xp[last] else lo
    if j == last or xp[j] == x:
        return fp[j]
    slope = (fp[j + 1] - fp[j]) / (xp[j + 1] - xp[j])
    out = slope * (x - xp[j]) + fp[j]
    if out != out:
        out = slope * (x - xp[j + 1]) + fp[j + 1]
        if out != out and fp[j] == fp[j + 1]:
            out = fp[j]
    return out


if numba is not None:
    _jit = numba.njit(cache=True, nogil=True, fastmath=False, boundscheck=False)
    clip = _jit(clip)
    maximum = _jit(maximum)
    minimum = _jit(minimum)
    interp = _jit(interp)
    pairwise_sum = _jit(pairwise_sum)

__all__ = ["clip", "interp", "maximum", "minimum", "pairwise_sum"]
