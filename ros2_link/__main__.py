"""``python -m ros2_link``: see :mod:`ros2_link.node`."""

from ros2_link.node import main
from transport.process import exit_process

exit_process(main())
