"""Secure deployment: mutual TLS and access control on the fleet's Zenoh network.

Topology.  One Zenoh router, on the lab computer, listens on a ``tls/``
endpoint.  Every fleet process (agents, ``epuck_link``, tracker, supervisor,
``fleet goal``, a script's ``Fleet.connect``) is a Zenoh *client* of that
router, so every message passes through it and nothing travels peer to peer.
The link is TLS 1.3 with certificates on both sides (mTLS), all issued by the
fleet's own CA (``deploy/make_certs.py``): a client without a certificate, or
with one from another CA, fails the handshake and never gets a session.

Identity.  A client's identity is the common name (CN) of its certificate:
the robot id for the agent and the ``epuck_link`` of that robot, and
``tracker``, ``supervisor``, ``operator`` (``fleet goal`` and scripts) for the
services (``router`` is the router's own), ``ros2`` for the ROS 2 face and
``ros_client`` for ROS 2 tools.  :func:`identity` maps a process role to it.

Rights.  The router's access control (Zenoh ``access_control``) is
default-deny and grants, for fleet ``F`` (keys of :mod:`ground.wire`):

==============  ======================================================  =====================
identity        may publish (put)                                       liveliness token
==============  ======================================================  =====================
robot ``R``     ``F/plan/R`` ``F/cmd/R`` ``F/odom/R`` ``F/wheels/R``     ``F/alive/R``
                ``F/emu/R`` ``F/applied/R`` ``F/link/R``                ``F/at/R/**``
                ``F/near/*/R``
``tracker``     ``F/pose/*`` ``F/truth/*`` ``F/clock`` ``F/outcome``     —
                (and ``F/odom/*`` and ``F/digest`` with
                ``sim_tracker``: the simulated tracker plays every
                robot's side and relays plans)
``supervisor``  —                                                       ``F/alive/supervisor``
``operator``    ``F/goal/*``                                            ``F/alive/script``
==============  ======================================================  =====================

Goals also travel as Zenoh queries (a script of :class:`fleet.Fleet` asks for
them and waits for the agent's answer): only the ``operator`` may query
``F/goal/*``, robot ``R`` receives the queries on ``F/goal/R`` only and may
declare its queryable and reply there, and only the operator receives the
replies.  So a script with the operator's certificate joins a fleet
(``Fleet.connect``) with its token ``F/alive/script``; it cannot permit or stop
steps (``F/script`` is granted to nobody: a script permits steps only to a
fleet it launched itself, on loopback).

ROS 2.  With a ROS domain ``D`` (``acl_json(..., ros_domain=D)``, ``--ros-domain D``), the
ROS face (``python -m ros2_link``, identity ``ros2``) and ROS 2 clients (rmw_zenoh: ``ros2
topic echo``, RViz; identity ``ros_client``) get, for every robot ``R`` (keys of
:func:`ros_keys`; a topic's DDS type name and type hash follow it):

==============  ===========================================  =========================================
identity        may publish (put)                            may also
==============  ===========================================  =========================================
``ros2``        ``D/R/pose/**`` ``D/R/plan/**``              subscribe to ``F/pose/*`` ``F/plan/*``
                ``D/R/reference/**``                         ``F/clock`` and ``D/R/goal_pose/**``;
                ``D/fleet/footprints/**``                    query ``F/goal/*`` (the agents answer);
                                                             tokens under ``@ros2_lv/D/**``
``ros_client``  —                                            subscribe to the ROS data keys (the
                                                             first column); subscribe to and query
                                                             ``@ros2_lv/D/**``, tokens there
``operator``    ``D/R/goal_pose/**`` (RViz's goals)          as ``ros_client``
==============  ===========================================  =========================================

``ros2`` and ``ros_client`` are not members of the fleet: they read nothing else of
``F/**``, and ``ros_client`` publishes nothing at all (its ``goal_pose`` is dropped).

Every identity of the fleet may declare subscribers, liveliness subscribers and
liveliness queries on ``F/**`` and receive what is published there.
Everything else is dropped at the router: a put outside the table (robot r1 on
``F/plan/r2``, anyone but the tracker on ``F/pose/*``, anyone on
``F/script``), deletes, a query from anyone but the operator, a queryable or a
reply anywhere but a robot's own goal key, any key outside ``F/**``, anything
from a client whose CN is not in the fleet.  Drops are silent to the sender
(Zenoh does not report them; a dropped query ends at once without a reply); the
router logs each decision at ``RUST_LOG=trace``.

Configuration.  :func:`client_config` builds the ``zenoh.Config`` of a role
from a certificate directory and the router's endpoint, :func:`router_config`
the router's; :func:`client_json`, :func:`router_json` and :func:`acl_json`
are the same as plain JSON-able dicts.  ``deploy/*.json5`` are the same
configurations as commented templates (``${NAME}`` placeholders, filled by
:func:`render`); a test keeps them equal to these functions.

Command line (``python -m secure_router``):

- ``router --config deploy/router.json5 --set CERTS=DIR --set LISTEN=tls/IP:7447``
  (or ``router --certs DIR --listen EP --robots r1 r2 ...``) runs the router
  until SIGTERM/SIGINT, after printing ``{"event": "ready", "role": "router", ...}``;
- ``config ROLE [--robot R] --certs DIR --router EP`` prints a client's
  configuration (``config router ...`` the router's) as JSON;
- ``probe`` opens a client session, reports what it receives as JSON lines
  and publishes what it is told on stdin: a diagnostic for a deployment, and
  the client the tests start.
"""

