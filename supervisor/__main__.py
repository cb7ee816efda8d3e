"""``python -m supervisor``: see :mod:`supervisor.monitor`."""

from supervisor.monitor import main
from transport.process import exit_process

exit_process(main())
