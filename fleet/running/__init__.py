"""Running fleets: what ``fleet run``, ``fleet simulate``, ``fleet goal`` and ``fleet report`` do.

* :mod:`fleet.running.launch` — ``fleet run``: the processes of a fleet, started, watched, stopped;
* :mod:`fleet.running.forkserver` — the fork server that starts the agents with their imports done;
* :mod:`fleet.running.simulate` — ``fleet simulate``: the whole fleet in one process, in lockstep;
* :mod:`fleet.running.operator` — ``fleet goal``; :mod:`fleet.running.report` — ``fleet report``;
* :mod:`fleet.running.scenes` — programmatic scenes (swaps, random scenes, the bench's families).
"""