from __future__ import annotations

import argparse
import json
import re
import signal
import sys
import threading
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ground.scenario import ROS_DOMAIN_MAX
from ground.wire import ROBOT_ID, SCRIPT, Keys
from ros2_link.graph import ADMIN_SPACE, FOOTPRINTS, GOAL_POSE, ROBOT_TOPICS, robot_topic
from transport.net import SecureConfigError, load_config

SERVICES = ("tracker", "supervisor", "operator")
"""Identities of the fleet's services (certificate common names)."""
ROS = ("ros2", "ros_client")
"""Identities of the ROS 2 face (``python -m ros2_link``) and of ROS 2 clients (``ros2 topic echo``,
RViz): not members of the fleet, they have only the ROS rights of :func:`acl_json`."""
ROUTER = "router"
"""Common name of the router's certificate."""
ROLES = ("agent", "link", "tracker", "supervisor", "operator", *ROS)
"""Process roles: ``agent`` and ``link`` (``epuck_link``) act for a robot and use its identity."""
WILDCARD_HOSTS = ("0.0.0.0", "[::]", "::", "*")
_ENDPOINT = re.compile(r"^tls/(?P<host>\[[0-9A-Fa-f:.]+\]|[^/:\[\]]+):(?P<port>\d{1,5})$")


def identity(role: str, robot: str | None = None) -> str:
    """The certificate common name a process of ``role`` uses (the robot id for agent and link)."""
    if role not in ROLES:
        raise SecureConfigError(f"role: {role!r} is not one of {', '.join(ROLES)}")
    if role in ("agent", "link"):
        if robot is None or not ROBOT_ID.fullmatch(robot):
            raise SecureConfigError(f"robot: role {role!r} needs a robot id matching {ROBOT_ID.pattern}")
        if robot in (*SERVICES, *ROS, ROUTER):
            raise SecureConfigError(f"robot: {robot!r} is the name of a service")
        return robot
    if robot is not None:
        raise SecureConfigError(f"robot: role {role!r} does not act for a robot")
    return role


