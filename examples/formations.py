"""A formation sequence: the four robots of the swap scene form a line, then a circle, then a
square, each time assigned to the points with the least total distance.

    python examples/formations.py               # the process fleet, lockstep
    python examples/formations.py --in-process  # the same script on the in-process simulator
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

from fleet import Fleet

SCENARIO = Path(__file__).resolve().parent.parent / "scenarios" / "swap_4.toml"
LINE = [(-0.525, 0.0), (-0.175, 0.0), (0.175, 0.0), (0.525, 0.0)]
"""Four points 0.35 m apart [m], more than the two footprints and the margin (0.278 m)."""
CIRCLE = [(0.55, 0.0), (0.0, 0.55), (-0.55, 0.0), (0.0, -0.55)]
"""Four points on a circle of 0.55 m [m]."""
SQUARE = [(0.35, 0.35), (-0.35, 0.35), (-0.35, -0.35), (0.35, -0.35)]
"""The corners of a square of side 0.7 m [m]."""


def main(processes: bool = True, out: str | None = None, seed: int = 3) -> dict[str, Any]:
    """Run the sequence; returns the run's summary.  Each shape must be reached within 60 s of
    the fleet's clock."""
    with Fleet.launch(SCENARIO, clock="lockstep", seed=seed, processes=processes, out=out) as fleet:
        for name, shape, heading in (
            ("line", LINE, math.pi / 2),
            ("circle", CIRCLE, 0.0),
            ("square", SQUARE, 0.0),
        ):
            assignment = fleet.formation(shape, heading=heading)
            if not fleet.wait_arrived(timeout=60):
                raise SystemExit(f"{name}: not every robot arrived within 60 s")
            print(f"t = {fleet.time:6.1f} s  {name:6s} " + "  ".join(
                f"{r}→({x:+.2f}, {y:+.2f})" for r, (x, y) in sorted(assignment.items())
            ))  # fmt: skip
    assert fleet.summary is not None
    return fleet.summary


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--in-process", action="store_true", help="run on the in-process simulator")
    ap.add_argument("--out", default=None, help="run directory (default out/swap_4)")
    args = ap.parse_args()
    s = main(processes=not args.in_process, out=args.out)
    print(f"collisions {s['collisions']}, min distance {s['min_distance_m']:.3f} m")
