"""A patrol: two robots go twice round a square of waypoints, anticlockwise, half a lap apart,
and end where they started; the summary counts the waypoints reached.

    python examples/patrol.py [--in-process]
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from fleet import Fleet

SCENARIO = Path(__file__).resolve().parent.parent / "scenarios" / "paper_two_robots.toml"
LOOP = [(0.4, 0.4), (-0.4, 0.4), (-0.4, -0.4), (0.4, -0.4)]
"""The corners of the patrol [m], world frame."""


def main(processes: bool = True, out: str | None = None, seed: int = 1) -> dict[str, Any]:
    """Run the patrol; returns the run's summary."""
    with Fleet.launch(SCENARIO, clock="lockstep", seed=seed, processes=processes, out=out) as fleet:
        a, b = fleet.ids
        start = fleet.points()
        lap_a, lap_b = LOOP, LOOP[2:] + LOOP[:2]  # b starts at the opposite corner
        fleet.mission({a: [*lap_a, *lap_a, start[a]], b: [*lap_b, *lap_b, start[b]]})
        if not fleet.wait_arrived(timeout=240):
            raise SystemExit("the patrol did not end within 240 s")
        for e in fleet.events():
            if e.kind in ("waypoint", "arrived"):
                print(f"t = {e.step * fleet.Ts:6.1f} s  {e.robot} {e.kind} {e.detail}")
    assert fleet.summary is not None
    return fleet.summary


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--in-process", action="store_true", help="run on the in-process simulator")
    ap.add_argument("--out", default=None, help="run directory")
    args = ap.parse_args()
    s = main(processes=not args.in_process, out=args.out)
    print(f"waypoints reached {s['waypoints_reached']}, collisions {s['collisions']}")