def check_endpoint(endpoint: str, listen: bool = False, allow_wildcard: bool = False) -> str:
    """``endpoint`` if it is ``tls/<host>:<port>``; a listening one must name an interface.

    A wildcard listen address (``0.0.0.0``, ``[::]``) exposes the router on
    every interface; pass ``allow_wildcard`` to accept that deliberately."""
    m = _ENDPOINT.match(endpoint)
    if m is None:
        raise SecureConfigError(f"endpoint: {endpoint!r} is not tls/<host>:<port> (only TLS is secure)")
    if not 0 <= int(m["port"]) <= 65535 or (not listen and int(m["port"]) == 0):
        raise SecureConfigError(f"endpoint: {endpoint!r} has a bad port")
    if listen and not allow_wildcard and m["host"] in WILDCARD_HOSTS:
        raise SecureConfigError(
            f"endpoint: {endpoint!r} listens on every interface; name the lab network's address"
        )
    return endpoint


@dataclass(frozen=True)
class Credentials:
    """The three PEM files of one identity, as ``deploy/make_certs.py`` lays them out."""

    ca: Path
    """The fleet CA's certificate: ``<certs>/<name>/ca.pem``."""
    cert: Path
    """The identity's certificate, CN = name: ``<certs>/<name>/cert.pem``."""
    key: Path
    """Its private key (PKCS#8, mode 0600): ``<certs>/<name>/key.pem``."""

    @classmethod
    def of(cls, certs: str | Path, name: str, check: bool = True) -> Credentials:
        """The files of ``name`` under ``certs`` (absolute paths); ``check``: they must exist."""
        d = Path(certs).expanduser().resolve() / name
        creds = cls(ca=d / "ca.pem", cert=d / "cert.pem", key=d / "key.pem")
        if check:
            for f in (creds.ca, creds.cert, creds.key):
                if not f.is_file():
                    raise SecureConfigError(
                        f"certs: {f} is missing (python deploy/make_certs.py {Path(certs)} ...)"
                    )
        return creds


def client_json(
    role: str,
    certs: str | Path,
    router: str,
    robot: str | None = None,
    connect_timeout_s: float = 0.0,
    check: bool = True,
) -> dict[str, Any]:
    """The Zenoh configuration of a fleet process, as a JSON-able dict.

    ``role``: one of :data:`ROLES`; ``robot``: the robot id for ``agent`` and
    ``link``.  ``certs``: the directory ``deploy/make_certs.py`` wrote (only
    ``<certs>/<identity>/`` is read).  ``router``: the router's
    ``tls/<host>:<port>``, where ``<host>`` must be a name or address of the
    router's certificate.  ``connect_timeout_s`` [s]: how long to retry
    connecting before ``zenoh.open`` fails; 0 tries once, a negative value
    retries for ever.  Client mode, no listener, multicast scouting off."""
    creds = Credentials.of(certs, identity(role, robot), check=check)
    timeout_ms = -1 if connect_timeout_s < 0 else round(connect_timeout_s * 1000)
    return {
        "mode": "client",
        "connect": {"endpoints": [check_endpoint(router)], "timeout_ms": timeout_ms},
        "listen": {"endpoints": []},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {
            "link": {
                "tls": {
                    "root_ca_certificate": str(creds.ca),
                    "connect_certificate": str(creds.cert),
                    "connect_private_key": str(creds.key),
                    "enable_mtls": True,
                    "verify_name_on_connect": True,
                    "close_link_on_expiration": True,
                }
            }
        },
    }


def ros_keys(robots: Sequence[str], domain: int) -> tuple[list[str], list[str], list[str]]:
    """(data, goals, graph): the key expressions of the ROS face on ROS domain ``domain``.

    ``data``: what the face publishes, ``<domain>/<id>/<topic>/**`` for the topics of
    :data:`ros2_link.graph.ROBOT_TOPICS` and ``<domain>/fleet/footprints/**`` (a topic's DDS type
    name and type hash follow its name); ``goals``: ``<domain>/<id>/goal_pose/**``, where it takes goals;
    ``graph``: ``@ros2_lv/<domain>/**``, the domain's liveliness tokens (rmw_zenoh's
    discovery)."""
    if isinstance(domain, bool) or not isinstance(domain, int) or not 0 <= domain <= ROS_DOMAIN_MAX:
        raise SecureConfigError(f"ros_domain: {domain!r} is not a ROS 2 domain id, 0 … {ROS_DOMAIN_MAX}")
    data = [f"{domain}{robot_topic(r, t)}/**" for r in robots for t in ROBOT_TOPICS] + [
        f"{domain}{FOOTPRINTS}/**"
    ]
    goals = [f"{domain}{robot_topic(r, GOAL_POSE)}/**" for r in robots]
    return data, goals, [f"{ADMIN_SPACE}/{domain}/**"]


