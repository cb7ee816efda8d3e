"""The ground the fleet stands on: the contract every process shares, importing nothing of ours.

* :mod:`ground.wire` — Zenoh keys and the versioned msgpack messages, with strict decoders;
* :mod:`ground.scenario` and :mod:`ground.params` — the scenario and controller schema;
* :mod:`ground.geometry` — the controlled point, the measured state, angle wrapping;
* :mod:`ground.model` — the nominal double-integrator model;
* :mod:`ground.net`, :mod:`ground.bus`, :mod:`ground.process` — Zenoh configuration, the
  session and inbox, and the prologue of every process;
* :mod:`ground.faults` — the fault-injection plan.
"""
