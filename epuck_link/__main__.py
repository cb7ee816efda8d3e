"""``python -m epuck_link``: the robot side of one E-puck (see :mod:`epuck_link.link`)."""

from epuck_link.link import main
from transport.process import exit_process

exit_process(main())
