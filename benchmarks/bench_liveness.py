#!/usr/bin/env python
"""Liveness benchmark: ``fleet bench --liveness N``.

Runs N scenes drawn by :func:`fleet.running.scenes.hard_scene` (seeds ``--seed`` … ``--seed + N − 1``,
seven families in turn: dense random scenes with goals at the closest legal spacing, odd
rings, mirrored grids, antipodal swaps of 4–24, thin corridors, a gap between polygons,
goals packed around obstacles) through ``fleet simulate``, in ``--jobs`` processes, and
prints a table per family and overall:

* completion: scenes whose every robot got home (settled at its goal), and robots home;
* collisions (the count must be 0);
* time to goal p50 / p90 [s] over all robots;
* path efficiency: each robot's path length over the straight line from its start to its
  goal (robots that do not move are left out), p50 / p90, measured to the moment it arrived
  (``path_to_arrival_m``: the hold at the goal left out);
* alone: the floor of path efficiency, p50 / p90 over the same robots: the shortest way of each
  robot alone past the walls and obstacles (:meth:`agent.navigator.GridPlanner.shortest`) over
  the straight line.  What path efficiency exceeds it by, the other robots cost;
* time over floor: each robot's time to goal over the least time the model's bounds allow
  in free space (``travel_floor_s``, :func:`ground.model.travel_floor`), p50 / p90;
* well-formed: scenes whose layout forces no order of arrival (no robot's way home walled in
  by the others' goals: ``ground.scenario.forced_order``, docs/method.md §7).
* where the path goes (a second table): per family, the share of the moved robots' paths up to
  arrival spent going their own way (to the goal or the wait point), making way for a robot
  that goes first (and holding the point made way to), and escaping a stall (the watchdog), by
  the navigator's mode at each step (:data:`WAYS`): what the gap between path efficiency and
  its floor is made of; and the length of the own way
  over the same robots' shortest ways alone (``own / alone``: over 1, the own way itself went
  round robots, or came back after making way); and ``no room``, of the steps robots spent in
  the corridor of a robot that goes first (mode ``yield``, every robot, the whole run), the
  share in which the point they chose was still in a corridor (``no_room_steps``: assumption
  (A) of docs/method.md §7 failing).
* ms/robot-step: the wall time of the scenes' runs (``fleet simulate``, one process each) over
  their steps times their robots: what a robot costs the simulator a step, at each size.

``--liveness-floor`` runs nothing: per family, that floor over every robot that has to move
(each scene's robots whose goal is over 5 cm from their start), in a second or so a scene.

``--liveness-realtime`` runs each scene instead as a process fleet on the realtime clock with
its defaults (``fleet run --clock realtime``: plans by place, planned a step ahead), one at a
time, and adds the deadline misses and the places heard late; its files go under
``OUT/realtime``.

A scene the loader refuses counts as refused, not run.  The JSON (``--json``, default
``out/bench/liveness.json``) holds every scene's figures.
"""

from __future__ import annotations

import os

os.environ["OMP_NUM_THREADS"] = "1"  # before proxsuite (libgomp) is imported

import argparse
import functools
import json
import multiprocessing
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

SCHEMA = 4

MOVES = 0.05
"""A robot whose goal is this far from its start or nearer [m] is left out of path efficiency."""


def _alone(scn: Any, footprint: float) -> dict[str, float]:
    """Per robot of scenario ``scn`` whose goal is over :data:`MOVES` from its start (its
    controlled point's), the shortest way alone over the straight line (the floor of path
    efficiency, :meth:`agent.navigator.GridPlanner.shortest`)."""
    from agent.navigator import grid_planner
    from ground.geometry import controlled_point

    grid = grid_planner(scn.arena, footprint, scn.obstacles)
    out = {}
    for r in scn.robots:
        a, b = controlled_point(r.start, scn.controller.lookahead), np.asarray(r.goal, dtype=float)
        line = float(np.linalg.norm(b - a))
        if line > MOVES:
            out[r.id] = grid.shortest(a, b) / line
    return out


def _scene(seed: int, families: tuple[str, ...] | None) -> tuple[dict[str, Any], str, Any, Any]:
    """Hard scene ``seed`` of ``families`` (default :data:`fleet.running.scenes.HARD_FAMILIES`): its
    data, its family, and the loaded scenario and design, or None and the loader's reason."""
    from agent.tube import validated_design
    from fleet.running.scenes import HARD_FAMILIES, hard_scene
    from ground.scenario import ConfigError, parse_scenario

    fams = families or HARD_FAMILIES
    data = hard_scene(seed, fams)
    try:
        scn = parse_scenario(data)
        return data, fams[seed % len(fams)], scn, validated_design(scn)
    except ConfigError as e:
        return data, fams[seed % len(fams)], None, str(e)


