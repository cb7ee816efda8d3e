"""``python -m ros2_link``: see :mod:`ros2_link.node`."""

from ground.process import exit_process
from ros2_link.node import main

exit_process(main())
