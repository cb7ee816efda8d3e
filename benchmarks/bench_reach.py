"""How many plans an agent needs, and what the fleet does if it gets only those.

    python -m benchmarks.bench_reach [--scenarios scenarios/swap_16.toml,...] [--reach 0.3,inf]
        [--cell 0.3] [--jobs 2]

In the peer mesh every agent takes every other agent's plan every step, so a fleet of n robots
moves n (n − 1) plans a step and an agent's CPU per step grows with n (docs/performance.md).
Most of those plans change nothing:

* The split rule (:func:`agent.coordination.split_halfplanes`) adds a row only for a neighbour
  whose committed point ĉ_j is within r_i + r_j + √2·ε·1.01 / s of the agent's own (s its
  share); every other row is implied by the ε box, which bounds how far ȳ moves in a step.
* The navigator (:class:`agent.navigator.Navigator`) is shaping only.  It yields to robots
  within r_i + r_j + ``conflict_range`` and plans its grid path around every robot it knows.

A subscription by place (a coarse cell of ĉ_j inside the plan's key, each agent subscribing to
the cells around its own) would let Zenoh deliver only nearby plans, peer to peer.  Its safety
needs only the first point above.  This benchmark measures the second: what the fleet does when
each agent knows only the robots whose last committed point is within a reach D of its own.

It runs ``fleet simulate`` (one process, the scenario's seed) once per reach, with
``TubeMPC.step`` wrapped at run time so that it drops the neighbours farther than D, and
``split_halfplanes`` wrapped so that it counts its rows.  Per run it reports:

* ``known``: neighbours an agent was given per step (mean and p99), and the mean as a share of
  n − 1.  That share is the least part of the mesh's plan messages a subscription of that reach
  would deliver (cells deliver more);
* ``cells``: the other robots an agent would take with a subscription by place of square cells
  of side ``--cell`` (its own cell and the eight around it), per step (mean), and as a share
  of n − 1: what Zenoh would deliver, counted over every robot whichever D the run uses;
* ``rows``: split-rule rows per agent-step, what the QP used;
* ``cpu``: the run's CPU per robot-step [ms] (the process's: agents, plants and judge), the
  cost of the math alone at that reach;
* the judge's verdict on the run: steps until every robot was home, whether all reached their
  goals, collisions and the smallest distance between references committed for the same time
  (it must stay at least 2 r).

``inf`` is today's fleet: every robot known.  Nothing here is a fleet of processes or a
transport: ``bench_zenoh_floor.py --cell`` measures what fewer plans per agent save there.
"""

from __future__ import annotations

import argparse
import math
import multiprocessing
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent

SCENARIOS = ("swap_16", "swap_32", "swap_48")
REACH = (0.3, 0.45, 0.6, 0.9, math.inf)
"""Reaches D [m] tried by default; inf is every robot."""
CELL = 0.3
"""Side of the square cells a subscription by place is counted for [m] (``--cell``)."""


def run_one(scenario_path: str, reach: float, cell: float = CELL) -> dict[str, Any]:
    """``fleet simulate`` of the scenario with every agent shown only the robots whose last
    committed point is within ``reach`` [m] of its own; the counts and the judge's figures.
    ``cell`` [m]: also count, of every other robot, those whose committed point lies in the
    3 × 3 block of square cells of that side around the agent's own (world frame, cells
    aligned on the origin)."""
    os.environ["OMP_NUM_THREADS"] = "1"
    import numpy as np

    import agent.controller as controller
    from fleet.running.simulate import run
    from ground.scenario import load_scenario

    known: list[int] = []
    in_cells: list[int] = []
    rows: list[int] = []
    step, split = controller.TubeMPC.step, controller.split_halfplanes

    def near_only(
        self: Any, x: Any, neighbours: Any, hazards: Any = (), predicted: bool = False, seen: Any = ()
    ) -> Any:
        c = self.last_point
        near = [nb for nb in neighbours if math.hypot(*(nb.last_point - c)) <= reach]
        known.append(len(near))
        if neighbours:
            mine = np.floor(c / cell)
            theirs = np.floor(np.array([nb.last_point for nb in neighbours]) / cell)
            in_cells.append(int(np.sum(np.all(np.abs(theirs - mine) <= 1, axis=1))))
        return step(self, x, near, hazards, predicted, seen)

    def counted(*args: Any, **kwargs: Any) -> Any:
        out = split(*args, **kwargs)
        rows.append(len(out[0]))
        return out

    controller.TubeMPC.step = near_only  # type: ignore[method-assign]
    controller.split_halfplanes = counted  # type: ignore[assignment]
    try:
        scenario = load_scenario(scenario_path)
        cpu = time.process_time()
        result = run(scenario)
        cpu = time.process_time() - cpu
    finally:
        controller.TubeMPC.step = step  # type: ignore[method-assign]
        controller.split_halfplanes = split
    n = len(scenario.robots)
    kn = np.asarray(known, dtype=float)
    return {
        "scenario": scenario.name,
        "robots": n,
        "reach_m": reach,
        "known_mean": float(kn.mean()),
        "known_p99": float(np.percentile(kn, 99)),
        "known_share": float(kn.mean() / (n - 1)),
        "cell_m": cell,
        "cells_mean": float(np.mean(in_cells)),
        "cells_share": float(np.mean(in_cells) / (n - 1)),
        "rows_mean": float(np.mean(rows)),
        "steps": result.steps,
        "cpu_ms_per_robot_step": 1e3 * cpu / (n * result.steps),
        "all_reached": result.all_reached,
        "collisions": result.collisions,
        "min_ref_m": result.min_reference_separation,
        "required_ref_m": result.required_reference_separation,
        "reference_violations": result.reference_violations,
    }


