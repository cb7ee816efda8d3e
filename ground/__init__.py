"""The ground the fleet stands on: the contract every process shares, importing nothing of ours.

* :mod:`ground.wire` — Zenoh keys and the versioned msgpack messages, with strict decoders;
* :mod:`ground.scenario` and :mod:`ground.params` — the scenario and controller schema;
* :mod:`ground.geometry` — the controlled point, the measured state, angle wrapping;
* :mod:`ground.model` — the nominal double-integrator model;
* :mod:`ground.freespace` — one model of free space past the walls and obstacles;
* :mod:`ground.arrival` — the order of arrival a layout forces, and the wait points that keep it.

The Zenoh transport stands one layer up, in :mod:`transport`.
"""
