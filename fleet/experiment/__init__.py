"""Experiments as Python scripts (``from fleet import Fleet``).

* :mod:`fleet.experiment.api` — :class:`~fleet.experiment.api.Fleet`: start or join a fleet, set
  goals, read poses and events, stop;
* :mod:`fleet.experiment.backend` — what a backend gives the API (events, samples);
* :mod:`fleet.experiment.script` — the backend of processes on the bus (``fleet run``'s fleet,
  started or joined); the in-process one is :class:`fleet.experiment.api.SimulatedFleet`.
"""
