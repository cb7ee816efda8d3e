"""The ``fleet`` command, the experiment API and what they run.

* :class:`fleet.api.Fleet` — experiments as Python scripts (``from fleet import Fleet``);

* :mod:`fleet.cli` — the command line (``fleet design | simulate | run | goal | report | bench |
  markers | calibrate``);
* :mod:`fleet.launch` — ``fleet run``: the processes of a fleet, started and stopped;
* :mod:`fleet.simulate` — ``fleet simulate``: the whole fleet in one process;
* :mod:`fleet.operator` — ``fleet goal``; :mod:`fleet.report` — ``fleet report``;
* :mod:`fleet.scenes` — programmatic scenes (swaps, random scenes);
* :mod:`fleet.secure` — the secure deployment's router, configurations and access control;
* :mod:`fleet.bench` — ``fleet bench``.
"""

from typing import Any

__all__ = ["Event", "Fleet", "FleetError", "GoalRefused"]


def __getattr__(name: str) -> Any:
    """``from fleet import Fleet`` without loading the API for the command line."""
    if name in __all__:
        from fleet import api

        return getattr(api, name)
    raise AttributeError(f"module 'fleet' has no attribute {name!r}")
