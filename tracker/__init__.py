"""The world the agents see: poses and the clock, from a simulation or an overhead camera.

* :mod:`tracker.world` — simulated plants, their disturbances and the simulated camera noise;
* :mod:`tracker.sim` — the simulated tracker process, the fleet's clock (``python -m tracker``);
* :mod:`tracker.reports` — what ``epuck_link`` processes applied, told in the next tick;
* :mod:`tracker.vision` — ArUco detection and the floor homography;
* :mod:`tracker.camera` — the camera tracker process (``python -m tracker --source camera``);
* :mod:`tracker.intrinsics` — the lens model and its ChArUco calibration.

The camera's offline tools (``fleet markers``, ``fleet calibrate``, the synthetic camera) are the
package :mod:`camera_tools`: the tracker process loads none of them.
"""
