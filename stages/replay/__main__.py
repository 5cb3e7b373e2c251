"""``python -m stages.replay``: the replay stage's process."""

from __future__ import annotations

from stages.replay.core import main

if __name__ == "__main__":
    raise SystemExit(main())