def acl_json(
    robots: Sequence[str], fleet: str = "lab", sim_tracker: bool = False, ros_domain: int | None = None
) -> dict[str, Any]:
    """The router's ``access_control`` section for ``robots`` of fleet ``fleet`` (see the module table).

    ``sim_tracker``: the tracker may also publish every robot's ``odom`` (the
    simulated tracker plays the robots' side; a camera tracker does not).
    ``ros_domain``: the ROS 2 domain of the fleet's ROS face (``python -m ros2_link
    --ros-domain N``), which then gets the rights of the module's ROS table; None: no ROS
    rights at all."""
    robots = list(robots)
    for r in robots:
        identity("agent", r)
    if len(set(robots)) != len(robots) or not robots:
        raise SecureConfigError(f"robots: need distinct robot ids, got {robots}")
    k = Keys(fleet)

    def rule(rid: str, messages: list[str], flow: str, key_exprs: list[str]) -> dict[str, Any]:
        return {"id": rid, "messages": messages, "flows": [flow], "permission": "allow",
                "key_exprs": key_exprs}  # fmt: skip

    everything = f"{k.root}/**"
    tracker_puts = [k.pose(), k.truth(), k.clock, k.outcome] + ([k.odom(), k.digest] if sim_tracker else [])
    rules = [
        rule("subscribe", ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"],
             "ingress", [everything]),
        rule("deliver", ["put", "declare_subscriber", "liveliness_token", "declare_liveliness_subscriber",
                         "liveliness_query"], "egress", [everything]),
        rule("publish-tracker", ["put"], "ingress", tracker_puts),
        rule("token-supervisor", ["liveliness_token"], "ingress", [k.alive("supervisor")]),
        rule("publish-operator", ["put"], "ingress", [k.goal()]),
        rule("query-operator", ["query"], "ingress", [k.goal()]),
        rule("token-operator", ["liveliness_token"], "ingress", [k.alive(SCRIPT)]),
        rule("answers-operator", ["reply"], "egress", [k.goal()]),
    ]  # fmt: skip
    subjects = [{"id": "members", "cert_common_names": [*robots, *SERVICES]}]
    subjects += [{"id": s, "cert_common_names": [s]} for s in SERVICES]
    policies = [
        {"id": "members", "rules": ["subscribe", "deliver"], "subjects": ["members"]},
        {"id": "tracker", "rules": ["publish-tracker"], "subjects": ["tracker"]},
        {"id": "supervisor", "rules": ["token-supervisor"], "subjects": ["supervisor"]},
        {"id": "operator", "subjects": ["operator"],
         "rules": ["publish-operator", "query-operator", "token-operator", "answers-operator"]},
    ]  # fmt: skip
    for r in robots:
        rules += [
            rule(
                f"publish-{r}",
                ["put"],
                "ingress",
                [k.plan(r), k.near(r), k.cmd(r), k.odom(r), k.wheels(r), k.emu(r), k.applied(r), k.link(r)],
            ),
            rule(f"token-{r}", ["liveliness_token"], "ingress", [k.alive(r), k.at(r)]),
            rule(f"goals-{r}", ["declare_queryable", "reply"], "ingress", [k.goal(r)]),
            rule(f"asked-{r}", ["query"], "egress", [k.goal(r)]),
        ]
        subjects.append({"id": f"robot-{r}", "cert_common_names": [r]})
        policies.append({"id": f"robot-{r}", "subjects": [f"robot-{r}"],
                         "rules": [f"publish-{r}", f"token-{r}", f"goals-{r}", f"asked-{r}"]})  # fmt: skip
    if ros_domain is not None:
        data, goals, graph = ros_keys(robots, ros_domain)
        fleet_reads = [k.pose(), k.plan(), k.clock]
        rules += [
            rule("ros-subscribe", ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"],
                 "ingress", data + graph),
            rule("ros-deliver",
                 ["put", "liveliness_token", "declare_liveliness_subscriber", "liveliness_query"],
                 "egress", data + graph),
            rule("ros-token", ["liveliness_token"], "ingress", graph),
            rule("ros-goal-subscribers", ["declare_subscriber"], "egress", goals),
            rule("publish-ros2", ["put"], "ingress", data),
            rule("ros2-subscribers", ["declare_subscriber"], "egress", data),
            rule("read-ros2", ["declare_subscriber"], "ingress", fleet_reads + goals),
            rule("receive-ros2", ["put"], "egress", fleet_reads + goals),
            rule("query-ros2", ["query"], "ingress", [k.goal()]),
            rule("answers-ros2", ["reply"], "egress", [k.goal()]),
            rule("publish-goal-pose", ["put"], "ingress", goals),
        ]  # fmt: skip
        subjects += [{"id": s, "cert_common_names": [s]} for s in ROS]
        policies += [
            {"id": "ros-readers", "subjects": ["ros_client", "operator"],
             "rules": ["ros-subscribe", "ros-deliver", "ros-token", "ros-goal-subscribers"]},
            {"id": "ros2", "subjects": ["ros2"],
             "rules": ["ros-token", "publish-ros2", "ros2-subscribers", "read-ros2", "receive-ros2",
                       "query-ros2", "answers-ros2"]},
            {"id": "ros-operator", "subjects": ["operator"], "rules": ["publish-goal-pose"]},
        ]  # fmt: skip
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


