"""``fleet bench``: the scale and performance benchmark.

The harness is ``benchmarks/bench_scale.py`` in the source tree (it shares its
instrumentation with ``benchmarks/bench_step.py``); this module is the command's
thin shell.  :func:`add_arguments` declares the options without importing
anything heavy (building the ``fleet`` parser stays cheap), and :func:`run`
loads the harness from the checkout and runs it.  ``python -m fleet.bench``
does the same without the ``fleet`` entry point.  What the figures mean:
docs/performance.md.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import sys
from pathlib import Path
from types import ModuleType

from fleet.launch import TOPOLOGIES
from transport.process import EXCHANGES, seed_arg

HARNESS = Path(__file__).resolve().parent.parent / "benchmarks" / "bench_scale.py"
"""The harness in the source checkout this package is installed from (editable install)."""
LIVENESS = HARNESS.with_name("bench_liveness.py")
"""The liveness harness (``--liveness N``), beside it."""
CPU = HARNESS.with_name("bench_cpu.py")
"""The CPU harness (``--cpu N``): fleet run against fleet simulate, by process and thread."""
TARGETS = HARNESS.with_name("bench_targets.py")
"""The runtime targets (``--targets``): CPU ratio, realtime misses, latency, start-up."""


class HarnessMissing(RuntimeError):
    """The package was installed without its source tree, so there is no harness to run."""


def _harness(path: Path = HARNESS) -> ModuleType:
    """The harness module, loaded once from ``path`` (:data:`HARNESS` or :data:`LIVENESS`)."""
    if not path.is_file():
        raise HarnessMissing(f"{path} not found: fleet bench needs the source checkout (pip install -e .)")
    os.environ["OMP_NUM_THREADS"] = "1"  # before the harness imports proxsuite
    name = path.stem
    mod = sys.modules.get(name)
    if mod is None or getattr(mod, "__file__", None) != str(path):
        spec = importlib.util.spec_from_file_location(name, path)
        assert spec is not None and spec.loader is not None
        mod = importlib.util.module_from_spec(spec)
        sys.modules[name] = mod
        spec.loader.exec_module(mod)
    return mod


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
        help="instead: run N hard scenes (fleet.scenes.hard_scene, seeds from --seed) through fleet "
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
        "fleet.scenes.HARD_FAMILIES, the default), 'layout' (fleet.scenes.LAYOUT_FAMILIES: pockets, "
        "single-file lanes, rooms, concentric rings, clutter), 'scale' (fleet.scenes.SCALE_FAMILIES: "
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
    from fleet.scenes import HARD_FAMILIES, LAYOUT_FAMILIES, SCALE_FAMILIES

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


def run(args: argparse.Namespace) -> int:
    """Run the benchmark; 0 once the tables are printed and the JSON written, 2 without a harness."""
    for name in ("liveness", "jobs"):
        value = getattr(args, name)
        if value is not None and value < 1:
            print(f"fleet: error: --{name}: must be at least 1, got {value}", file=sys.stderr)
            return 2
    if args.liveness is not None:
        try:
            args.families = families(args.families)
        except ValueError as e:
            print(f"fleet: error: --families: {e}", file=sys.stderr)
            return 2
    chosen = [f for f, on in (("--liveness", args.liveness is not None), ("--cpu", args.cpu is not None),
                              ("--targets", args.targets)) if on]  # fmt: skip
    if len(chosen) > 1:
        print(f"fleet: error: {chosen[1]}: not with {chosen[0]} (one harness a run)", file=sys.stderr)
        return 2
    path = {"--liveness": LIVENESS, "--cpu": CPU, "--targets": TARGETS}.get(
        chosen[0] if chosen else "", HARNESS
    )
    try:
        mod = _harness(path)
    except HarnessMissing as e:
        print(f"fleet: error: {e}", file=sys.stderr)
        return 2
    return int(mod.run(args))


def main(argv: list[str] | None = None) -> int:
    """``python -m fleet.bench``: parse ``argv`` and :func:`run`; returns its exit code."""
    ap = argparse.ArgumentParser(prog="fleet bench", description=__doc__.splitlines()[0])
    add_arguments(ap)
    return run(ap.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
