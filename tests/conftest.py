"""The test tree follows the packages: ``tests/<package>/`` tests one package, ``tests/system/``
runs process fleets and long closed loops, ``tests/test_layers.py`` reads the whole house.

Every test under ``tests/system/`` is marked ``slow``, as are the few slow tests elsewhere
(``@pytest.mark.slow``), so that ``python -m pytest -m "not slow"`` runs the fast unit tests
alone.  The helper modules beside this file (``procfs``, ``netns_util``, ``fuzzing``) are
importable from every test directory.

Tests marked ``realtime`` run fleets on the wall clock, and what they assert (no tube left,
every deadline met, counts that agree) holds while each step's computing fits its budget. On
two cores, a second heavy test beside one of them starves its processes, and the delays act as
disturbances the tube was not sized for. So under ``pytest -n 2`` a ``realtime`` test holds an
exclusive lock on a file while every other test holds it shared: it waits for the other worker's
current test to end, and no test starts beside it.
"""

from __future__ import annotations

import fcntl
import hashlib
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.append(str(HERE))
SYSTEM = HERE / "system"


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        if SYSTEM in Path(str(item.path)).resolve().parents:
            item.add_marker(pytest.mark.slow)


@pytest.hookimpl(wrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> Iterator[object]:
    """Shared lock around each test's setup, call and teardown (module fixtures included),
    exclusive for a ``realtime`` one (see the module docstring)."""
    root = hashlib.sha256(str(item.config.rootpath).encode()).hexdigest()[:12]
    path = Path(tempfile.gettempdir()) / f"fleet-tests-{root}.lock"
    with path.open("a") as f:
        fcntl.flock(f, fcntl.LOCK_EX if item.get_closest_marker("realtime") else fcntl.LOCK_SH)
        try:
            return (yield)
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)
