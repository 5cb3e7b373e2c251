"""Stages of hybrid-iamp: pure cores plus thin bus bindings (see STYLE.md)."""

from stages import _numba_cache

_numba_cache.ensure()  # before any stage imports numba: a folder to cache the kernels in, where the install has none
