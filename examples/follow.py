"""Musical chairs: three times over, each robot is sent to where the next one stands, measured
from the camera's poses, so that the fleet turns round by one place each round.

    python examples/follow.py [--in-process]
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from fleet import Fleet

SCENARIO = Path(__file__).resolve().parent.parent / "scenarios" / "swap_4.toml"


def main(processes: bool = True, out: str | None = None, seed: int = 3, rounds: int = 3) -> dict[str, Any]:
    """Run ``rounds`` rounds; returns the run's summary."""
    with Fleet.launch(SCENARIO, clock="lockstep", seed=seed, processes=processes, out=out) as fleet:
        ids = fleet.ids
        for n in range(rounds):
            here = fleet.points()  # the controlled points, measured [m]
            fleet.goto({r: here[ids[(i + 1) % len(ids)]] for i, r in enumerate(ids)})
            if not fleet.wait_arrived(timeout=90):
                raise SystemExit(f"round {n + 1}: not every robot arrived within 90 s")
            print(f"t = {fleet.time:6.1f} s  round {n + 1} done")
    assert fleet.summary is not None
    return fleet.summary


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--in-process", action="store_true", help="run on the in-process simulator")
    ap.add_argument("--out", default=None, help="run directory")
    args = ap.parse_args()
    s = main(processes=not args.in_process, out=args.out)
    print(f"collisions {s['collisions']}, min distance {s['min_distance_m']:.3f} m")
