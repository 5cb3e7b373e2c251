"""``python -m stages.recorder``: the recorder stage's process."""

from __future__ import annotations

from stages.recorder.core import main

if __name__ == "__main__":
    raise SystemExit(main())
