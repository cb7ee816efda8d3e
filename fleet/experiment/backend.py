"""What a :class:`fleet.experiment.api.Fleet` drives and what it reports: the backend protocol (the
in-process simulator, :class:`fleet.experiment.api.SimulatedFleet`, or a fleet of processes,
:class:`fleet.experiment.script.ProcessFleet`), its samples and the fleet's events."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from ground.geometry import Array
from ground.scenario import Scenario

EVENT_KINDS = (
    "arrived", "waypoint", "fallback", "deadline_miss", "stale_neighbour", "dead_neighbour", "refused",
)  # fmt: skip
"""What :meth:`Fleet.events` reports (see :class:`Event`)."""


@dataclass(frozen=True)
class Event:
    """Something that happened in the fleet, at ``step`` (the sample or step index, t = step·Ts).

    ``kind`` is one of :data:`EVENT_KINDS`:

    * ``arrived`` — ``robot`` settled at its current goal;
    * ``waypoint`` — ``robot`` reached a waypoint of its mission (``detail``: which);
    * ``fallback`` — ``robot``'s QP did not give a solution at that step; it followed its
      shifted candidate (``detail``: the solver status);
    * ``deadline_miss`` — ``robot``'s command missed its deadline; its robot side followed the
      candidate or braked (process fleets);
    * ``stale_neighbour`` / ``dead_neighbour`` — ``robot``'s plan did not arrive in time / its
      agent left the fleet (process fleets);
    * ``refused`` — a goal for ``robot`` was refused (``detail``: the reason).
    """

    step: int
    robot: str
    kind: str
    detail: str = ""


@dataclass
class Sample:
    """One sample of the fleet, at t = ``step``·Ts."""

    step: int
    truth: dict[str, Array]
    """Each robot's true axle-centre pose (3,) [m, m, rad] (the camera's, on real robots)."""
    measured: dict[str, Array]
    """Each robot's measured pose (3,) [m, m, rad], as its agent sees it."""


class Backend(Protocol):
    """What a :class:`Fleet` drives: the in-process simulator or a fleet of processes."""

    scenario: Scenario
    footprint: float
    """The design's footprint radius r [m]: goals clear walls and obstacles by it."""
    realtime: bool
    out: Path | None
    """The run's directory (summary.json), None for a fleet the script joined."""

    def sample(self) -> Sample:
        """The newest sample."""
        ...

    def advance(self) -> bool:
        """Run the fleet to its next sample; False once the fleet has ended."""
        ...

    def goals(self) -> dict[str, Array]:
        """Each robot's current goal (2,) [m] (one just given counts)."""
        ...

    def send(self, goals: Mapping[str, Array]) -> dict[str, str]:
        """Give these goals together; robot → reason for each one its agent refused."""
        ...

    def events(self) -> list[Event]:
        """The backend's events since the last call."""
        ...

    def close(self) -> dict[str, Any] | None:
        """End what this backend started; the run's summary, if there is one."""
        ...

    @property
    def verdict(self) -> str | None:
        """Once closed: why the run failed in one line (a collision, a goal not reached, a
        process that failed), or None."""
        ...

    @property
    def processes(self) -> dict[str, int]:
        """The pid of every process the backend started, by role."""
        ...