def router_json(
    listen: str,
    certs: str | Path,
    robots: Sequence[str],
    fleet: str = "lab",
    sim_tracker: bool = False,
    allow_wildcard: bool = False,
    check: bool = True,
    ros_domain: int | None = None,
) -> dict[str, Any]:
    """The router's Zenoh configuration, as a JSON-able dict.

    ``listen``: its only endpoint, ``tls/<address>:<port>`` on the lab
    network's interface (the address must be in the router certificate's
    subject alternative names, see ``make_certs.py --router-host``).  mTLS
    against the fleet CA, access control of :func:`acl_json`, no outgoing
    connections, multicast scouting off.  ``ros_domain``: see :func:`acl_json`."""
    creds = Credentials.of(certs, ROUTER, check=check)
    return {
        "mode": "router",
        "listen": {"endpoints": [check_endpoint(listen, listen=True, allow_wildcard=allow_wildcard)]},
        "connect": {"endpoints": []},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {
            "link": {
                "tls": {
                    "root_ca_certificate": str(creds.ca),
                    "listen_certificate": str(creds.cert),
                    "listen_private_key": str(creds.key),
                    "enable_mtls": True,
                    "close_link_on_expiration": True,
                }
            }
        },
        "access_control": acl_json(robots, fleet, sim_tracker, ros_domain),
    }


def to_zenoh(conf: dict[str, Any]) -> Any:
    """A ``zenoh.Config`` from a configuration dict (zenoh checks every key)."""
    import zenoh

    return zenoh.Config.from_json5(json.dumps(conf))


def client_config(
    role: str, certs: str | Path, router: str, robot: str | None = None, connect_timeout_s: float = 0.0
) -> Any:
    """The ``zenoh.Config`` of a fleet process (see :func:`client_json`)."""
    return to_zenoh(client_json(role, certs, router, robot, connect_timeout_s))


