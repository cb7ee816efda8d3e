"""The runtime targets of a fleet of processes, measured in one run: ``fleet bench --targets``.

Every figure comes from ``fleet run`` with its default flags (no ``--exchange``, no
``--topology``), as a user types it:

1. **CPU.** The marginal CPU per robot-step of ``fleet run`` over ``fleet simulate``'s on the
   same scene, the 16-robot swap on the lockstep clock (``bench_cpu.py``: two run lengths, the
   difference), with the split by process.  Goal: at most 2×.  Beside it, the floor that no
   fleet whose agents exchange their plans peer to peer can go below on this machine: the
   fewest messages of a whole step, with two neighbours' plans an agent and no fleet code
   (``bench_zenoh_floor.py --pattern step --cell 1``), at the pace of a fleet that met the
   target (:func:`floor_rate`), as (math + floor) / math.
2. **Realtime.** 32 robots on the realtime clock at Ts = 0.1 s for ``--realtime-s`` (60 s):
   fewer than 0.1 % of the robot-steps miss their deadline, with 0 collisions, every step
   judged.  48 robots are reported beside it, with no goal.
3. **Latency.** Pose → command p99 at 16 robots in the same kind of run: at most 5 ms.
4. **Start-up.** A 16-robot fleet ready in at most 5 s of wall time, from launching ``fleet
   run`` to its first tick (the observer's arrival time); the resident memory of each kind of
   process beside it.  Beside it, side by side: short lockstep launches of the same fleet,
   interleaved, with the agents forked from the fork server (the default) and spawned
   (``--start-agents spawn``), and the ratio of their medians.

``--quick`` runs every target at 3 robots for a few seconds: the plumbing, not the figures.
The JSON (schema ``fleet-bench-targets/1``) holds one entry per target (goal, measured, met)
and the rows it came from.  What the figures mean: docs/performance.md.
"""

from __future__ import annotations

import argparse
import json
import math
import queue
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

SCHEMA = "fleet-bench-targets/1"
CPU_RATIO = 2.0
"""Target 1: fleet run's marginal CPU per robot-step over fleet simulate's, at most."""
P99_MS = 5.0
"""Target 3: pose → command p99 [ms], at most."""
READY_S = 5.0
"""Target 4: launch to first tick [s], at most."""


def _harnesses() -> tuple[Any, Any]:
    from benchmarks import bench_cpu, bench_scale

    return bench_scale, bench_cpu


def _floor_harness() -> Any:
    from benchmarks import bench_zenoh_floor

    return bench_zenoh_floor


FLOOR_RATES = (10.0, 200.0)
"""The bounds of target 1's floor's pace [steps/s] (:func:`floor_rate`)."""


def floor_rate(robots: int, sim_ms: float, cores: int) -> float:
    """The pace [steps/s] of a lockstep fleet of ``robots`` that met target 1 on ``cores``: its
    CPU, CPU_RATIO × ``sim_ms`` per robot-step, spread over every core.  Target 1's floor is
    measured at that pace, since what the transport costs by the second (keep-alives, timers)
    counts per step in proportion to 1 / pace; within :data:`FLOOR_RATES`."""
    if not (sim_ms > 0 and math.isfinite(sim_ms)):
        return FLOOR_RATES[0]
    rate = cores / (robots * CPU_RATIO * sim_ms / 1e3)
    return min(max(rate, FLOOR_RATES[0]), FLOOR_RATES[1])


START_LAUNCHES = 3
"""Launches of each kind (agents forked, agents spawned) in target 4's side-by-side comparison."""


