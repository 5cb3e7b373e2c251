"""A fingerprint of the project's own code, for caches whose contents the code decides.

``code_fingerprint()`` hashes the relative path and the bytes of every ``.py``
file under the project's ``stages/`` and ``bus_schemas/`` packages (sorted by
path; ``__pycache__`` left out) into 16 hex digits. A cache keyed by it (the
AR training data set of ``iamp train``, the models and spread files of
``bench/generalisation.py``) is rebuilt after any change to that code, instead
of serving what older code produced: a model trained before a change of the
feature or training code would otherwise go on being scored as if it were
today's. It is coarse on purpose: a change to the viewer rebuilds them too,
which costs minutes, where a stale entry costs a wrong figure.
"""

from __future__ import annotations

import functools
import hashlib
from pathlib import Path
from typing import Iterable

PROJECT_ROOT = Path(__file__).resolve().parents[2]
"""The folder that holds ``stages/`` and ``bus_schemas/`` (the repository, or site-packages when installed)."""
PACKAGES = ("stages", "bus_schemas")


def fingerprint_of(roots: Iterable[Path], base: Path) -> str:
    """16 hex digits of sha256 over every ``.py`` file under ``roots`` (path relative to ``base``, then its bytes), in
    sorted order; a root that does not exist adds nothing."""
    files = sorted({p for r in roots if r.is_dir() for p in r.rglob("*.py") if "__pycache__" not in p.parts})
    digest = hashlib.sha256()
    for path in files:
        rel = path.relative_to(base).as_posix().encode()
        data = path.read_bytes()
        digest.update(len(rel).to_bytes(4, "little") + rel + len(data).to_bytes(8, "little") + data)
    return digest.hexdigest()[:16]


@functools.lru_cache(maxsize=1)
def code_fingerprint() -> str:
    """``fingerprint_of`` this project's ``stages/`` and ``bus_schemas/`` (read once per process)."""
    return fingerprint_of([PROJECT_ROOT / p for p in PACKAGES], PROJECT_ROOT)


__all__ = ["PACKAGES", "PROJECT_ROOT", "code_fingerprint", "fingerprint_of"]