def router_config(
    listen: str,
    certs: str | Path,
    robots: Sequence[str],
    fleet: str = "lab",
    sim_tracker: bool = False,
    ros_domain: int | None = None,
) -> Any:
    """The router's ``zenoh.Config`` (see :func:`router_json`)."""
    return to_zenoh(router_json(listen, certs, robots, fleet, sim_tracker, ros_domain=ros_domain))


def _get(conf: Any, key: str) -> Any:
    return json.loads(conf.get_json(key))


def check_router(conf: Any, allow_wildcard: bool = False) -> list[str]:
    """The router's listen endpoints, after checking ``conf`` is a secure router configuration.

    Refuses (SecureConfigError) anything but router mode, TLS-only listeners
    (a plain ``tcp/`` one would admit anonymous clients), mTLS off, or access
    control off or default-allow."""
    if _get(conf, "mode") != "router":
        raise SecureConfigError("mode: a router configuration needs mode 'router'")
    eps = _get(conf, "listen/endpoints")
    if isinstance(eps, dict):
        eps = eps.get("router", [])
    if not eps:
        raise SecureConfigError("listen/endpoints: the router listens nowhere")
    for ep in eps:
        check_endpoint(ep, listen=True, allow_wildcard=allow_wildcard)
    if _get(conf, "transport/link/tls/enable_mtls") is not True:
        raise SecureConfigError("transport/link/tls/enable_mtls: must be true")
    if _get(conf, "access_control/enabled") is not True:
        raise SecureConfigError("access_control/enabled: must be true")
    if _get(conf, "access_control/default_permission") != "deny":
        raise SecureConfigError("access_control/default_permission: must be 'deny'")
    return list(eps)


# ------------------------------------------------------------------ processes
def serve_router(conf: Any, allow_wildcard: bool = False) -> int:
    """Run a router from ``conf`` until SIGTERM or SIGINT; 0 on a clean stop, 1 if it cannot start.

    Prints ``{"event": "ready", "role": "router", "pid", "zid", "listen"}`` once
    the listener is bound (``zenoh.open`` returns only then)."""
    import zenoh

    from transport.process import announce, log

    listen = check_router(conf, allow_wildcard)
    zenoh.init_log_from_env_or("warn")  # to stderr; RUST_LOG=trace also shows each ACL decision
    stop = {signal.SIGTERM, signal.SIGINT}
    # Blocked before zenoh starts its threads, which inherit the mask: only sigwait sees them.
    signal.pthread_sigmask(signal.SIG_BLOCK, stop)
    try:
        session = zenoh.open(conf)
    except zenoh.ZError as e:
        log("router", f"cannot start: {e}")
        return 1
    try:
        announce("router", zid=str(session.info.zid()), listen=listen)
        sig = signal.sigwait(stop)
        log("router", f"stopping on {signal.Signals(sig).name}")
    finally:
        session.close()
    return 0


class _Out:
    """JSON lines on stdout from several threads."""

    def __init__(self) -> None:
        self.lock = threading.Lock()

    def __call__(self, **event: Any) -> None:
        line = json.dumps(event)
        with self.lock:
            print(line, flush=True)


