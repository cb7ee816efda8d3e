"""``python -m supervisor``: see :mod:`supervisor.monitor`."""

from ground.process import exit_process
from supervisor.monitor import main

exit_process(main())