def targets(
    cpu_rows: list[dict[str, Any]], rt: dict[int, dict[str, Any]], sizes: dict[str, int],
    starts: dict[str, list[float]] | None = None, beside: dict[int, dict[str, Any]] | None = None,
    floor: dict[str, Any] | None = None,
) -> list[dict[str, Any]]:  # fmt: skip
    """The four targets from the measured rows: ``cpu_rows`` (fleet simulate first, then fleet
    run's defaults), ``rt`` the realtime runs by fleet size, ``sizes`` which size each target
    is judged at ("cpu", "realtime", "latency", "ready"), ``starts`` the side-by-side launch
    times [s] by how the agents were started ("fork", "spawn"), ``beside`` the realtime runs of
    targets 2's and 3's sizes with ``--no-delay-compensation``, beside the defaults' (their
    misses and latency go in those targets' detail; the verdicts are the defaults'), ``floor``
    the row of ``bench_zenoh_floor.measure`` beside target 1 (its least ratio goes in the detail)."""
    beside = beside or {}
    miss_rate = _harnesses()[0].GOAL_MISS_RATE_32  # target 2 is the realtime goal [5] for 32 robots
    out: list[dict[str, Any]] = []
    sim, run = cpu_rows[0], cpu_rows[1]
    ratio = run["ms_per_robot_step"] / sim["ms_per_robot_step"]
    out.append({
        "target": 1,
        "what": f"marginal CPU per robot-step, fleet run (defaults) / fleet simulate, {sizes['cpu']} robots",
        "goal": f"<= {CPU_RATIO:g}", "measured": ratio, "met": ratio <= CPU_RATIO,
        "detail": {"simulate_ms": sim["ms_per_robot_step"], "run_ms": run["ms_per_robot_step"],
                   "by_role_ms": run["by_role_ms"], "by_thread_ms": run["by_thread_ms"]},
    })  # fmt: skip
    if floor is not None:
        try:
            least = _floor_harness().least_ratio(
                sim["ms_per_robot_step"], floor.get("ms_per_robot_step", math.nan)
            )
        except ValueError:  # --quick's fleet simulate can come out at zero or below: no ratio then
            least = math.nan
        out[-1]["detail"]["floor"] = {**floor, "least_ratio": least}
    n = sizes["realtime"]
    r = rt.get(n, {})
    if "steps" in r:
        ok = r["miss_rate"] < miss_rate and r["collisions"] == 0 and r["supervisor_complete"]
        measured: float = r["miss_rate"]
        detail = {k: r[k] for k in ("deadline_misses", "steps", "collisions", "supervisor_complete")}
        detail["places_late"] = r["agents"]["places_late"]
    else:
        ok, measured, detail = False, math.nan, {"error": r.get("verdict", "not run")}
    keys = ("miss_rate", "deadline_misses", "steps", "collisions")
    others = {
        str(m): {**{k: x.get(k) for k in keys}, "places_late": x.get("agents", {}).get("places_late")}
        for m, x in rt.items()
        if m not in (n, sizes["latency"])
    }
    if n in beside:
        detail["no_delay_compensation"] = {k: beside[n].get(k) for k in keys}
    out.append({
        "target": 2, "what": f"realtime, {n} robots: share of robot-steps that missed the deadline",
        "goal": f"< {miss_rate:g}, 0 collisions", "measured": measured, "met": ok,
        "detail": {**detail, "also": others},
    })  # fmt: skip
    r = rt.get(sizes["latency"], {})
    p99 = r.get("latency", {}).get("pose_to_command_ms", {}).get("p99", math.nan)
    detail = dict(r.get("latency", {}))
    if sizes["latency"] in beside:
        a = beside[sizes["latency"]]
        detail["no_delay_compensation"] = {
            **{k: a.get(k) for k in ("deadline_misses", "miss_rate", "collisions")},
            **a.get("latency", {}),
        }
    out.append({
        "target": 3, "what": f"pose -> command p99 [ms], realtime, {sizes['latency']} robots",
        "goal": f"<= {P99_MS:g}", "measured": p99, "met": bool(p99 <= P99_MS), "detail": detail,
    })  # fmt: skip
    r = rt.get(sizes["ready"], {})
    ready = r.get("ready_s", math.nan)
    out.append({
        "target": 4, "what": f"launch to first tick [s], {sizes['ready']} robots",
        "goal": f"<= {READY_S:g}", "measured": ready, "met": bool(ready <= READY_S),
        "detail": {"rss_mb": r.get("rss_mb", {}), "side_by_side": _side_by_side(starts or {})},
    })  # fmt: skip
    return out