def probe(conf: Any, subs: Iterable[str], lives: Iterable[str], label: str) -> int:
    """A client that reports what it receives and publishes what stdin asks; 3 if it cannot connect.

    stdout, one JSON object per line: ``{"event": "ready", "role": "probe", ...}``
    or ``{"event": "open_failed", "error"}``, then ``{"event": "sample", "key",
    "payload"}`` per sample on ``subs``, ``{"event": "token", "key", "kind"}``
    per liveliness change on ``lives`` (``kind`` put or delete), ``{"event":
    "query", "key", "payload"}`` per query its queryables receive, ``{"event":
    "reply", "key", "payload"}`` per reply to its query (``"error"`` instead of
    ``"payload"`` for an error reply), ``{"event": "done", "op", "key"}`` after
    each request (with ``"replies"``, their number, after a query) and
    ``{"event": "error", ...}`` for a bad one.  stdin, one JSON object per
    line: ``{"put": KEY, "payload": TEXT}`` (blocking congestion control,
    express, as the fleet's publishers), ``{"token": KEY}`` (declare a
    liveliness token), ``{"queryable": KEY, "reply": TEXT}`` (declare a
    queryable that answers TEXT on KEY) or ``{"get": KEY, "payload": TEXT,
    "timeout": SECONDS}`` (query KEY, every reply kept, and wait for the end
    of the query; default timeout 10 s).  EOF ends the probe."""
    import zenoh

    from transport.process import announce

    out = _Out()
    try:
        session = zenoh.open(conf)
    except zenoh.ZError as e:
        out(event="open_failed", error=str(e))
        return 3

    def on_sample(s: Any) -> None:
        out(event="sample", key=str(s.key_expr), payload=s.payload.to_bytes().decode(errors="replace"))

    def on_token(s: Any) -> None:
        kind = "delete" if s.kind == zenoh.SampleKind.DELETE else "put"
        out(event="token", key=str(s.key_expr), kind=kind)

    def answer(key: str, text: str) -> Any:
        def on_query(q: Any) -> None:
            payload = b"" if q.payload is None else q.payload.to_bytes()
            out(event="query", key=str(q.key_expr), payload=payload.decode(errors="replace"))
            q.reply(key, text.encode())

        return on_query

    keep: list[Any] = [session.declare_subscriber(k, on_sample) for k in subs]
    keep += [session.liveliness().declare_subscriber(k, on_token, history=True) for k in lives]
    pubs: dict[str, Any] = {}
    with out.lock:
        announce("probe", identity=label, zid=str(session.info.zid()))
    try:
        for line in sys.stdin:
            if not line.strip():
                continue
            try:
                req = json.loads(line)
                if "put" in req:
                    key = str(req["put"])
                    if key not in pubs:
                        pubs[key] = session.declare_publisher(
                            key, congestion_control=zenoh.CongestionControl.BLOCK, express=True
                        )
                    pubs[key].put(str(req.get("payload", "")).encode())
                    out(event="done", op="put", key=key)
                elif "token" in req:
                    key = str(req["token"])
                    keep.append(session.liveliness().declare_token(key))
                    out(event="done", op="token", key=key)
                elif "queryable" in req:
                    key = str(req["queryable"])
                    keep.append(session.declare_queryable(key, answer(key, str(req.get("reply", "")))))
                    out(event="done", op="queryable", key=key)
                elif "get" in req:
                    key, n = str(req["get"]), 0
                    payload, timeout = str(req.get("payload", "")).encode(), float(req.get("timeout", 10.0))
                    none = zenoh.ConsolidationMode.NONE
                    for r in session.get(key, payload=payload, timeout=timeout, consolidation=none):
                        n += 1
                        if r.ok is not None:
                            text = r.ok.payload.to_bytes().decode(errors="replace")
                            out(event="reply", key=str(r.ok.key_expr), payload=text)
                        elif r.err is not None:
                            text = r.err.payload.to_bytes().decode(errors="replace")
                            out(event="reply", key=key, error=text)
                    out(event="done", op="get", key=key, replies=n)
                else:
                    out(event="error", error=f"unknown request {sorted(req)}")
            except (json.JSONDecodeError, AttributeError, TypeError, ValueError, zenoh.ZError) as e:
                out(event="error", error=f"{type(e).__name__}: {e}")
    finally:
        session.close()
    return 0