def floor(seed: int, families: tuple[str, ...] | None = None) -> dict[str, Any]:
    """The floor of path efficiency of hard scene ``seed`` of ``families`` (:func:`_alone`), no run."""
    data, family, scn, design = _scene(seed, families)
    head = {"seed": seed, "name": data["name"], "family": family}
    if scn is None:
        return {**head, "refused": design}
    return {**head, "robots": len(scn.robots), "alone": list(_alone(scn, design.footprint).values())}


def one(
    seed: int, ahead: bool = True, families: tuple[str, ...] | None = None, realtime: Path | None = None
) -> dict[str, Any]:
    """Run hard scene ``seed`` of ``families`` (default :data:`fleet.running.scenes.HARD_FAMILIES`) in
    this process, with every plan made a step ahead as ``fleet simulate`` makes them by default
    (``ahead`` False: each from its measurement); its figures.  ``realtime``: instead run it as
    a process fleet on the realtime clock with its defaults (``fleet run --clock realtime``:
    plans by place, planned ahead), its files under that directory."""
    from fleet.running.scenes import scene_to_toml
    from fleet.running.simulate import run

    t0 = time.perf_counter()
    data, family, scn, design = _scene(seed, families)
    if scn is None:
        return {"seed": seed, "name": data["name"], "family": family, "refused": design}
    extra: dict[str, Any] = {}
    if realtime is None:
        res = run(scn, design=design, ahead=ahead)
        s = res.summary()
        extra = {"ways": _ways(res, s)}
        # Steps making way (in a corridor), and of them those with no point out of it: (A) failing.
        extra["making_way"] = sum(tr.modes.count("yield") for tr in res.traces.values())
        extra["no_room"] = sum(r["no_room_steps"] for r in s["robots"].values())
    else:
        where = realtime / data["name"]
        where.mkdir(parents=True, exist_ok=True)
        (where / "scene.toml").write_text(scene_to_toml(data))
        cmd = [sys.executable, "-m", "fleet.cli", "run", str(where / "scene.toml"), "--clock", "realtime",
               "--out", str(where / "run")]  # fmt: skip
        if not ahead:
            cmd.append("--no-delay-compensation")
        with open(where / "fleet.stderr", "w") as err:
            subprocess.run(
                cmd, stdout=subprocess.DEVNULL, stderr=err, timeout=3 * scn.duration + 300, check=False
            )
        s = json.loads((where / "run" / "summary.json").read_text())
        extra = {"deadline_misses": s["deadline_misses"], "places_heard_late": s["places_heard_late"]}
    robots = s["robots"]
    moved = {k: r for k, r in robots.items() if r["straight_line_m"] > MOVES and r["reached_goal"]}
    eff = [r["path_to_arrival_m"] / r["straight_line_m"] for r in moved.values()]
    slow = [r["time_to_goal_s"] / r["travel_floor_s"] for r in moved.values() if r["travel_floor_s"] > 0]
    alone = _alone(scn, design.footprint)
    if "ways" in extra:  # the shortest ways alone of the same robots [m]
        extra["ways"]["alone"] = sum(alone[k] * r["straight_line_m"] for k, r in moved.items() if k in alone)
    return {
        "seed": seed,
        "name": data["name"],
        "family": family,
        "robots": len(robots),
        "home": sum(r["reached_goal"] for r in robots.values()),
        "collisions": s["collisions"],
        "steps": s["steps"],
        "time_to_goal_s": [r["time_to_goal_s"] for r in robots.values() if r["time_to_goal_s"] is not None],
        "path_efficiency": eff,
        "alone": [alone[k] for k in moved if k in alone],
        "time_over_floor": slow,
        "forced": len(s["forced_order"] or {}),
        "wall_s": time.perf_counter() - t0,
        **extra,
    }


WAYS = {"goal": "own", "path": "own", "yield": "make way", "aside": "make way", "escape": "escape"}
"""The navigator's modes (``agent.navigator.Navigator.target``) grouped by what a robot is doing:
going its own way (to its goal, or to its wait point, along its path), making way for a robot
that goes first (in its corridor, then holding the point made way to), or escaping a stall (the
watchdog); any other mode counts as "other"."""


def _ways(res: Any, s: dict[str, Any]) -> dict[str, float]:
    """Over the robots that moved and arrived, the length [m] of their paths up to arrival
    (the controlled point's, sample to sample) by what each step's mode had them do (:data:`WAYS`)."""
    out = dict.fromkeys(["own", "make way", "escape", "other"], 0.0)
    Ts = res.design.params.Ts
    for rid, r in s["robots"].items():
        if not (r["straight_line_m"] > MOVES and r["reached_goal"]):
            continue
        tr = res.traces[rid]
        k_end = min(len(tr.modes), round(r["time_to_goal_s"] / Ts))
        P = np.asarray(tr.point[: k_end + 1])
        d = np.hypot(*np.diff(P, axis=0).T) if len(P) > 1 else np.zeros(0)
        for mode, m in zip(tr.modes[:k_end], d, strict=False):
            out[WAYS.get(mode, "other")] += float(m)
    return out


