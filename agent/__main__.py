"""``python -m agent``: one robot's agent process (see :mod:`agent.node`)."""

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")  # ProxSuite links libgomp (docs/method.md §9)

from agent.node import main
from transport.process import exit_process

exit_process(main())
