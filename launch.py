#!/usr/bin/env python3
"""Launch a hybrid-iamp pipeline: ``python launch.py [PIPELINE] [options]`` (``--help`` lists them).

The launcher itself is ``stages.runtime.launcher``; this file is the
command at the top of a checkout.
"""

from stages.runtime.launcher import main

if __name__ == "__main__":
    raise SystemExit(main())
