"""The overhead camera's offline tools, beside the tracker process that needs none of them.

* :mod:`camera_tools.markers` — ``fleet markers``: printable ArUco markers and ChArUco boards;
* :mod:`camera_tools.calibrate` — ``fleet calibrate``: the floor homography and the lens;
* :mod:`camera_tools.synth` — a synthetic camera, with lens distortion, for tests and rehearsals
  (``python -m camera_tools.synth``).
"""