def ways_table(rows: list[dict[str, Any]]) -> list[str]:
    """Per family, where the path to arrival goes: the share of it spent going one's own way,
    making way and escaping (:func:`_ways`)."""
    ran = [r for r in rows if "ways" in r]
    if not ran:
        return []
    out = [
        f"{'family':<14} {'path [m]':>9} {'own way':>8} {'make way':>9} {'escape':>7} {'other':>6} "
        f"{'own / alone':>11} {'no room':>8}"
    ]
    kinds = ("own", "make way", "escape", "other")
    for fam in [*sorted({r["family"] for r in ran}), "all"]:
        tot = dict.fromkeys([*kinds, "alone"], 0.0)
        for r in ran:
            if fam in ("all", r["family"]):
                for k, v in r["ways"].items():
                    tot[k] += v
        path = sum(tot[k] for k in kinds)
        share = [f"{100.0 * tot[k] / path:.0f} %" if path else "–" for k in kinds]
        own = f"{tot['own'] / tot['alone']:.2f}" if tot["alone"] else "–"
        yielding = sum(r.get("making_way", 0) for r in ran if fam in ("all", r["family"]))
        cornered = sum(r.get("no_room", 0) for r in ran if fam in ("all", r["family"]))
        room = f"{100.0 * cornered / yielding:.1f} %" if yielding else "–"
        out.append(
            f"{fam:<14} {path:>9.1f} {share[0]:>8} {share[1]:>9} {share[2]:>7} {share[3]:>6} {own:>11} "
            f"{room:>8}"
        )
    return out


def _pct(values: list[float], q: float) -> str:
    return f"{np.percentile(values, q):.1f}" if values else "–"


def _cost(ran: list[dict[str, Any]]) -> str:
    """Wall time per robot-step [ms] over the scenes ``ran`` (all their steps, all their robots)."""
    if any("deadline_misses" in r for r in ran):
        return "–"  # on the realtime clock the wall time is the run's length
    work = sum(r["steps"] * r["robots"] for r in ran)
    return f"{1e3 * sum(r['wall_s'] for r in ran) / work:.2f}" if work else "–"


def table(rows: list[dict[str, Any]]) -> list[str]:
    """The printed table: one line per family and one for all."""
    fams = sorted({r["family"] for r in rows})
    out = [
        f"{'family':<14} {'scenes':>6} {'refused':>7} {'complete':>9} {'robots home':>12} {'collisions':>10} "
        f"{'ttg p50':>8} {'ttg p90':>8} {'path p50':>8} {'path p90':>8} "
        f"{'alone p50':>9} {'alone p90':>9} "
        f"{'t/floor p50':>11} {'t/floor p90':>11} {'well-formed':>11} {'ms/robot-step':>13}"
    ]
    for fam in [*fams, "all"]:
        sel = [r for r in rows if fam in ("all", r["family"])]
        ran = [r for r in sel if "refused" not in r]
        done = sum(r["home"] == r["robots"] for r in ran)
        home = sum(r["home"] for r in ran)
        total = sum(r["robots"] for r in ran)
        ttg = [t for r in ran for t in r["time_to_goal_s"]]
        eff = [e for r in ran for e in r["path_efficiency"]]
        slow = [e for r in ran for e in r["time_over_floor"]]
        alone = [e for r in ran for e in r["alone"]]
        rate = f"{100.0 * done / len(ran):.1f} %" if ran else "–"
        formed = sum(r["forced"] == 0 for r in ran)
        out.append(
            f"{fam:<14} {len(sel):>6} {len(sel) - len(ran):>7} {rate:>9} {f'{home}/{total}':>12} "
            f"{sum(r['collisions'] for r in ran):>10} {_pct(ttg, 50):>8} {_pct(ttg, 90):>8} "
            f"{_pct(eff, 50):>8} {_pct(eff, 90):>8} {_pct(alone, 50):>9} {_pct(alone, 90):>9} "
            f"{_pct(slow, 50):>11} {_pct(slow, 90):>11} "
            f"{f'{formed}/{len(ran)}':>11} {_cost(ran):>13}"
        )
    return out