def _run(job: tuple[str, float, float]) -> dict[str, Any]:
    return run_one(*job)


def _problem(args: argparse.Namespace) -> str | None:
    """The first bad option, in one line, or None."""
    try:
        reaches = [float(r) for r in args.reach.split(",")]
    except ValueError:
        return f"--reach: {args.reach!r} is not a comma-separated list of distances in metres"
    if not reaches or not all(r > 0 for r in reaches):
        return "--reach: every reach must be a positive distance [m] (or inf)"
    if args.jobs < 1:
        return "--jobs: must be at least 1"
    if not 0 < args.cell < math.inf:
        return "--cell: the side of a cell must be a positive, finite distance [m]"
    from ground.scenario import ConfigError, load_scenario

    for path in args.scenarios.split(","):
        try:
            scenario = load_scenario(path)
        except ConfigError as e:
            return f"--scenarios: {e}"
        if len(scenario.robots) < 2:
            return f"--scenarios: {path} has one robot: nobody to reach"
    return None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--scenarios", default=",".join(str(ROOT / "scenarios" / f"{s}.toml") for s in SCENARIOS),
        help="comma-separated scenario files",
    )  # fmt: skip
    ap.add_argument(
        "--reach", default=",".join(f"{r:g}" for r in REACH), help="comma-separated reaches D [m]"
    )
    ap.add_argument("--jobs", type=int, default=2, help="runs at once (each one process)")
    ap.add_argument("--cell", type=float, default=CELL, help="side of the counted cells [m]")
    args = ap.parse_args(argv)
    problem = _problem(args)
    if problem is not None:
        print(f"bench_reach: error: {problem}", file=sys.stderr)
        return 2
    reaches = [float(r) for r in args.reach.split(",")]
    jobs = [(path, d, args.cell) for path in args.scenarios.split(",") for d in reaches]
    print(
        f"plans an agent needs: {len(jobs)} runs of fleet simulate; nproc {os.cpu_count()}, "
        f"{platform.processor() or platform.machine()}, python {platform.python_version()}, "
        f"load {os.getloadavg()[0]:.1f}",
        flush=True,
    )
    print(
        f"{'scenario':<10}{'D m':>6}{'known':>7}{'p99':>5}{'share':>7}{'cells':>7}{'share':>7}{'rows':>6}"
        f"{'steps':>7}{'cpu ms':>7}{'reached':>8}{'coll':>5}{'min ref':>8}{'need':>6}",
        flush=True,
    )
    with multiprocessing.get_context("spawn").Pool(min(args.jobs, len(jobs))) as pool:
        for r in pool.imap(_run, jobs):  # in order, each as soon as it is done
            print(
                f"{r['scenario']:<10}{r['reach_m']:>6g}{r['known_mean']:>7.1f}{r['known_p99']:>5.0f}"
                f"{r['known_share']:>7.2f}{r['cells_mean']:>7.1f}{r['cells_share']:>7.2f}"
                f"{r['rows_mean']:>6.2f}{r['steps']:>7}"
                f"{r['cpu_ms_per_robot_step']:>7.2f}{r['all_reached']!s:>8}"
                f"{r['collisions']:>5}{r['min_ref_m']:>8.3f}{r['required_ref_m']:>6.3f}",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
