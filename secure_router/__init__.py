"""The secure deployment: mutual TLS and default-deny access control on the fleet's Zenoh network.

* :mod:`secure_router.access` — who may publish what (the rights, one identity per certificate),
  the router's and each client's Zenoh configuration, the router itself and the probe;
* ``python -m secure_router router|config|probe`` — its command line (``deploy/README.md``).

It stands beside the fleet's processes, on the transport: it loads neither the agent's math nor
the launcher.
"""
