"""Shared test helpers: where the shared real data lives, skipping cleanly when it is absent."""

from __future__ import annotations

from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def shared_file(relative: str) -> Path:
    """A file of ../shared/data, or skip the calling test when the shared data is not beside the repo."""
    path = SHARED_DATA / relative
    if not path.exists():
        pytest.skip(f"needs ../shared/data/{relative} (shared data not present)")
    return path


@pytest.hookimpl(tryfirst=True)  # before pytest-xdist's worker reads the groups off the marks
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Every test file without an `xdist_group` mark of its own is a group of its own.

    Under `--dist loadgroup` (pyproject's addopts) a worker then runs each file whole, as `--dist loadfile`
    did: a file's module-scoped fixtures (replays, generated logs) are built once. Files marked with one
    group (the multigrid polish stack, `MULTIGRID_STACK`) run on one worker, one after another, so their
    kernels are compiled once on a cold cache instead of by both workers at the same time."""
    for item in items:
        if item.get_closest_marker("xdist_group") is None:
            item.add_marker(pytest.mark.xdist_group(item.nodeid.split("::")[0]))


MULTIGRID_STACK = pytest.mark.xdist_group("multigrid_stack")
"""The group of the test files that compile the multigrid polish's kernels (`pytestmark` of each)."""
