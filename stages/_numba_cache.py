"""Where numba may cache the compiled kernels: a writable folder, or one found for it before numba is imported.

The stages compile their kernels with ``numba.njit(cache=True)`` when their modules are imported. numba caches next
to the module (``__pycache__``), else in the user's cache folder (``~/.cache/numba``, ``$XDG_CACHE_HOME``), else it
raises ``RuntimeError: cannot cache function ...: no locator available`` at the import: an install that is not
writable (a container's read-only image) run by a user whose home is not writable either stopped every stage and
``iamp`` with a 46-line traceback. ``ensure()`` (run once, from ``stages/__init__.py``, before anything imports
numba) finds that case and sets ``NUMBA_CACHE_DIR`` to a folder of this user's in the temporary folder, with one line
on stderr; the processes a launcher starts inherit it. A ``NUMBA_CACHE_DIR`` already set is the user's choice and
left alone.
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path
from typing import MutableMapping

ENV = "NUMBA_CACHE_DIR"


def _can_write(folder: Path) -> bool:
    """numba's own test of a cache folder: made if missing, and a temporary file made in it."""
    try:
        os.makedirs(folder, exist_ok=True)
        tempfile.TemporaryFile(dir=folder).close()
        return True
    except OSError:
        return False


def user_cache_dir(environ: MutableMapping[str, str]) -> Path:
    """numba's user-wide cache folder (its ``AppDirs("numba").user_cache_dir``, without importing numba)."""
    if sys.platform == "darwin":
        return Path.home() / "Library" / "Caches" / "numba"
    base = environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "numba"


def ensure(environ: MutableMapping[str, str] | None = None, package_dir: Path | None = None, user_dir: Path | None = None,
           fallback: Path | None = None, numba_imported: bool | None = None) -> str | None:
    """Set ``NUMBA_CACHE_DIR`` in ``environ`` (default ``os.environ``) where numba would find nowhere to cache; returns
    the folder set, or None (nothing to do: a folder was set already, numba is imported (``numba_imported``, default:
    whether it is), or it can cache)."""
    environ = os.environ if environ is None else environ
    if environ.get(ENV) or ("numba" in sys.modules if numba_imported is None else numba_imported):
        return None
    package_dir = Path(__file__).resolve().parent if package_dir is None else package_dir
    if _can_write(package_dir / "lib" / "markov" / "__pycache__"):
        return None
    if _can_write(user_cache_dir(environ) if user_dir is None else user_dir):
        return None
    uid = os.getuid() if hasattr(os, "getuid") else 0
    fallback = Path(tempfile.gettempdir()) / f"hybrid-iamp-numba-{uid}" if fallback is None else fallback
    if not _can_write(fallback):
        return None  # (numba will say it cannot cache; nothing better to offer)
    environ[ENV] = str(fallback)
    sys.stderr.write(f"hybrid-iamp: numba cannot cache its compiled kernels beside the install nor in the home folder: using"
                     f" {ENV}={fallback} (set {ENV} to a writable folder of your own to keep them)\n")
    return str(fallback)