def _values(pairs: list[str]) -> dict[str, str]:
    values = {}
    for p in pairs:
        name, sep, value = p.partition("=")
        if not sep or not name:
            raise SecureConfigError(f"--set: expected NAME=VALUE, got {p!r}")
        values[name] = value
    return values


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python -m secure_router", description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)

    def router_args(p: argparse.ArgumentParser) -> None:
        p.add_argument("--certs", help="certificate directory of deploy/make_certs.py")
        p.add_argument("--listen", help="the router's endpoint, tls/<address>:<port>")
        p.add_argument("--robots", nargs="+", help="robot ids of the fleet")
        p.add_argument("--fleet", default="lab", help="fleet name in the keys (default lab)")
        p.add_argument("--sim-tracker", action="store_true",
                       help="the simulated tracker: it may also publish every robot's odom")  # fmt: skip
        p.add_argument("--allow-wildcard", action="store_true",
                       help="accept a listen endpoint on every interface (0.0.0.0, [::])")  # fmt: skip
        p.add_argument("--ros-domain", type=int, metavar="N",
                       help="grant the ROS 2 face (ros2) and ROS 2 clients (ros_client) their rights on "
                            f"this ROS domain, 0 … {ROS_DOMAIN_MAX} (default: no ROS rights)")  # fmt: skip

    r = sub.add_parser("router", help="run the fleet's router until SIGTERM")
    r.add_argument("--config", help="router configuration file (JSON5; instead of --certs/--listen/--robots)")
    r.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                   help="value of a ${NAME} placeholder of --config (repeatable)")  # fmt: skip
    router_args(r)

    c = sub.add_parser("config", help="print a role's configuration as JSON")
    c.add_argument("role", choices=[*ROLES, ROUTER])
    c.add_argument("--robot", help="robot id (agent, link)")
    c.add_argument("--router", help="the router's endpoint, tls/<host>:<port> (clients)")
    c.add_argument("--connect-timeout", type=float, default=0.0,
                   help="seconds to retry connecting (0 once, negative for ever)")  # fmt: skip
    router_args(c)

    p = sub.add_parser("probe", help="a diagnostic client (JSON lines on stdin/stdout)")
    p.add_argument("--config", help="client configuration file (instead of --role/--certs/--router)")
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    p.add_argument("--role", choices=ROLES)
    p.add_argument("--robot")
    p.add_argument("--certs")
    p.add_argument("--router")
    p.add_argument("--sub", action="append", default=[], help="key expression to subscribe to")
    p.add_argument("--live", action="append", default=[], help="liveliness key expression to watch")
    return ap


def _need(args: argparse.Namespace, *names: str) -> None:
    missing = [f"--{n.replace('_', '-')}" for n in names if getattr(args, n) in (None, [])]
    if missing:
        raise SecureConfigError(f"{', '.join(missing)}: required here")


def main(argv: list[str] | None = None) -> int:
    """``python -m secure_router router|config|probe``: run the fleet's router, print a role's
    configuration as JSON, or run a diagnostic client; returns the exit code (2 bad input)."""
    args = _parser().parse_args(argv)
    try:
        if args.cmd == "router":
            if args.config:
                conf = load_config(args.config, _values(args.set))
            else:
                _need(args, "certs", "listen", "robots")
                conf = to_zenoh(
                    router_json(args.listen, args.certs, args.robots, args.fleet, args.sim_tracker,
                                args.allow_wildcard, ros_domain=args.ros_domain)
                )  # fmt: skip
            return serve_router(conf, args.allow_wildcard)
        if args.cmd == "config":
            if args.role == ROUTER:
                _need(args, "certs", "listen", "robots")
                d = router_json(args.listen, args.certs, args.robots, args.fleet, args.sim_tracker,
                                args.allow_wildcard, ros_domain=args.ros_domain)  # fmt: skip
            else:
                _need(args, "certs", "router")
                d = client_json(args.role, args.certs, args.router, args.robot, args.connect_timeout)
            print(json.dumps(d, indent=2))
            return 0
        # probe
        if args.config:
            conf, label = load_config(args.config, _values(args.set)), str(args.config)
        else:
            _need(args, "role", "certs", "router")
            conf = client_config(args.role, args.certs, args.router, args.robot)
            label = identity(args.role, args.robot)
        return probe(conf, args.sub, args.live, label)
    except SecureConfigError as e:
        print(f"secure_router: error: {e}", file=sys.stderr)
        return 2
