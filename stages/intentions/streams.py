"""The particle filter's random streams: ``np.random.default_rng([seed, frame, track])`` for many tracks at once.

Building a generator per vehicle through ``SeedSequence`` and ``PCG64``
costs about 20 µs each. `Streams` computes the same PCG64 states for all
vehicles of a frame at once: numpy's ``SeedSequence`` hashing
(``mix_entropy`` and ``generate_state``, numpy/random/bit_generator.pyx) in
one compiled loop over the vehicles (`_hash_rows`), then PCG64's seeding (``pcg64_set_seed``: state 0,
increment ``2 * initseq + 1``, one step, add the seed, one step) on
Python integers. The states are set on generators kept between frames, so
every vehicle's stream is the one ``default_rng`` gives, number for number
(tests/stages/test_intentions.py checks it on edge values).
"""

from __future__ import annotations

import numpy as np

try:
    import numba
except ImportError:  # pragma: no cover - numba is a dependency; without it the same loops run in Python
    numba = None

_M32 = 0xFFFFFFFF
_M128 = (1 << 128) - 1
_PCG_MULT = 0x2360ED051FC65DA44385DF649FCCF645


def _words(n: int) -> list[int]:
    """numpy's ``_int_to_uint32_array``: little-endian 32-bit words, ``[0]`` for 0."""
    if n < 0:
        raise ValueError(f"expected non-negative integer entropy, got {n}")
    out = [n & _M32]
    n >>= 32
    while n:
        out.append(n & _M32)
        n >>= 32
    return out


def _hash_rows(entropy, lengths, out):
    """``SeedSequence(entropy[r, :lengths[r]]).generate_state(4, np.uint64)`` into out[r] (uint64 arithmetic masked to 32
    bits: the low 32 bits of products and differences are those of numpy's uint32 arithmetic)."""
    m32 = np.uint64(0xFFFFFFFF)
    sixteen = np.uint64(16)
    mixer = np.zeros(4, np.uint64)
    for r in range(entropy.shape[0]):
        n = lengths[r]
        const = np.uint64(0x43B0D7E5)
        for i in range(4):
            value = entropy[r, i] if i < n else np.uint64(0)
            value = value ^ const
            const = (const * np.uint64(0x931E8875)) & m32
            value = (value * const) & m32
            mixer[i] = value ^ (value >> sixteen)
        for i_src in range(4 + max(n - 4, 0)):
            for i_dst in range(4):
                if i_src < 4 and i_src == i_dst:
                    continue
                value = mixer[i_src] if i_src < 4 else entropy[r, i_src]
                value = value ^ const
                const = (const * np.uint64(0x931E8875)) & m32
                value = (value * const) & m32
                value = value ^ (value >> sixteen)
                # L x - R y modulo 2**32, written without a negative intermediate (no wrap-around, no overflow)
                mixed = (np.uint64(0xCA01F9DD) * mixer[i_dst] + (np.uint64(0x100000000) - ((np.uint64(0x4973F715) * value) & m32))) & m32
                mixer[i_dst] = mixed ^ (mixed >> sixteen)
        const = np.uint64(0x8B51F9DD)
        for i_dst in range(8):
            value = mixer[i_dst % 4] ^ const
            const = (const * np.uint64(0x58F38DED)) & m32
            value = (value * const) & m32
            value = value ^ (value >> sixteen)
            if i_dst % 2 == 0:
                out[r, i_dst // 2] = value
            else:
                out[r, i_dst // 2] = out[r, i_dst // 2] | (value << np.uint64(32))


if numba is not None:
    _hash_rows_compiled = numba.njit(cache=True, nogil=True, boundscheck=False)(_hash_rows)
else:  # pragma: no cover
    _hash_rows_compiled = _hash_rows


class Streams:
    """Generators with the streams of ``np.random.default_rng([seed, frame, track])``, reused from frame to frame."""

    def __init__(self) -> None:
        self._generators: list[np.random.Generator] = []

    def __call__(self, seed: int, frame: int, tracks: list[int]) -> list[np.random.Generator]:
        """One generator per track (the list and its generators are reused by the next call)."""
        while len(self._generators) < len(tracks):
            self._generators.append(np.random.Generator(np.random.PCG64(0)))
        head = _words(seed) + _words(frame)
        entropy = [head + _words(t) for t in tracks]
        lengths = np.array([len(e) for e in entropy], dtype=np.int64)
        width = int(lengths.max()) if len(tracks) else 0
        words = np.zeros((len(tracks), width), np.uint64)
        for k, e in enumerate(entropy):
            words[k, : len(e)] = e
        hashed = np.zeros((len(tracks), 4), np.uint64)
        _hash_rows_compiled(words, lengths, hashed)
        states = hashed.tolist()
        out = self._generators[: len(tracks)]
        for generator, (s0, s1, i0, i1) in zip(out, states):
            inc = (((i0 << 64) | i1) << 1 | 1) & _M128
            state = (((inc + ((s0 << 64) | s1)) & _M128) * _PCG_MULT + inc) & _M128  # state 0, a step (inc), + seed, a step
            generator.bit_generator.state = {
                "bit_generator": "PCG64", "state": {"state": state, "inc": inc}, "has_uint32": 0, "uinteger": 0,
            }
        return out
