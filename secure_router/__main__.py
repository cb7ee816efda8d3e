"""``python -m secure_router router|config|probe``: run the fleet's TLS router, print a role's
configuration, or probe what an identity may see (:func:`secure_router.access.main`)."""

from secure_router.access import main
from transport.process import exit_process

exit_process(main())
