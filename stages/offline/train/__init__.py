"""Training the AR model offline: its data set (``dataset``), the fit (``fit``, ``iamp train``) and the command line (``cli``).

``cli`` only builds arguments (``iamp --help`` imports it) and imports ``fit``
when the command runs; ``fit`` never imports ``cli``. The defaults both use
live here.
"""

from __future__ import annotations

from pathlib import Path

DEFAULT_OUT = Path("artefacts") / "ar_model.pt"
"""Where ``iamp train`` writes by default, relative to the working directory (git-ignored in a checkout); the shipped model is written only with an explicit ``--out``."""
DEFAULT_CACHE_DIR = Path("artefacts") / "ar_cache"
"""The data set cache of ``iamp train``."""
SPLITS = ("sequence", "recording", "time")
#: what the training loss compares (``iamp train --loss``): the target steps' accelerations, or the along-track
#: displacement they integrate to
LOSSES = ("accel", "displacement")
