"""The options of ``fleet bench`` (and of ``python -m benchmarks.bench_scale``), declared without
importing anything heavy, so that building the ``fleet`` parser stays cheap."""

from __future__ import annotations

import argparse

from fleet.running.launch import TOPOLOGIES
from transport.process import EXCHANGES, seed_arg


def add_arguments(ap: argparse.ArgumentParser) -> None:
    """Declare the options of ``fleet bench`` (and of ``benchmarks/bench_scale.py``) on ``ap``.

    Fleet sizes name shipped scenes: 3 paper_three_robots, 8 swap_8, 16 swap_16, 32 swap_32."""
    ap.add_argument(
        "--quick", action="store_true", help="tiny configuration (< 1 min): every figure, few samples"
    )
    ap.add_argument("--json", metavar="OUT.json", help="where to write the figures (default DIR/bench.json)")
    ap.add_argument(
        "--out", metavar="DIR", default="out/bench", help="run directories and JSON (default out/bench)"
    )
    ap.add_argument("--seed", type=seed_arg, default=0, help="seed of the step grid and the recorded QPs")
    ap.add_argument(
        "--steps", type=int, default=None, help="steps per step-grid cell (default 600; quick 12)"
    )
    ap.add_argument(
        "--lockstep", default=None, metavar="N,N,…",
        help="fleet sizes of the lockstep real-time-factor runs (default 3,8,16,32; quick 3)",
    )  # fmt: skip
    ap.add_argument(
        "--realtime", default=None, metavar="N,N,…",
        help="fleet sizes of the realtime runs (default 16,32; quick 3); the largest runs again at "
        "twice the period for the capacity figure [6]",
    )  # fmt: skip
    ap.add_argument(
        "--lockstep-s", type=float, default=None, metavar="S",
        help="simulated seconds per lockstep run (default 40; quick 10)",
    )  # fmt: skip
    ap.add_argument(
        "--realtime-s", type=float, default=None, metavar="S",
        help="seconds per realtime run at Ts (default 60; quick 3)",
    )  # fmt: skip
    ap.add_argument(
        "--exchange", choices=["auto", *EXCHANGES], default="relay",
        help="how the fleet runs' plans travel (fleet run --exchange; default relay)",
    )  # fmt: skip
    ap.add_argument(
        "--topology", choices=TOPOLOGIES, default="star",
        help="how the fleet runs' processes link (fleet run --topology; default star: the tracker a "
        "router, one link per process)",
    )  # fmt: skip
    ap.add_argument(
        "--delay-compensation", action=argparse.BooleanOptionalAction, default=True,
        help="the fleet runs plan a step ahead, as fleet run does by default; --no-delay-compensation "
        "runs them with fleet run --no-delay-compensation",
    )  # fmt: skip
    ap.add_argument("--no-fleet", action="store_true", help="skip the fleet runs (figures [4] to [6])")
    ap.add_argument(
        "--liveness", type=int, default=None, metavar="N",
        help="instead: run N hard scenes (fleet.running.scenes.hard_scene, seeds from --seed) through fleet "
        "simulate and print completion, time to goal and path efficiency (docs/performance.md)",
    )  # fmt: skip
    ap.add_argument("--jobs", type=int, default=2, help="--liveness: processes (default 2)")
    ap.add_argument(
        "--liveness-realtime", action="store_true",
        help="--liveness: run each scene as a process fleet on the realtime clock with its defaults "
        "(fleet run --clock realtime: plans by place), one at a time, instead of in fleet simulate",
    )  # fmt: skip
    ap.add_argument(
        "--liveness-floor", action="store_true",
        help="--liveness: run nothing; print per family the floor of path efficiency, each robot's "
        "shortest way alone past the walls and obstacles over its straight line",
    )  # fmt: skip
    ap.add_argument(
        "--families", default="hard", metavar="LIST",
        help="--liveness: the scene families, in turn by seed: 'hard' (the seven of "
        "fleet.running.scenes.HARD_FAMILIES, the default), 'layout' "
        "(fleet.running.scenes.LAYOUT_FAMILIES: pockets, single-file lanes, rooms, concentric "
        "rings, clutter), 'scale' (fleet.running.scenes.SCALE_FAMILIES: "
        "100 robots on a circle, in a grid permutation, among obstacles), 'all' (hard and layout), "
        "or a comma-separated list",
    )  # fmt: skip
    ap.add_argument(
        "--cpu", type=int, default=None, metavar="N",
        help="instead: the marginal CPU per robot-step of fleet run (defaults, --ros2, "
        "--no-delay-compensation, place, relay + star) against fleet simulate on the swap of N "
        "robots (3, 8, 16, 32), split by process (agents, tracker, supervisor, the ROS 2 face) "
        "and thread",
    )  # fmt: skip
    ap.add_argument(
        "--targets", action="store_true",
        help="instead: the runtime targets of fleet run with its default flags: CPU per robot-step "
        "against fleet simulate (16 robots), realtime deadline misses (32, and 48), pose-to-command "
        "p99 (16) and the time to the first tick (16), with goal, figure and verdict each",
    )  # fmt: skip
    ap.add_argument(
        "--cpu-s", default="6,46", metavar="S,S",
        help="--cpu: the two run lengths [simulated s] whose difference is measured (default 6,46)",
    )  # fmt: skip


def families(text: str) -> tuple[str, ...]:
    """``--families``: 'hard', 'layout', 'all' or a comma-separated list of family names, as a
    tuple; ValueError names an unknown one."""
    from fleet.running.scenes import HARD_FAMILIES, LAYOUT_FAMILIES, SCALE_FAMILIES

    named = {
        "hard": HARD_FAMILIES, "layout": LAYOUT_FAMILIES, "scale": SCALE_FAMILIES,
        "all": HARD_FAMILIES + LAYOUT_FAMILIES,
    }  # fmt: skip
    if text in named:
        return named[text]
    out = tuple(f.strip() for f in text.split(",") if f.strip())
    known = HARD_FAMILIES + LAYOUT_FAMILIES + SCALE_FAMILIES
    for f in out:
        if f not in known:
            raise ValueError(f"unknown family {f!r} (families: {', '.join(known)})")
    if not out:
        raise ValueError("no family named")
    return out
