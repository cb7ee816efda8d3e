"""``python -m agent``: one robot's agent process (see :mod:`agent.node`)."""

import os
import sys

os.environ.setdefault("OMP_NUM_THREADS", "1")  # ProxSuite links libgomp (DESIGN §8)

from agent.node import main

sys.exit(main())
