"""The test tree follows the packages: ``tests/<package>/`` tests one package, ``tests/system/``
runs process fleets and long closed loops, ``tests/test_layers.py`` reads the whole house.

Every test under ``tests/system/`` is marked ``slow``, as are the few slow tests elsewhere
(``@pytest.mark.slow``), so that ``python -m pytest -m "not slow"`` runs the fast unit tests
alone.  The helper modules beside this file (``procfs``, ``netns_util``, ``fuzzing``) are
importable from every test directory.
"""

from __future__ import annotations

import sys
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
