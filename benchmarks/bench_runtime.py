"""Real-time factor of `fleet run` (one process per robot, lockstep clock, loopback Zenoh).

    python -m benchmarks.bench_runtime [--json OUT.json]

Runs the shipped scenarios paper_three_robots, swap_8 and swap_16 as separate
processes and prints simulated seconds / wall seconds (wall time from the first
step to the end, start-up excluded), the step count and the safety verdict.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SCENES = ["paper_three_robots", "swap_8", "swap_16"]


def machine_speed(reps: int = 2000) -> float:
    """One look-ahead plant step (20 substeps, scalar Python) [µs]: a fixed yardstick of how
    fast this machine runs Python right now (the project's machine measured 27 µs and, later
    the same day, 53–57 µs), printed with the real-time factors so runs can be compared."""
    import numpy as np

    from epuck_link.unicycle import LookaheadInnerLoop, UnicyclePlant
    from ground.params import WheelGeometry

    plant = UnicyclePlant(np.array([0.1, 0.2, 0.3]), LookaheadInnerLoop(0.04), WheelGeometry())
    a = np.array([0.1, -0.1])
    t0 = time.perf_counter()
    for _ in range(reps):
        plant.step(a, 0.1)
    return (time.perf_counter() - t0) / reps * 1e6


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", help="write the figures to this file")
    ap.add_argument("--scenes", nargs="*", default=SCENES)
    args = ap.parse_args()
    env = {**os.environ, "OMP_NUM_THREADS": "1", "RERUN_ANALYTICS": "0"}
    speed = machine_speed()
    print(
        f"fleet run, lockstep, nproc {os.cpu_count()}, python {sys.version.split()[0]}, "
        f"load {os.getloadavg()[0]:.1f}, yardstick (one plant step) {speed:.0f} µs"
    )
    print(
        f"{'scenario':<20}{'robots':>7}{'steps':>7}{'sim s':>8}{'wall s':>8}{'RTF':>7}{'total s':>9}  verdict"
    )
    rows = []
    for name in args.scenes:
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.monotonic()
            res = subprocess.run(
                [
                    sys.executable,
                    "-m",
                    "fleet.cli",
                    "run",
                    str(ROOT / "scenarios" / f"{name}.toml"),
                    "--out",
                    tmp,
                ],
                cwd=ROOT,
                env=env,
                capture_output=True,
                text=True,
                timeout=1800,
            )
            total = time.monotonic() - t0
            s = json.loads((Path(tmp) / "summary.json").read_text())
        rtf = s["sim_time_s"] / s["wall_time_s"]
        verdict = "ok" if res.returncode == 0 else res.stderr.strip().splitlines()[-1]
        rows.append(
            {
                "scenario": name,
                "robots": len(s["robots"]),
                "steps": s["steps"],
                "sim_s": s["sim_time_s"],
                "wall_s": s["wall_time_s"],
                "rtf": rtf,
                "total_s": total,
                "ok": res.returncode == 0,
                "yardstick_us": speed,
            }
        )
        print(
            f"{name:<20}{len(s['robots']):>7}{s['steps']:>7}{s['sim_time_s']:>8.1f}{s['wall_time_s']:>8.1f}"
            f"{rtf:>7.1f}{total:>9.1f}  {verdict}"
        )
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
