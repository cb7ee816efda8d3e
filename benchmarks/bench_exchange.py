"""How the agents' plans travel, side by side on the realtime clock: every plan to every agent,
or by place.

    python -m benchmarks.bench_exchange [--robots 32] [--seconds 60] [--order mesh,place,mesh,place]
        [--json OUT.json]

Runs ``fleet run`` of the shipped swap of ``--robots`` robots on the realtime clock for
``--seconds`` of its clock, once per entry of ``--order`` (``fleet run --exchange E``, every other
flag its default: delay compensation, the peer mesh topology), interleaved so that the machine's
drift falls on both alike.  An entry ``E/zenoh`` runs the same with Zenoh's own runtime sizes
(``ZENOH_RUNTIME=()``) instead of the one worker thread the fleet's processes size it down to
(``transport.net.RUNTIME``).  Each run is :func:`bench_scale.fleet_run`'s, the harness of ``fleet
bench``: deadline misses and their share of the robot-steps, the clock's real-time factor,
collisions, pose → command latency, the cores of the agents, the tracker and the supervisor, the
plans each agent took a step (its closing line, ``N plans taken``), the news of places that
came later than the reach's proof assumes (``late``, over all agents: docs/method.md §6.7),
and the agents' cores by thread: their main threads, Zenoh's runtime threads, and the Python
threads Zenoh runs the callbacks on (sampled from ``/proc`` about once a second).  The last lines give the
medians of each exchange and their ratios to the first's.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import statistics
import sys
import tempfile
from pathlib import Path
from typing import Any

from benchmarks import bench_cpu
from benchmarks.bench_scale import SCENES, fleet_run
from benchmarks.bench_step import machine_info
from transport.process import EXCHANGES

ROOT = Path(__file__).resolve().parent.parent

RUNTIMES = {"": None, "zenoh": {"ZENOH_RUNTIME": bench_cpu.ZENOH_OWN}}
"""Environment of an ``--order`` entry's fleet by its suffix: none (the fleet's own sizing of
Zenoh's runtime), or ``/zenoh``, Zenoh's own sizes."""

FIGURES = (
    "miss_pct",
    "rtf",
    "agents_cores",
    "cores",
    "p99_ms",
    "plans",
    "late",
    "main",
    "zenoh",
    "callbacks",
)


def _plans_taken(run_dir: str, steps: int) -> float:
    """Plans an agent took a step, averaged over the agents (their closing lines)."""
    text = (Path(run_dir) / "fleet.stderr").read_text()
    taken = [int(n) for n in re.findall(r"(\d+) plans taken", text)]
    return sum(taken) / len(taken) / steps if taken and steps else float("nan")


def _row(r: dict[str, Any], entry: str) -> dict[str, Any]:
    if "steps" not in r:
        return {"exchange": entry, "error": r.get("error", r["verdict"])}
    cpu, lat = r["cpu"], r.get("latency", {}).get("pose_to_command_ms", {"p99": float("nan")})
    late = r["agents"]["places_late"]  # None: not measured (every plan to every agent, relay)
    return {
        "exchange": entry, "steps": r["steps"], "misses": r["deadline_misses"],
        "miss_pct": 100.0 * r["miss_rate"], "rtf": r["rtf"], "collisions": r["collisions"],
        "agents_cores": cpu["agents_cores"], "cores": cpu["cores_used"], "p99_ms": lat["p99"],
        "plans": _plans_taken(r["out"], r["steps"]), "late": math.nan if late is None else late,
        "load": r["loadavg_before"][0],
        **cpu.get("agents_threads_cores", dict.fromkeys(("main", "zenoh", "callbacks"), math.nan)),
    }  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, default=32, choices=sorted(SCENES))
    ap.add_argument("--seconds", type=float, default=60.0, help="simulated seconds a run (default 60)")
    ap.add_argument("--order", default="mesh,place,mesh,place", help="the runs' exchanges, in order")
    ap.add_argument("--out", default="out/bench_exchange", help="the runs' directories")
    ap.add_argument("--json", help="write the rows to this file")
    args = ap.parse_args(argv)
    if not (math.isfinite(args.seconds) and args.seconds > 0):
        print(f"bench_exchange: error: --seconds: {args.seconds} is not a positive number", file=sys.stderr)
        return 2
    order = args.order.split(",")
    bad = [e for e in order if e.partition("/")[0] not in EXCHANGES or e.partition("/")[2] not in RUNTIMES]
    if bad or not order:
        what = bad[0] if bad else "(empty)"
        print(
            f"bench_exchange: error: --order: {what} is not one of {', '.join(EXCHANGES)}, "
            "each alone or with /zenoh", file=sys.stderr,
        )  # fmt: skip
        return 2
    print(
        f"# {machine_info()['cpu']}, {os.cpu_count()} cores, "
        f"load {os.getloadavg()[0]:.1f}: "
        f"swap of {args.robots} robots, realtime, {args.seconds:g} s a run, default flags but --exchange"
    )
    head = f"{'exchange':<12}{'steps':>6}{'misses':>8}{'miss %':>8}{'RTF':>6}{'coll':>5}{'agents':>8}"
    head += f"{'cores':>6}{'p99 ms':>8}{'plans':>7}{'late':>5}{'load':>6}"
    print(head + "  agents' threads: main zenoh callbacks")
    rows = []
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        for i, ex in enumerate(order):
            exchange, _, runtime = ex.partition("/")
            tag, environ = f"{exchange}_{runtime or 'sized'}_{i}", RUNTIMES[runtime]
            run = fleet_run(args.robots, "realtime", args.seconds, out, Path(tmp), print, exchange=exchange,
                            topology=None, tag=tag, environ=environ)  # fmt: skip
            r = _row(run, ex)
            rows.append(r)
            if "error" in r:
                print(f"{ex:<12} failed: {r['error']}")
                continue
            print(
                f"{ex:<12}{r['steps']:>6}{r['misses']:>8}{r['miss_pct']:>8.2f}{r['rtf']:>6.2f}{r['collisions']:>5}"
                f"{r['agents_cores']:>8.2f}{r['cores']:>6.2f}{r['p99_ms']:>8.1f}{r['plans']:>7.1f}{r['late']:>5.0f}{r['load']:>6.1f}"
                f"  {r['main']:.2f} {r['zenoh']:.2f} {r['callbacks']:.2f}",
                flush=True,
            )
    done = [r for r in rows if "error" not in r]
    medians = {
        ex: {f: statistics.median(r[f] for r in done if r["exchange"] == ex) for f in FIGURES}
        for ex in dict.fromkeys(r["exchange"] for r in done)
    }
    if medians:
        base = next(iter(medians))
        print(f"# medians, and ratios to {base}: " + ", ".join(FIGURES))
        for ex, m in medians.items():
            ratios = " ".join(
                f"{m[f] / medians[base][f]:.2f}" if medians[base][f] else "nan" for f in FIGURES
            )
            print(f"{ex:<12}" + " ".join(f"{m[f]:.3g}" for f in FIGURES) + f"   ({ratios})")
    if args.json:
        Path(args.json).write_text(json.dumps({"rows": rows, "medians": medians}, indent=1))
    return 1 if len(done) < len(rows) else 0


if __name__ == "__main__":
    sys.exit(main())
