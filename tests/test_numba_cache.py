"""Where numba caches the kernels on an install nobody may write to (``stages._numba_cache``).

Found by a new user's probe: an unprivileged user running a root-owned install with a home folder that is not
writable got a 46-line traceback from numba (``cannot cache function ...: no locator available``) in every stage and
in ``iamp``. The folders are made unwritable here by being files (root, who runs these tests, may write anywhere)."""

from __future__ import annotations

from stages import _numba_cache


def test_a_writable_install_or_home_is_left_as_it_is(tmp_path):
    env: dict[str, str] = {}
    assert _numba_cache.ensure(env, package_dir=tmp_path / "pkg", user_dir=tmp_path / "none", numba_imported=False) is None and env == {}
    blocked = tmp_path / "blocked"
    blocked.write_text("a file, not a folder")
    assert _numba_cache.ensure(env, package_dir=blocked, user_dir=tmp_path / "home-cache", numba_imported=False) is None and env == {}
    env = {_numba_cache.ENV: "/somewhere/of/the/users"}  # the user's choice stands
    assert _numba_cache.ensure(env, package_dir=blocked, user_dir=blocked, numba_imported=False) is None
    # numba imported already: too late to tell it anything
    assert _numba_cache.ensure({}, package_dir=blocked, user_dir=blocked, fallback=tmp_path / "f", numba_imported=True) is None


def test_neither_writable_sets_a_folder_in_the_temporary_one_and_says_so(tmp_path, capsys):
    blocked = tmp_path / "blocked"
    blocked.write_text("a file, not a folder")
    env: dict[str, str] = {}
    got = _numba_cache.ensure(env, package_dir=blocked, user_dir=blocked / "numba", fallback=tmp_path / "fallback", numba_imported=False)
    assert got == str(tmp_path / "fallback") == env[_numba_cache.ENV] and (tmp_path / "fallback").is_dir()
    assert f"NUMBA_CACHE_DIR={tmp_path / 'fallback'}" in capsys.readouterr().err


def test_numba_user_cache_folder_is_the_one_numba_uses(monkeypatch, tmp_path):
    from numba.misc.appdirs import AppDirs

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert str(_numba_cache.user_cache_dir({"XDG_CACHE_HOME": str(tmp_path / "xdg")})) == AppDirs(appname="numba", appauthor=False).user_cache_dir
