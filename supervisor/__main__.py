"""``python -m supervisor``: see :mod:`supervisor.monitor`."""

import sys

from supervisor.monitor import main

sys.exit(main())