def floor_table(rows: list[dict[str, Any]]) -> list[str]:
    """The printed table of ``--liveness-floor``: one line per family and one for all."""
    fams = sorted({r["family"] for r in rows})
    out = [
        f"{'family':<14} {'scenes':>6} {'refused':>7} {'robots':>6} {'alone p50':>9} {'alone p90':>9} "
        f"{'max':>6}"
    ]
    for fam in [*fams, "all"]:
        sel = [r for r in rows if fam in ("all", r["family"])]
        ran = [r for r in sel if "refused" not in r]
        alone = [e for r in ran for e in r["alone"]]
        top = f"{max(alone):.2f}" if alone else "–"
        out.append(
            f"{fam:<14} {len(sel):>6} {len(sel) - len(ran):>7} {len(alone):>6} "
            f"{_pct(alone, 50):>9} {_pct(alone, 90):>9} {top:>6}"
        )
    return out


def run(args: argparse.Namespace) -> int:
    n, seed0, jobs = int(args.liveness), int(args.seed), max(1, int(args.jobs))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    json_path = Path(args.json) if args.json else out / "liveness.json"
    order = "" if getattr(args, "delay_compensation", True) else ", each plan from its measurement"
    from fleet.running.scenes import HARD_FAMILIES

    fams = tuple(getattr(args, "families", None) or HARD_FAMILIES)
    named = ", ".join(fams)
    print(f"fleet bench --liveness: {n} scenes from seed {seed0} ({named}), {jobs} processes{order}",
          flush=True)  # fmt: skip
    print(f"machine: nproc {os.cpu_count()}, {platform.processor() or platform.machine()}; "
          f"python {platform.python_version()}; load average {os.getloadavg()}", flush=True)  # fmt: skip
    t0 = time.perf_counter()
    rows: list[dict[str, Any]] = []
    ctx = multiprocessing.get_context("spawn")
    ahead = bool(getattr(args, "delay_compensation", True))
    realtime = out / "realtime" if getattr(args, "liveness_realtime", False) else None
    if realtime is not None:
        jobs = 1  # a realtime fleet needs the machine to itself
        print("each scene a process fleet on the realtime clock (fleet run --clock realtime), one at a time")
    floor_only = bool(getattr(args, "liveness_floor", False))
    if floor_only:
        print("the floor of path efficiency only: each robot's shortest way alone, nothing run")
    work: Any = (
        functools.partial(floor, families=fams)
        if floor_only
        else functools.partial(one, ahead=ahead, families=fams, realtime=realtime)
    )
    with ctx.Pool(jobs) as pool:
        for r in pool.imap_unordered(work, range(seed0, seed0 + n)):
            rows.append(r)
            what = r.get("refused") or (
                f"{len(r['alone'])} robots to move" if floor_only
                else f"{r['home']}/{r['robots']} home, {r['collisions']} collisions"
            )  # fmt: skip
            print(f"  [{len(rows):>3}/{n}] {r['name']}: {what}", flush=True)
    rows.sort(key=lambda r: r["seed"])
    lines = floor_table(rows) if floor_only else [*table(rows), *ways_table(rows)]
    if realtime is not None:
        ran = [r for r in rows if "refused" not in r]
        lines.append(
            f"realtime: deadline misses {sum(r['deadline_misses'] for r in ran)} of "
            f"{sum(r['steps'] * r['robots'] for r in ran)} commands, places heard late "
            f"{sum(r['places_heard_late'] for r in ran)}"
        )
    print("\n".join(lines), flush=True)
    print(f"wall time {time.perf_counter() - t0:.0f} s", flush=True)
    json_path.write_text(json.dumps({"schema": SCHEMA, "scenes": rows, "table": lines}, indent=1))
    print(f"figures: {json_path}", flush=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--liveness", type=int, default=105, metavar="N", help="scenes to run (default 105)")
    ap.add_argument("--seed", type=int, default=0, help="first scene seed (default 0)")
    ap.add_argument("--jobs", type=int, default=2, help="processes (default 2)")
    ap.add_argument("--families", default="hard", help="hard, layout, scale, all, or a comma-separated list")
    ap.add_argument("--out", default="out/bench", help="directory of the JSON (default out/bench)")
    ap.add_argument("--json", default=None, help="where the JSON goes (default OUT/liveness.json)")
    ap.add_argument(
        "--liveness-realtime", action="store_true",
        help="run each scene as a process fleet on the realtime clock, one at a time",
    )  # fmt: skip
    ap.add_argument(
        "--delay-compensation", action=argparse.BooleanOptionalAction, default=True,
        help="plans made a step ahead, as fleet simulate makes them by default",
    )  # fmt: skip
    ap.add_argument(
        "--liveness-floor", action="store_true",
        help="run nothing: the floor of path efficiency (each robot's shortest way alone) per family",
    )  # fmt: skip
    args = ap.parse_args(argv)
    from benchmarks.options import families

    try:
        args.families = families(args.families)
    except ValueError as e:
        print(f"bench_liveness: error: --families: {e}", file=sys.stderr)
        return 2
    return run(args)


if __name__ == "__main__":
    sys.exit(main())
