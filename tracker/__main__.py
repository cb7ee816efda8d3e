"""``python -m tracker``: the pose source and clock.

``--source camera``: the ArUco camera tracker (:mod:`tracker.camera`, needs
OpenCV); ``--source sim`` (the default) or ``emulator``: :mod:`tracker.sim`.
Each parses the whole command line itself.
"""

import argparse
import sys

from transport.process import exit_process


def main(argv: list[str] | None = None) -> int:
    """``python -m tracker``: hand the whole command line to :func:`tracker.camera.main`
    (``--source camera``) or :func:`tracker.sim.main`; returns its exit code."""
    args = sys.argv[1:] if argv is None else argv
    peek = argparse.ArgumentParser(prog="python -m tracker", add_help=False)
    peek.add_argument("--source", choices=["sim", "emulator", "camera"], default="sim")
    source = peek.parse_known_args(args)[0].source
    if source == "camera":
        from tracker.camera import main as camera_main

        return camera_main(args)
    from tracker.sim import main as sim_main

    return sim_main(args)


exit_process(main())
