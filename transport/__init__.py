"""How the fleet's processes reach one another: one layer above the contract (:mod:`ground`).

* :mod:`transport.net` — the Zenoh configuration: peer mesh, client or router, TLS, the runtime;
* :mod:`transport.bus` — the session, publishers, the inbox each process drains, joining a fleet
  from outside, asking an agent for a goal;
* :mod:`transport.process` — the prologue of every process and the options they all share;
* :mod:`transport.faults` — the fault-injection plan the inbox applies.

The math of one robot (``agent``'s controller and its parts), the safety judge and the robot
side's decisions import none of it.
"""
