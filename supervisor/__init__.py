"""The supervisor: watches the whole fleet, judges safety live, records and summarises the run.

* :mod:`supervisor.judge` — the one safety judge, which ``fleet simulate`` uses too;
* :mod:`supervisor.monitor` — the supervisor process (``python -m supervisor``);
* :mod:`supervisor.recorder` — the Rerun recording;
* :mod:`supervisor.trace` — ``trace.npz``, which ``fleet report`` draws.
"""
