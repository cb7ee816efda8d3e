"""``python -m tracker``: the pose source and lockstep clock (see :mod:`tracker.sim`)."""

import sys

from tracker.sim import main

sys.exit(main())
