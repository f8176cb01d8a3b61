"""numba's cache folder when the package is installed read-only."""

from __future__ import annotations

from pathlib import Path

from optimizer.jit_cache import cache_dir_for

PACKAGE = Path("/usr/lib/python3/site-packages")


def test_writable_package_keeps_numbas_default() -> None:
    assert cache_dir_for(PACKAGE, {"HOME": "/home/u"}, lambda _: True) is None


def test_read_only_package_caches_per_user() -> None:
    expected = Path("/home/u/.cache/sgdslam/numba")
    assert cache_dir_for(PACKAGE, {"HOME": "/home/u"}, lambda _: False) == expected
    assert cache_dir_for(PACKAGE, {"HOME": "/home/u", "XDG_CACHE_HOME": "/var/cache/u"},
                         lambda _: False) == Path("/var/cache/u/sgdslam/numba")


def test_a_cache_folder_the_user_chose_is_kept() -> None:
    assert cache_dir_for(PACKAGE, {"NUMBA_CACHE_DIR": "/tmp/mine"}, lambda _: False) is None
