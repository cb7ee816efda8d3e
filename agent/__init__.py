"""One robot's agent: the tube MPC and the process that runs it.

The math, which imports no transport, logging or plotting (docs/method.md maps each equation):

* :mod:`agent.sets` — zonotopes, support functions, the mRPI outer approximation;
* :mod:`agent.tube` — offline synthesis: K, Z, the tightened sets, K_r, Ψ, ρ, the footprint;
* :mod:`agent.qp` — the per-step QP, assembled once, solved by ProxSuite;
* :mod:`agent.coordination` — the split rule, obstacle and hazard half-planes, the penalty;
* :mod:`agent.navigator` — the goal term's target: grid path, precedence yielding, escapes;
* :mod:`agent.hazards` — which neighbours are coordinated with and which are kept clear of;
* :mod:`agent.controller` — one step: QP, shifted-candidate fallback, ancillary law, commit.

The step protocol, which both the process and ``fleet simulate`` drive: :mod:`agent.protocol`
(the plan and command of a step, the plan made a step ahead, the candidate followed).

The process: :mod:`agent.node` (``python -m agent``).
"""
