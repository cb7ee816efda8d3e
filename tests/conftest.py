"""The test tree follows the packages: ``tests/<package>/`` tests one package, ``tests/system/``
runs process fleets and long closed loops, ``tests/test_layers.py`` reads the whole house.

Every test under ``tests/system/`` is marked ``slow``, as are the few slow tests elsewhere
(``@pytest.mark.slow``), so that ``python -m pytest -m "not slow"`` runs the fast unit tests
alone.  The helper modules beside this file (``procfs``, ``netns_util``, ``fuzzing``) are
importable from every test directory.

Tests marked ``realtime`` run fleets (or a robot's link) on the wall clock, and what they
assert (no tube left, every deadline met, counts that agree) holds while each step's computing
fits its budget. On two cores, a second heavy test beside one of them starves its processes,
and the delays act as disturbances the tube was not sized for. So under ``pytest -n 2`` a
``realtime`` test holds an exclusive lock on a file while every other test holds it shared: it
waits for the other worker's current test to end, and no test starts beside it.

Each such wait idles a worker for the rest of the other's test, up to a minute. So the
``realtime`` tests are collected first, in their order, and a worker keeps the exclusive lock
from one ``realtime`` test to the next. ``pytest -n``'s load scheduling hands each worker a
run of consecutive tests to start with (a quarter of its share: over a hundred), so one worker
takes them all and runs them one after another, and the suite waits once, not once per
``realtime`` test. (Grouping them with ``xdist_group`` would say so more directly, but
pytest-xdist 3.8 cannot group under pytest 9.2: the id it would mark no longer names the
test.) A small selection, or ``--lf`` and ``--ff``, which reorder after this, may share them
between the workers again: slower, never wrong. A module with tests of both kinds sets its
module fixtures up twice (``tests/system/test_multihost.py``).
"""

from __future__ import annotations

import fcntl
import hashlib
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO

import pytest

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.append(str(HERE))
SYSTEM = HERE / "system"


def _realtime(item: pytest.Item | None) -> bool:
    return item is not None and item.get_closest_marker("realtime") is not None


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        if SYSTEM in Path(str(item.path)).resolve().parents:
            item.add_marker(pytest.mark.slow)
    items.sort(key=lambda item: not _realtime(item))  # stable: the realtime tests first, in order


_kept: list[IO[str]] = []
"""The lock file whose exclusive lock one ``realtime`` test passes to the next."""


@pytest.hookimpl(wrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> Iterator[object]:
    """Shared lock around each test's setup, call and teardown (module fixtures included),
    exclusive for a ``realtime`` one, and kept for the next if that is ``realtime`` too (see
    the module docstring)."""
    if _kept:
        f = _kept.pop()  # the previous test was realtime and so is this one: the lock is held
    else:
        root = hashlib.sha256(str(item.config.rootpath).encode()).hexdigest()[:12]
        f = (Path(tempfile.gettempdir()) / f"fleet-tests-{root}.lock").open("a")
        fcntl.flock(f, fcntl.LOCK_EX if _realtime(item) else fcntl.LOCK_SH)
    try:
        return (yield)
    finally:
        if _realtime(item) and _realtime(nextitem):
            _kept.append(f)
        else:
            fcntl.flock(f, fcntl.LOCK_UN)
            f.close()
