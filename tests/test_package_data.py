"""Every file the packages need besides their modules is in the package data (pyproject.toml), so that an install that
is not editable (``pip install .``, a wheel) has it: the shipped pipelines were left out, and the launcher of such an
install found none (a new user's probe)."""

from __future__ import annotations

import subprocess
import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_every_tracked_file_of_a_package_is_a_module_or_package_data():
    config = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    covered: set[Path] = set()
    for package, patterns in config["package-data"].items():
        root = REPO / package.replace(".", "/")
        for pattern in patterns:
            covered.update(p for p in root.glob(pattern) if p.is_file())
    tops = [t.rstrip("*") for t in config["packages"]["find"]["include"] if t.endswith("*")]
    tracked = subprocess.run(["git", "ls-files", *tops], cwd=REPO, capture_output=True, text=True, check=True).stdout.split()
    needed = [REPO / f for f in tracked if not f.endswith(".py")]
    assert any(p.name == "hybrid.toml" for p in needed)
    missing = sorted(str(p.relative_to(REPO)) for p in needed if p not in covered)
    assert not missing, f"add to [tool.setuptools.package-data]: {missing[:10]}"
