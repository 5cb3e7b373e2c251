"""stages.lib.fingerprint: the code fingerprint that keys the training data set and bench/generalisation's caches."""

from __future__ import annotations

from pathlib import Path

from stages.lib.fingerprint import code_fingerprint, fingerprint_of


def _tree(root: Path) -> Path:
    (root / "pkg" / "sub").mkdir(parents=True)
    (root / "pkg" / "__init__.py").write_text("x = 1\n")
    (root / "pkg" / "sub" / "mod.py").write_text("def f():\n    return 2\n")
    (root / "pkg" / "notes.txt").write_text("not code")
    return root / "pkg"


def test_fingerprint_follows_the_code_and_nothing_else(tmp_path):
    pkg = _tree(tmp_path)
    first = fingerprint_of([pkg], tmp_path)
    assert len(first) == 16 and first == fingerprint_of([pkg], tmp_path)
    # what is not .py source leaves it alone: other files, compiled caches
    (pkg / "notes.txt").write_text("other text")
    (pkg / "__pycache__").mkdir()
    (pkg / "__pycache__" / "mod.cpython-311.py").write_text("junk")
    assert fingerprint_of([pkg], tmp_path) == first
    # one changed byte, a moved file or a new file changes it
    (pkg / "sub" / "mod.py").write_text("def f():\n    return 3\n")
    changed = fingerprint_of([pkg], tmp_path)
    assert changed != first
    (pkg / "sub" / "mod.py").rename(pkg / "mod.py")
    moved = fingerprint_of([pkg], tmp_path)
    assert moved not in (first, changed)
    (pkg / "new.py").write_text("")
    assert fingerprint_of([pkg], tmp_path) != moved
    # a root that does not exist adds nothing
    assert fingerprint_of([pkg, tmp_path / "absent"], tmp_path) == fingerprint_of([pkg], tmp_path)


def test_code_fingerprint_keys_the_training_data_set():
    from stages.offline.train.dataset import DatasetConfig

    assert DatasetConfig().key_dict()["code"] == code_fingerprint()
    assert len(code_fingerprint()) == 16
