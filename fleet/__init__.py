"""The ``fleet`` command and the experiment API, over what they run.

* :mod:`fleet.cli` — the command line (``fleet design | simulate | run | goal | report | bench |
  markers | calibrate``); :mod:`fleet.bench` — ``fleet bench``'s shell over :mod:`benchmarks`;
* :mod:`fleet.experiment` — experiments as Python scripts (``from fleet import Fleet``): the API,
  its two backends (in process, or processes on the bus) and the script's view of a running fleet;
* :mod:`fleet.running` — running fleets: the launcher of ``fleet run`` and its fork server,
  ``fleet simulate``, ``fleet goal``, ``fleet report`` and the programmatic scenes.

The secure deployment's router has its own package, :mod:`secure_router`.
"""

from typing import Any

__all__ = ["Event", "Fleet", "FleetError", "GoalRefused"]


def __getattr__(name: str) -> Any:
    """``from fleet import Fleet`` without loading the API for the command line."""
    if name in __all__:
        from fleet.experiment import api

        return getattr(api, name)
    raise AttributeError(f"module 'fleet' has no attribute {name!r}")
