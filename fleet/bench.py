"""``fleet bench``: the scale and performance benchmark.

The harnesses are the :mod:`benchmarks` package of the source tree (``benchmarks/bench_scale.py``
shares its instrumentation with ``benchmarks/bench_step.py``); this module is the command's thin
shell.  Its options live in :mod:`benchmarks.options`, which imports nothing heavy (building the
``fleet`` parser stays cheap), and :func:`run` imports the harness a run asks for and runs it.
``python -m fleet.bench`` does the same without the ``fleet`` entry point.  What the figures
mean: docs/performance.md.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from types import ModuleType

from benchmarks.options import add_arguments, families

HARNESSES = {"--liveness": "bench_liveness", "--cpu": "bench_cpu", "--targets": "bench_targets"}
"""The harness (a module of :mod:`benchmarks`) of each option that picks one; the scale and
performance figures are ``bench_scale``'s."""
DEFAULT = "bench_scale"
"""The harness of a run that names none of :data:`HARNESSES`."""


class HarnessMissing(RuntimeError):
    """The package was installed without its benchmarks, so there is no harness to run."""


def harness(name: str = DEFAULT) -> ModuleType:
    """The harness ``benchmarks.<name>``, imported with OpenMP at one thread (before ProxSuite)."""
    os.environ["OMP_NUM_THREADS"] = "1"
    try:
        return importlib.import_module(f"benchmarks.{name}")
    except ModuleNotFoundError as e:
        if e.name not in ("benchmarks", f"benchmarks.{name}"):
            raise
        raise HarnessMissing(
            f"benchmarks.{name} not found: fleet bench needs the source checkout (pip install -e .)"
        ) from e


__all__ = ["HARNESSES", "HarnessMissing", "add_arguments", "families", "harness", "main", "run"]


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
    try:
        mod = harness(HARNESSES[chosen[0]] if chosen else DEFAULT)
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