def _side_by_side(starts: dict[str, list[float]]) -> dict[str, Any]:
    """Median launch-to-first-tick [s] of each way of starting the agents, and spawn / fork."""
    med = {k: float(statistics.median(v)) for k, v in starts.items() if v}
    out: dict[str, Any] = {"ready_s": starts, "median_s": med}
    if "fork" in med and "spawn" in med:
        out["spawn_over_fork"] = med["spawn"] / med["fork"]
    return out


def run(args: argparse.Namespace) -> int:
    scale, cpu = _harnesses()
    quick = bool(args.quick)
    small = 3 if quick else None
    sizes = {"cpu": small or 16, "realtime": small or 32, "latency": small or 16, "ready": small or 16}
    rt_sizes = [small] if small else [16, 32, 48]
    rt_s = args.realtime_s if args.realtime_s is not None else (3.0 if quick else 60.0)
    lengths = (2.0, 12.0) if quick else cpu.LENGTHS
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    json_path = Path(args.json) if args.json else out / "targets.json"
    t_start = time.monotonic()
    info = scale.bs.machine_info()
    print("fleet bench --targets: fleet run with its default flags" + (" (--quick)" if quick else ""))
    print(f"machine: nproc {info['nproc']}, {info['cpu']}; python {info['python']}; "
          f"load average {info['loadavg_at_start']}", flush=True)  # fmt: skip
    print(
        f"[1] CPU: swap of {sizes['cpu']} robots, lockstep, {lengths[0]:g} s and {lengths[1]:g} s", flush=True
    )
    cpu_rows = cpu.marginal_rows(
        sizes["cpu"], lengths, args.seed, {"fleet simulate": ["simulate"], "fleet run (defaults)": ["run"]}
    )
    floor_s = 2.0 if quick else 15.0
    rate = floor_rate(sizes["cpu"], cpu_rows[0]["ms_per_robot_step"], info["nproc"])
    print(f"[1] beside it, the floor: the fewest messages of a step, {sizes['cpu']} processes and a "
          f"tracker's and a supervisor's stand-ins, {rate:.0f} steps/s (the pace of a fleet at "
          f"{CPU_RATIO:g}x), {floor_s:g} s", flush=True)  # fmt: skip
    try:
        floor = _floor_harness().measure(
            sizes["cpu"], rate, floor_s, "callback", "mesh", cell=1, pattern="step"
        )
    except (RuntimeError, OSError, EOFError, queue.Empty) as e:  # the other targets still count
        floor = {"error": f"{type(e).__name__}: {e}"}
        print(f"  the floor was not measured: {floor['error']}", flush=True)
    rt: dict[int, dict[str, Any]] = {}
    with tempfile.TemporaryDirectory(prefix="fleet-targets-") as tmp_s:
        print(f"[2]-[4] realtime runs, {rt_s:g} s each: {', '.join(map(str, rt_sizes))} robots", flush=True)
        print(scale.RUN_HEADER, flush=True)
        for n in rt_sizes:
            rt[n] = scale.fleet_run(
                n, "realtime", rt_s, out, Path(tmp_s), print, exchange=None, topology=None
            )
            scale.print_run(rt[n], print)
        beside: dict[int, dict[str, Any]] = {}
        for n in sorted({sizes["realtime"], sizes["latency"]}):
            print(f"[2], [3] beside them: {n} robots, realtime, --no-delay-compensation", flush=True)
            beside[n] = scale.fleet_run(
                n, "realtime", rt_s, out, Path(tmp_s), print, exchange=None, topology=None,
                extra=("--no-delay-compensation",), tag=f"realtime_{n}_no_delay_compensation",
            )  # fmt: skip
            scale.print_run(beside[n], print)
        n = sizes["ready"]
        launches = 1 if quick else START_LAUNCHES
        print(f"[4] start-up side by side: {n} robots, lockstep, {launches} launches each, interleaved",
              flush=True)  # fmt: skip
        starts: dict[str, list[float]] = {"fork": [], "spawn": []}
        for i in range(launches):
            for how in starts:
                row = scale.fleet_run(
                    n, "lockstep", 1.0, out, Path(tmp_s), print, exchange=None, topology=None,
                    extra=("--start-agents", how), tag=f"start_{how}_{i}",
                )  # fmt: skip
                starts[how].append(row.get("ready_s", math.nan))
                print(f"  agents {how}: ready in {starts[how][-1]:.2f} s", flush=True)
    result = targets(cpu_rows, rt, sizes, starts, beside, floor)
    print("\ntarget  goal                      measured   met   what")
    for t in result:
        met = "yes" if t["met"] else "NO"
        print(f"  {t['target']}     {t['goal']:<25} {t['measured']:>9.4g}   {met:<4}  {t['what']}")
    fl = result[0]["detail"]["floor"]
    if "error" not in fl:
        print(f"  1's floor: a step's fewest messages, {fl['plans_per_step']:.1f} neighbours' plans an "
              f"agent, {fl['rate']:.0f} steps/s: {fl['ms_per_robot_step']:.2f} ms per robot-step; no fleet "
              f"exchanging plans peer to peer goes below {fl['least_ratio']:.2f}x fleet simulate "
              "here")  # fmt: skip
    d2 = result[1]["detail"]
    for m, x in {str(sizes["realtime"]): d2, **d2.get("also", {})}.items():
        if x.get("places_late") is not None:
            print(f"  2 at {m} robots: {x['places_late']} places heard later than the reach's proof assumes "
                  "(docs/method.md 6.7), over all agents")  # fmt: skip
    nd2 = result[1]["detail"].get("no_delay_compensation")
    if nd2:
        print(f"  2 with --no-delay-compensation: {nd2['miss_rate']:.4g} of the robot-steps missed the "
              f"deadline, {nd2['collisions']} collisions")  # fmt: skip
    p2c = result[2]["detail"].get("no_delay_compensation", {}).get("pose_to_command_ms")
    if p2c:
        over = p2c["p99"] / result[2]["measured"]
        print(f"  3 with --no-delay-compensation: pose -> command p99 {p2c['p99']:.1f} ms "
              f"(p50 {p2c['p50']:.1f}); its p99 over the defaults': {over:.2f}")  # fmt: skip
    side = result[3]["detail"]["side_by_side"]
    if "spawn_over_fork" in side:
        print(f"  start-up, medians: agents forked {side['median_s']['fork']:.2f} s, spawned "
              f"{side['median_s']['spawn']:.2f} s: spawn / fork {side['spawn_over_fork']:.2f}")  # fmt: skip
    rss = result[3]["detail"]["rss_mb"]
    if rss:
        print(f"  resident memory [MB]: agent p50 {rss['agent_p50']:.0f}, max {rss['agent_max']:.0f} "
              f"(PSS, the pages shared with the other agents counted as its share: p50 "
              f"{rss.get('agent_pss_p50', math.nan):.0f}); tracker {rss['tracker']:.0f}; "
              f"supervisor {rss['supervisor']:.0f}")  # fmt: skip
    info["loadavg_at_end"] = scale.loadavg()
    doc = {"schema": SCHEMA, "quick": quick, "seed": args.seed, "machine": info, "targets": result,
           "cpu_rows": cpu_rows, "realtime_runs": {str(n): r for n, r in rt.items()},
           "total_wall_s": time.monotonic() - t_start}  # fmt: skip
    json_path.write_text(json.dumps(scale._finite(doc), indent=1) + "\n")
    print(f"total {doc['total_wall_s']:.0f} s; figures: {json_path}", flush=True)
    return 0
