"""``python -m tracker``: the pose source and lockstep clock (see :mod:`tracker.sim`)."""

from fleet.runtime import exit_process
from tracker.sim import main

exit_process(main())
