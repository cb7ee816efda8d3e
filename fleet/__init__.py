"""The ``fleet`` command and what it runs.

* :mod:`fleet.cli` — the command line (``fleet design | simulate | run | goal | report | bench |
  markers | calibrate``);
* :mod:`fleet.launch` — ``fleet run``: the processes of a fleet, started and stopped;
* :mod:`fleet.simulate` — ``fleet simulate``: the whole fleet in one process;
* :mod:`fleet.operator` — ``fleet goal``; :mod:`fleet.report` — ``fleet report``;
* :mod:`fleet.scenes` — programmatic scenes (swaps, random scenes);
* :mod:`fleet.secure` — the secure deployment's router, configurations and access control;
* :mod:`fleet.bench` — ``fleet bench``.
"""
