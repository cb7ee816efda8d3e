"""Secure deployment: mutual TLS and access control at a real Zenoh router.

One router process (``python -m secure_router router`` on the shipped template
``deploy/router.json5``) listens on ``tls/127.0.0.1:<free port>``; the clients
are ``python -m secure_router probe`` processes, each with its own
certificate.  Certificates come from ``deploy/make_certs.py`` into tmp_path.
Multicast scouting is off everywhere; nothing binds a wildcard address.

Absence of a delivery is proved with a barrier, not a pause: the sender
publishes the forbidden message, then an allowed one of the same kind on the
same session, so both travel in one priority lane (data for puts, control
for liveliness declarations) and keep their order on the sender's link to
the router and on the router's link to the observer.  Once the observer has
the allowed one, the forbidden one would have arrived before it.
"""

from __future__ import annotations

import json
import stat
import subprocess
import sys
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from functools import partial
from pathlib import Path
from typing import Any

import pytest
from netns_util import LOCAL, HostProc
from procfs import tcp_sockets

from ground.wire import SCRIPT, Keys
from secure_router.access import (
    ROS,
    Credentials,
    SecureConfigError,
    acl_json,
    check_endpoint,
    check_router,
    client_json,
    identity,
    main,
    ros_keys,
    router_json,
    to_zenoh,
)
from transport.net import free_port, render

ROOT = Path(__file__).resolve().parents[2]
DEPLOY = ROOT / "deploy"
K = Keys("lab")
DELIVERY_S = 10.0
"""Limit for an allowed message to arrive [s]."""

Event = dict[str, Any]
Proc = HostProc
"""A child process printing JSON lines (tests/netns_util.py), on this host here."""


def _local(name: str, args: list[str], ends_on_eof: bool = True) -> Proc:
    """A child process on this host that prints JSON lines.  ``ends_on_eof``: it ends when its
    stdin closes (probes); otherwise SIGTERM ends it (the router)."""
    return HostProc(name, LOCAL, "local", args, None, stdin=ends_on_eof)


def _has(payload: str, key: str) -> Callable[[Event], bool]:
    return lambda e: e["event"] == "sample" and e["key"] == key and e["payload"] == payload


def deliver(sender: Proc, key: str, receivers: list[Proc], timeout: float = DELIVERY_S) -> str:
    """Publish fresh markers on ``key`` until every receiver got the same one; returns it.

    Repeats because a client learns of remote subscribers asynchronously; once
    one marker is through, the route exists."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        marker = f"ok-{uuid.uuid4().hex[:8]}"
        sender.send(put=key, payload=marker)
        if all(r.wait_for(_has(marker, key), 0.3) is not None for r in receivers):
            return marker
    raise AssertionError(f"{key} from {sender.name} did not reach {[r.name for r in receivers]}")


def barrier(sender: Proc, key: str, receivers: list[Proc]) -> None:
    """Publish one marker on ``key`` (an allowed key, after the forbidden ones) and wait for it."""
    marker = f"barrier-{uuid.uuid4().hex[:8]}"
    sender.send(put=key, payload=marker)
    for r in receivers:
        assert r.wait_for(_has(marker, key), DELIVERY_S) is not None, f"barrier {key} missed {r.name}"


# ------------------------------------------------------------------ fixtures
@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(fleet certificates, an unrelated CA's certificate for r1).

    The fleet's are for r1 r2 r3 r9 and the services; the router's ACL lists r1 r2 r3 only."""
    base = tmp_path_factory.mktemp("pki")
    fleet, rogue = base / "certs", base / "rogue"
    for args in ([str(fleet), "--robots", "r1", "r2", "r3", "r9"],
                 [str(rogue), "--robots", "r1", "--no-services", "--new-ca"]):  # fmt: skip
        res = subprocess.run(
            [sys.executable, str(DEPLOY / "make_certs.py"), *args], capture_output=True, text=True, timeout=60
        )
        assert res.returncode == 0, res.stderr
    return fleet, rogue


@pytest.fixture(scope="module")
def router(certs: tuple[Path, Path]) -> Iterator[tuple[str, Proc]]:
    """(endpoint, process) of a router running the shipped deploy/router.json5."""
    endpoint = f"tls/127.0.0.1:{free_port()}"
    proc = _local("router", ["-m", "secure_router", "router", "--config", str(DEPLOY / "router.json5"),
                           "--set", f"CERTS={certs[0]}", "--set", f"LISTEN={endpoint}"],
                ends_on_eof=False)  # fmt: skip
    try:
        ev = proc.ready()
        assert ev["role"] == "router" and ev["pid"] == proc.popen.pid and ev["listen"] == [endpoint]
        yield endpoint, proc
    finally:
        code = proc.stop()
    assert code == 0, f"the router did not stop cleanly on SIGTERM: {proc.tail()}"


@contextmanager
def probes() -> Iterator[Callable[..., Proc]]:
    """A factory of probe processes, every one stopped by pid on exit."""
    with ExitStack() as stack:

        def start(name: str, *args: str, subs: tuple[str, ...] = (), lives: tuple[str, ...] = ()) -> Proc:
            extra = [a for s in subs for a in ("--sub", s)] + [a for s in lives for a in ("--live", s)]
            p = _local(name, ["-m", "secure_router", "probe", *args, *extra])
            stack.callback(p.stop)
            return p

        yield start


def _member(certs: Path, endpoint: str, role: str, robot: str | None = None) -> tuple[str, ...]:
    args = ("--role", role, "--certs", str(certs), "--router", endpoint)
    return (*args, "--robot", robot) if robot else args


# ------------------------------------------------------------- certificates
def test_make_certs_writes_a_ca_and_one_identity_per_name(certs: tuple[Path, Path]) -> None:
    from cryptography import x509
    from cryptography.exceptions import InvalidSignature
    from cryptography.x509.oid import NameOID

    fleet, rogue = certs
    ca = x509.load_pem_x509_certificate((fleet / "ca.pem").read_bytes())
    other_ca = x509.load_pem_x509_certificate((rogue / "ca.pem").read_bytes())
    assert stat.S_IMODE((fleet / "ca.key").stat().st_mode) == 0o600
    for name in ("r1", "r2", "r3", "tracker", "supervisor", "operator", "router", "ros2", "ros_client"):
        d = fleet / name
        assert stat.S_IMODE(d.stat().st_mode) == 0o700
        assert stat.S_IMODE((d / "key.pem").stat().st_mode) == 0o600
        cert = x509.load_pem_x509_certificate((d / "cert.pem").read_bytes())
        assert cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == name
        cert.verify_directly_issued_by(ca)  # raises if not signed by the fleet CA
        assert (d / "ca.pem").read_bytes() == (fleet / "ca.pem").read_bytes()
    san = x509.load_pem_x509_certificate((fleet / "router/cert.pem").read_bytes()).extensions
    names = san.get_extension_for_class(x509.SubjectAlternativeName).value
    assert "localhost" in names.get_values_for_type(x509.DNSName)
    assert [str(a) for a in names.get_values_for_type(x509.IPAddress)] == ["127.0.0.1"]
    assert sorted(p.name for p in rogue.iterdir()) == ["ca.key", "ca.pem", "r1"]
    assert other_ca.subject == ca.subject and other_ca.public_key() != ca.public_key()
    with pytest.raises(InvalidSignature):  # same CN r1, but another CA's signature
        x509.load_pem_x509_certificate((rogue / "r1/cert.pem").read_bytes()).verify_directly_issued_by(ca)


def test_make_certs_reuses_the_ca_and_keeps_identities(certs: tuple[Path, Path]) -> None:
    fleet, _ = certs
    before = {p: p.read_bytes() for p in (fleet / "ca.pem", fleet / "r1/cert.pem")}
    res = subprocess.run(
        [sys.executable, str(DEPLOY / "make_certs.py"), str(fleet), "--robots", "r1"],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert res.returncode == 0 and "reusing the CA" in res.stderr and "kept" in res.stderr
    assert all(p.read_bytes() == b for p, b in before.items())
    res = subprocess.run(
        [sys.executable, str(DEPLOY / "make_certs.py"), str(fleet), "--robots", "bad/name"],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert res.returncode == 2 and "must match" in res.stderr


# ------------------------------------------------------------------ router
def _listening(pid: int) -> list[tuple[str, int]]:
    """(IPv4 address, port) of the listening TCP sockets of ``pid`` (IPv6 ones as ("v6", port))."""
    out = []
    for state, local, _, v6 in tcp_sockets(pid):
        if state == "0A":  # LISTEN
            addr, port = local.split(":")
            host = "v6" if v6 else ".".join(str(b) for b in reversed(bytes.fromhex(addr)))
            out.append((host, int(port, 16)))
    return out


def test_router_listens_only_on_its_tls_loopback_endpoint(router: tuple[str, Proc]) -> None:
    endpoint, proc = router
    port = int(endpoint.rsplit(":", 1)[1])
    assert _listening(proc.popen.pid) == [("127.0.0.1", port)]


# -------------------------------------------------------- authentication
def _intruder_config(kind: str, certs: tuple[Path, Path], endpoint: str) -> dict[str, Any]:
    """A client configuration that is r2's except for its credentials."""
    conf = client_json("agent", certs[0], endpoint, "r2")
    tls = conf["transport"]["link"]["tls"]
    if kind == "no certificate":  # a plain TLS client: verifies the router, presents nothing
        del tls["connect_certificate"], tls["connect_private_key"]
        tls["enable_mtls"] = False
    else:  # CN r1, signed by another CA; trusts the fleet CA, so it can verify the router
        rogue = Credentials.of(certs[1], "r1")
        tls["connect_certificate"], tls["connect_private_key"] = str(rogue.cert), str(rogue.key)
    return conf


@pytest.mark.parametrize("kind", ["no certificate", "another CA"])
def test_a_client_without_a_fleet_certificate_gets_no_data_either_way(
    kind: str, certs: tuple[Path, Path], router: tuple[str, Proc], tmp_path: Path
) -> None:
    """The intruder and a certified control differ only in credentials: the control's samples
    flow both ways through the router, the intruder's in neither direction.  (With zenoh 1.10
    the router refuses the TLS handshake, so the intruder's ``zenoh.open`` raises; should a
    later version connect it anyway, the access control must still cut it off.)"""
    endpoint, _ = router
    bad, good = tmp_path / "intruder.json5", tmp_path / "control.json5"
    bad.write_text(json.dumps(_intruder_config(kind, certs, endpoint)))
    good.write_text(json.dumps(client_json("agent", certs[0], endpoint, "r2")))
    everything = (f"{K.root}/**",)
    with probes() as start:
        observer = start("supervisor", *_member(certs[0], endpoint, "supervisor"), subs=everything)
        sender = start("r1", *_member(certs[0], endpoint, "agent", "r1"))
        intruder = start("intruder", "--config", str(bad), subs=everything)
        control = start("control", "--config", str(good), subs=everything)
        for p in (observer, sender, control):
            p.ready()
        outcome = intruder.started()
        if outcome["event"] == "ready":  # connected after all: then it must be cut off by the ACL
            intruder.send(put=K.plan("r2"), payload="intruder")
        # Positive control, same setup: r1 → control and observer; control (r2) → observer.
        marker = deliver(sender, K.plan("r1"), [observer, control])
        deliver(control, K.plan("r2"), [observer])
        barrier(sender, K.plan("r1"), [observer, control])
        assert not [e for e in observer.samples() if e["payload"] == "intruder"]
        if outcome["event"] == "open_failed":
            assert intruder.popen.wait(timeout=10) == 3
        else:  # the control got r1's marker; the intruder, a client of the same router, must not
            assert intruder.wait_for(_has(marker, K.plan("r1")), 1.0) is None
            assert [e["payload"] for e in intruder.samples()] == ["intruder"]  # only its own, locally


# ---------------------------------------------------------- access control
def test_a_robot_cannot_publish_for_another_robot(certs: tuple[Path, Path], router: tuple[str, Proc]) -> None:
    endpoint, _ = router
    with probes() as start:
        observer = start("supervisor", *_member(certs[0], endpoint, "supervisor"),
                         subs=(f"{K.root}/**",), lives=(K.alive(),))  # fmt: skip
        r1 = start("r1", *_member(certs[0], endpoint, "agent", "r1"))
        r2 = start("r2", *_member(certs[0], endpoint, "agent", "r2"))
        for p in (observer, r1, r2):
            p.ready()
        # Controls: each robot's own plan is delivered, r2's plan key included.
        deliver(r1, K.plan("r1"), [observer])
        deliver(r2, K.plan("r2"), [observer])
        forged = {K.plan("r2"), K.cmd("r2"), K.odom("r2"), K.wheels("r2"), K.goal("r2"), K.plan("r3")}
        for key in sorted(forged):
            r1.send(put=key, payload="forged")
        r1.send(token=K.alive("r2"))
        r1.send(token=K.alive("r1"))
        barrier(r1, K.plan("r1"), [observer])
        barrier(r1, K.cmd("r1"), [observer])  # its own command is delivered
        own = observer.wait_for(lambda e: e["event"] == "token" and e["key"] == K.alive("r1"), DELIVERY_S)
        assert own is not None and own["kind"] == "put"
        assert [e["key"] for e in observer.samples() if e["payload"] == "forged"] == []
        assert [e["key"] for e in observer.tokens()] == [K.alive("r1")]


def test_only_the_tracker_publishes_poses_truth_and_the_clock(
    certs: tuple[Path, Path], router: tuple[str, Proc]
) -> None:
    endpoint, _ = router
    with probes() as start:
        observer = start("r2", *_member(certs[0], endpoint, "agent", "r2"), subs=(f"{K.root}/**",))
        tracker = start("tracker", *_member(certs[0], endpoint, "tracker"))
        r1 = start("r1", *_member(certs[0], endpoint, "agent", "r1"))
        operator = start("operator", *_member(certs[0], endpoint, "operator"))
        for p in (observer, tracker, r1, operator):
            p.ready()
        for key in (K.pose("r1"), K.truth("r1"), K.clock):  # controls: the tracker's are delivered
            deliver(tracker, key, [observer])
        deliver(r1, K.plan("r1"), [observer])
        deliver(operator, K.goal("r1"), [observer])
        # The digest too: the lab router (a camera tracker) grants it to nobody, and a robot's
        # forged digest would speak for every robot at once.
        forged = (K.pose("r1"), K.pose("r2"), K.truth("r1"), K.clock, K.digest)
        for attacker, allowed in ((r1, K.plan("r1")), (operator, K.goal("r1"))):
            for key in forged:
                attacker.send(put=key, payload=f"forged by {attacker.name}")
            barrier(attacker, allowed, [observer])
        got = [(e["key"], e["payload"]) for e in observer.samples() if e["payload"].startswith("forged")]
        assert got == []


def _done(p: Proc, op: str, n: int, timeout: float = DELIVERY_S) -> int:
    """Wait until probe ``p`` has done its ``n``-th request ``op``; the index of that event."""

    def nth(_: Event) -> bool:
        return sum(e["event"] == "done" and e["op"] == op for e in p.events) >= n

    assert p.wait_for(nth, timeout) is not None, f"{p.name} did not do {op} #{n}: {p.tail()}"
    with p.cond:
        return [i for i, e in enumerate(p.events) if e["event"] == "done" and e["op"] == op][n - 1]


def _count(p: Proc, op: str) -> int:
    """How many requests ``op`` probe ``p`` has done so far."""
    with p.cond:
        return sum(e["event"] == "done" and e["op"] == op for e in p.events)


def _replies(p: Proc, key: str, payload: str, timeout: float = DELIVERY_S) -> list[Event]:
    """Have probe ``p`` query ``key`` with ``payload`` and wait for the query to end; its replies."""
    with p.cond:
        start, n = len(p.events), sum(e["event"] == "done" and e["op"] == "get" for e in p.events)
    p.send(get=key, payload=payload, timeout=str(timeout))
    end = _done(p, "get", n + 1, timeout + DELIVERY_S)
    with p.cond:
        return [e for e in p.events[start:end] if e["event"] == "reply"]


def _queries(p: Proc, payload: str) -> list[Event]:
    with p.cond:
        return [e for e in p.events if e["event"] == "query" and e["payload"] == payload]


def test_only_the_operator_asks_for_goals_and_only_the_robot_answers(
    certs: tuple[Path, Path], router: tuple[str, Proc]
) -> None:
    """Goals as queries (a script's ``Fleet.connect``): the operator's query on r1's goal key
    reaches r1's queryable and r1's reply comes back; r2 cannot answer for r1 (its queryable on
    r1's key is refused, r1's queries are not passed to it, nor would its reply on r1's key be),
    and a robot or the supervisor that asks is refused, its query ending at once without r1's
    reply and never reaching r1."""
    endpoint, _ = router
    with probes() as start:
        operator = start("operator", *_member(certs[0], endpoint, "operator"))
        r1 = start("r1", *_member(certs[0], endpoint, "agent", "r1"))
        r2 = start("r2", *_member(certs[0], endpoint, "agent", "r2"))
        supervisor = start("supervisor", *_member(certs[0], endpoint, "supervisor"))
        for p in (operator, r1, r2, supervisor):
            p.ready()
        r1.send(queryable=K.goal("r1"), reply="genuine r1")
        # r2's forged queryable first, then its own: both declarations travel in order on r2's link.
        r2.send(queryable=K.goal("r1"), reply="forged by r2")
        r2.send(queryable=K.goal("r2"), reply="genuine r2")
        _done(r1, "queryable", 1)
        _done(r2, "queryable", 2)
        # Controls, repeated until the routes exist: the operator's queries are answered by each robot.
        for rid in ("r2", "r1"):
            deadline = time.monotonic() + DELIVERY_S
            while not (got := _replies(operator, K.goal(rid), f"ask {rid}", 1.0)):
                assert time.monotonic() < deadline, f"no answer from {rid}: {operator.tail()}"
            assert [e["payload"] for e in got] == [f"genuine {rid}"], got
        assert r2.wait_for(lambda e: e["event"] == "query" and e["key"] == K.goal("r2"), DELIVERY_S)
        # Only r1 answers on r1's key: once r2's own queryable answers, its forged one would have too.
        got = _replies(operator, K.goal("r1"), "ask r1 again")
        assert [(e["key"], e["payload"]) for e in got] == [(K.goal("r1"), "genuine r1")], got
        assert [e for e in r2.events if e["event"] == "query" and e["key"] == K.goal("r1")] == []
        # Anyone else's query ends at once without r1's reply, and never reaches r1.  (r2's own
        # queryable on r1's key answers it, locally.)
        for asker, local in ((r2, ["forged by r2"]), (supervisor, [])):
            got = _replies(asker, K.goal("r1"), f"asked by {asker.name}")
            assert [e["payload"] for e in got] == local, got
        _replies(operator, K.goal("r1"), "barrier")  # behind theirs on the router's link to r1
        assert r1.wait_for(lambda e: e["event"] == "query" and e["payload"] == "barrier", DELIVERY_S)
        assert _queries(r1, "asked by r2") == [] and _queries(r1, "asked by supervisor") == []


def test_the_operator_declares_the_script_token_and_publishes_goals_only(
    certs: tuple[Path, Path], router: tuple[str, Proc]
) -> None:
    """What a script joining with the operator's certificate may not do: speak for a robot (a
    plan, a command, a robot's token) or hold and stop the fleet's clock (``F/script``, which
    only a script that launched its own fleet locally uses).  Its token ``F/alive/script`` and its
    goals go through."""
    endpoint, _ = router
    with probes() as start:
        observer = start("supervisor", *_member(certs[0], endpoint, "supervisor"),
                         subs=(f"{K.root}/**",), lives=(K.alive(),))  # fmt: skip
        operator = start("operator", *_member(certs[0], endpoint, "operator"))
        for p in (observer, operator):
            p.ready()
        deliver(operator, K.goal("r1"), [observer])
        for key in (K.plan("r1"), K.cmd("r1"), K.script, K.odom("r1"), K.applied("r1")):
            operator.send(put=key, payload="forged by operator")
        barrier(operator, K.goal("r1"), [observer])
        assert [e["key"] for e in observer.samples() if e["payload"] == "forged by operator"] == []
        operator.send(token=K.alive("r1"))
        operator.send(token=K.alive("supervisor"))
        operator.send(token=K.alive(SCRIPT))
        own = observer.wait_for(lambda e: e["event"] == "token" and e["key"] == K.alive(SCRIPT), DELIVERY_S)
        assert own is not None and own["kind"] == "put"
        assert [e["key"] for e in observer.tokens()] == [K.alive(SCRIPT)]


GRACE_S = 1.0
"""How long after a listed client got a sample an unlisted one must still have nothing [s]."""


def test_a_fleet_certificate_missing_from_the_acl_gets_nothing(
    certs: tuple[Path, Path], router: tuple[str, Proc]
) -> None:
    """r9 holds a valid fleet certificate but the router does not list it (a revoked robot):
    it connects, and the router drops its traffic both ways.  It may publish nothing, so no
    barrier exists: absence is judged GRACE_S after the same traffic reached a listed client."""
    endpoint, _ = router
    everything, alive = (f"{K.root}/**",), (K.alive(),)
    with probes() as start:
        observer = start(
            "supervisor", *_member(certs[0], endpoint, "supervisor"), subs=everything, lives=alive
        )
        r1 = start("r1", *_member(certs[0], endpoint, "agent", "r1"))
        r9 = start("r9", *_member(certs[0], endpoint, "agent", "r9"), subs=everything, lives=alive)
        for p in (observer, r1, r9):
            p.ready()
        r9.send(put=K.plan("r9"), payload="stranger")
        r9.send(token=K.alive("r9"))
        assert r9.wait_for(lambda e: e["event"] == "done" and e["op"] == "token", DELIVERY_S)
        marker = deliver(r1, K.plan("r1"), [observer])
        r1.send(token=K.alive("r1"))
        assert observer.wait_for(lambda e: e["event"] == "token" and e["key"] == K.alive("r1"), DELIVERY_S)
        late = r9.wait_for(lambda e: e.get("payload") == marker or e.get("key") == K.alive("r1"), GRACE_S)
        assert late is None, late
        assert [e["payload"] for e in r9.samples()] == ["stranger"]  # its own, delivered locally
        assert [e["key"] for e in r9.tokens()] == [K.alive("r9")]
        assert [e["payload"] for e in observer.samples() if e["payload"] == "stranger"] == []
        assert [e["key"] for e in observer.tokens()] == [K.alive("r1")]


# ------------------------------------------------------------------ ROS 2
ROS_POSE, ROS_GOAL = "0/r1/pose/T/H", "0/r1/goal_pose/T/H"
"""Keys of /r1/pose and /r1/goal_pose on ROS domain 0 (T and H stand for the DDS type name and
the type hash, which the access control does not look at)."""
FACE_TOKEN, CLIENT_TOKEN = "@ros2_lv/0/aa/0/0/NN/%/%/fleet_lab", "@ros2_lv/0/bb/0/0/NN/%/%/rviz"


def _token(key: str, e: Event) -> bool:
    return bool(e["event"] == "token" and e["key"] == key)


def _forged_for(receiver: str, e: Event) -> bool:
    """``e`` is a forged sample that ``receiver`` did not send itself."""
    return (
        e["event"] == "sample"
        and e["payload"].startswith("forged")
        and e["payload"] != f"forged by {receiver}"
    )


@pytest.fixture(scope="module")
def ros_router(certs: tuple[Path, Path]) -> Iterator[tuple[str, Proc]]:
    """(endpoint, process) of a router for r1 r2 r3 with the ROS rights of domain 0, from the
    command line (``router ... --ros-domain 0``)."""
    endpoint = f"tls/127.0.0.1:{free_port()}"
    args = ["--certs", str(certs[0]), "--listen", endpoint, "--robots", "r1", "r2", "r3", "--ros-domain", "0"]
    proc = _local("router-ros", ["-m", "secure_router", "router", *args], ends_on_eof=False)
    try:
        assert proc.ready()["listen"] == [endpoint]
        yield endpoint, proc
    finally:
        code = proc.stop()
    assert code == 0, f"the router did not stop cleanly on SIGTERM: {proc.tail()}"


def test_only_the_ros_face_publishes_ros_topics_and_only_the_operator_gives_goals(
    certs: tuple[Path, Path], ros_router: tuple[str, Proc]
) -> None:
    """A ROS client reads the face's topics and tokens and declares its own token, but reads
    nothing of the fleet and writes nothing: its pose and goal_pose are dropped, as is anyone's
    but the face's pose and anyone's but the operator's goal_pose.  The face reads the fleet's
    poses and the operator's goal_pose, and cannot publish for the tracker.  None of the
    dropped senders has an allowed put the same receiver gets, so absence is judged GRACE_S
    after an allowed sample sent behind them reached that receiver."""
    endpoint, _ = ros_router
    c = certs[0]
    with probes() as start:
        reader = start("reader", *_member(c, endpoint, "ros_client"), subs=("0/r1/pose/**", f"{K.root}/**"),
                       lives=("@ros2_lv/0/**",))  # fmt: skip
        face = start("face", *_member(c, endpoint, "ros2"), subs=("0/r1/goal_pose/**", K.pose()))
        observer = start("observer", *_member(c, endpoint, "supervisor"), subs=(f"{K.root}/**",))
        writer = start("writer", *_member(c, endpoint, "ros_client"))
        operator = start("operator", *_member(c, endpoint, "operator"))
        tracker = start("tracker", *_member(c, endpoint, "tracker"))
        r1 = start("r1", *_member(c, endpoint, "agent", "r1"))
        for p in (reader, face, observer, writer, operator, tracker, r1):
            p.ready()
        face.send(token=FACE_TOKEN)
        writer.send(token=CLIENT_TOKEN)
        for token in (FACE_TOKEN, CLIENT_TOKEN):
            assert reader.wait_for(partial(_token, token), DELIVERY_S), token
        # Controls: the face's pose reaches the client, the operator's goal and the tracker's pose the face.
        deliver(face, ROS_POSE, [reader])
        deliver(operator, ROS_GOAL, [face])
        fleet_pose = deliver(tracker, K.pose("r1"), [face, observer])
        # Forged: a pose on ROS by anyone but the face, a goal_pose by anyone but the operator,
        # a fleet pose by the face.
        sent = {p.name: _count(p, "put") for p in (writer, operator, tracker, r1, face)}
        for p in (writer, operator, tracker, r1):
            p.send(put=ROS_POSE, payload=f"forged by {p.name}")
        for p in (writer, tracker, r1, face):
            p.send(put=ROS_GOAL, payload=f"forged by {p.name}")
        face.send(put=K.pose("r2"), payload="forged by face")
        for p, n in ((writer, 2), (operator, 1), (tracker, 2), (r1, 2), (face, 2)):
            _done(p, "put", sent[p.name] + n)
        deliver(face, ROS_POSE, [reader])
        deliver(operator, ROS_GOAL, [face])
        deliver(tracker, K.pose("r1"), [observer])
        for p in (reader, face, observer):  # (the face's own goal_pose is delivered to it locally)
            late = p.wait_for(partial(_forged_for, p.name), GRACE_S)
            assert late is None, p.samples()
        # The client got nothing of the fleet itself.
        assert [e for e in reader.samples() if e["key"].startswith(f"{K.root}/")] == [], fleet_pose


# ----------------------------------------------------- configuration code
def _same(a: Any, b: Any, keys: list[str]) -> None:
    for k in keys:
        assert json.loads(a.get_json(k)) == json.loads(b.get_json(k)), k


COMMON = ["mode", "connect/endpoints", "listen/endpoints", "scouting/multicast/enabled", "transport/link/tls"]


@pytest.mark.parametrize("role", ["agent", "tracker", "supervisor", "operator", "ros2", "ros_client"])
def test_client_templates_equal_the_builder(role: str, certs: tuple[Path, Path]) -> None:
    endpoint = "tls/127.0.0.1:7447"
    robot = "r1" if role == "agent" else None
    values = {"CERTS": str(certs[0]), "ROUTER": endpoint} | ({"ROBOT": "r1"} if robot else {})
    import zenoh

    shipped = zenoh.Config.from_json5(render((DEPLOY / f"{role}.json5").read_text(), values))
    built = to_zenoh(client_json(role, certs[0], endpoint, robot))
    _same(shipped, built, [*COMMON, "connect/timeout_ms"])
    tls = json.loads(built.get_json("transport/link/tls"))
    assert tls["connect_certificate"] == str(certs[0] / identity(role, robot) / "cert.pem")
    assert tls["enable_mtls"] is True and tls["verify_name_on_connect"] is True


def test_router_template_equals_the_builder(certs: tuple[Path, Path]) -> None:
    import zenoh

    endpoint = "tls/127.0.0.1:7447"
    text = (DEPLOY / "router.json5").read_text()
    shipped = zenoh.Config.from_json5(render(text, {"CERTS": str(certs[0]), "LISTEN": endpoint}))
    built = to_zenoh(router_json(endpoint, certs[0], ["r1", "r2", "r3"]))
    _same(shipped, built, [*COMMON, "access_control"])
    assert check_router(shipped) == [endpoint]


def test_acl_grants_exactly_the_documented_rights() -> None:
    acl = acl_json(["r1", "r2"], fleet="lab")
    rules = {r["id"]: r for r in acl["rules"]}
    assert acl["default_permission"] == "deny"
    own = [K.plan("r1"), K.near("r1"), K.cmd("r1"), K.odom("r1"), K.wheels("r1"), K.emu("r1")]
    assert rules["publish-r1"]["key_exprs"] == [*own, K.applied("r1"), K.link("r1")]
    assert K.near("r1") == "fleet/lab/near/*/r1" and K.at("r1") == "fleet/lab/at/r1/**"
    assert rules["token-r1"] == {"id": "token-r1", "messages": ["liveliness_token"], "flows": ["ingress"],
                                 "permission": "allow", "key_exprs": [K.alive("r1"), K.at("r1")]}  # fmt: skip
    assert rules["publish-tracker"]["key_exprs"] == [K.pose(), K.truth(), K.clock, K.outcome]
    sim = {r["id"]: r for r in acl_json(["r1"], sim_tracker=True)["rules"]}
    sim_puts = [K.pose(), K.truth(), K.clock, K.outcome, K.odom(), K.digest]
    assert sim["publish-tracker"]["key_exprs"] == sim_puts
    ingress_puts = [r for r in acl["rules"] if "put" in r["messages"] and "ingress" in r["flows"]]
    assert sorted(r["id"] for r in ingress_puts) == ["publish-operator", "publish-r1", "publish-r2",
                                                     "publish-tracker"]  # fmt: skip
    assert all(r["permission"] == "allow" for r in acl["rules"])
    # Beyond reading (every member: the subscribe and deliver rules), each identity's grants as
    # (flow, message, key): the operator's are exactly what fleet goal and Fleet.connect need.
    members = {p["id"]: p for p in acl["policies"]}["members"]
    assert members["subjects"] == ["members"] and members["rules"] == ["subscribe", "deliver"]
    assert {r["id"]: r for r in acl["rules"]}["deliver"]["flows"] == ["egress"]
    reading = {"declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"}
    assert set(rules["subscribe"]["messages"]) == reading
    names = {s["id"]: s["cert_common_names"] for s in acl["subjects"]}
    grants: dict[str, set[tuple[str, str, str]]] = {}
    for pol in acl["policies"]:
        if pol["id"] == "members":
            continue
        for subject in pol["subjects"]:
            (cn,) = names[subject]
            grants.setdefault(cn, set()).update(
                (flow, m, key) for r in pol["rules"] for flow in rules[r]["flows"]
                for m in rules[r]["messages"] for key in rules[r]["key_exprs"]
            )  # fmt: skip
    robot = {
        *{("ingress", "put", key) for key in rules["publish-r1"]["key_exprs"]},
        ("ingress", "liveliness_token", K.alive("r1")),
        ("ingress", "liveliness_token", K.at("r1")),  # its place tokens (plans by place)
        ("ingress", "declare_queryable", K.goal("r1")),  # the agent's goal queryable
        ("ingress", "reply", K.goal("r1")),  # its answers
        ("egress", "query", K.goal("r1")),  # the queries for it, and no other robot's
    }
    assert grants == {
        "r1": robot,
        "r2": {(f, m, key.replace("r1", "r2")) for f, m, key in robot},
        "tracker": {("ingress", "put", key) for key in (K.pose(), K.truth(), K.clock, K.outcome)},
        "supervisor": {("ingress", "liveliness_token", K.alive("supervisor"))},
        "operator": {
            ("ingress", "put", K.goal()),  # fleet goal
            ("ingress", "query", K.goal()),  # a script's goals, answered by the agents
            ("egress", "reply", K.goal()),
            ("ingress", "liveliness_token", K.alive(SCRIPT)),  # a script's token
        },
    }
    assert not any(K.script in r["key_exprs"] for r in acl["rules"])  # nobody permits or stops steps


def _grants(acl: dict[str, Any]) -> dict[str, set[tuple[str, str, str]]]:
    """Each certificate common name's (flow, message, key) grants, by every policy."""
    rules = {r["id"]: r for r in acl["rules"]}
    names = {s["id"]: s["cert_common_names"] for s in acl["subjects"]}
    grants: dict[str, set[tuple[str, str, str]]] = {}
    for pol in acl["policies"]:
        for subject in pol["subjects"]:
            for cn in names[subject]:
                grants.setdefault(cn, set()).update(
                    (flow, m, key) for r in pol["rules"] for flow in rules[r]["flows"]
                    for m in rules[r]["messages"] for key in rules[r]["key_exprs"]
                )  # fmt: skip
    return grants


def test_acl_grants_the_ros_rights_of_its_domain_only() -> None:
    """With a ROS domain, the ROS face (ros2) and ROS clients (ros_client) get exactly their ROS
    rights, and the operator those of a ROS client plus RViz's goals; the fleet's own grants are
    unchanged, and without a domain nothing is granted on any ROS key."""
    plain, acl = acl_json(["r1", "r2"]), acl_json(["r1", "r2"], ros_domain=7)
    grants, before = _grants(acl), _grants(plain)
    assert not ({"ros2", "ros_client"} & set(before))
    assert all(k.startswith(f"{K.root}/") for g in before.values() for _, _, k in g)
    data = [f"7/{r}/{t}/**" for r in ("r1", "r2") for t in ("pose", "plan", "reference")]
    data.append("7/fleet/footprints/**")
    goals, graph = ["7/r1/goal_pose/**", "7/r2/goal_pose/**"], ["@ros2_lv/7/**"]
    assert ros_keys(["r1", "r2"], 7) == (data, goals, graph)
    reading = {"declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"}
    delivered = {"put", "liveliness_token", "declare_liveliness_subscriber", "liveliness_query"}
    client = {
        *{("ingress", m, k) for m in reading for k in data + graph},  # ros2 topic echo, RViz, discovery
        *{("egress", m, k) for m in delivered for k in data + graph},
        *{("ingress", "liveliness_token", k) for k in graph},  # its own node and endpoints
        *{("egress", "declare_subscriber", k) for k in goals},  # the face's goal_pose subscriptions
    }
    fleet_reads = [K.pose(), K.plan(), K.clock]
    face = {
        *{("ingress", "put", k) for k in data},
        *{("egress", "declare_subscriber", k) for k in data},  # its publishers see the clients
        *{("ingress", "liveliness_token", k) for k in graph},
        *{
            (flow, m, k)
            for flow, m in (("ingress", "declare_subscriber"), ("egress", "put"))
            for k in fleet_reads + goals
        },
        ("ingress", "query", K.goal()),  # goal_pose given to the agent as a goal query
        ("egress", "reply", K.goal()),
    }
    assert grants.pop("ros_client") == client
    assert grants.pop("ros2") == face
    assert grants.pop("operator") == before.pop("operator") | client | {("ingress", "put", k) for k in goals}
    assert grants == before  # nothing else changed
    members = next(s for s in acl["subjects"] if s["id"] == "members")["cert_common_names"]
    assert not set(ROS) & set(members)  # the ROS identities read nothing else of the fleet
    # Only the face puts on the ROS data keys; only the operator on goal_pose.
    puts = {cn for cn, g in _grants(acl).items() for f, m, k in g if (f, m) == ("ingress", "put")
            and not k.startswith(f"{K.root}/")}  # fmt: skip
    assert puts == {"ros2", "operator"}
    for bad in (-1, 233, True, "0", 1.0):
        with pytest.raises(SecureConfigError, match="ros_domain"):
            acl_json(["r1"], ros_domain=bad)  # type: ignore[arg-type]


def test_the_command_line_grants_the_ros_rights(
    certs: tuple[Path, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    args = ["config", "router", "--certs", str(certs[0]), "--listen", "tls/127.0.0.1:7447", "--robots", "r1"]
    assert main(args) == 0
    assert "ros2" not in capsys.readouterr().out
    assert main([*args, "--ros-domain", "3"]) == 0
    assert json.loads(capsys.readouterr().out)["access_control"] == acl_json(["r1"], ros_domain=3)
    assert main([*args, "--ros-domain", "300"]) == 2
    assert "ros_domain" in capsys.readouterr().err
    for role in ROS:
        assert main(["config", role, "--certs", str(certs[0]), "--router", "tls/127.0.0.1:7447"]) == 0
        tls = json.loads(capsys.readouterr().out)["transport"]["link"]["tls"]
        assert tls["connect_certificate"] == str(certs[0] / role / "cert.pem")


def test_bad_configurations_are_refused_naming_the_field(certs: tuple[Path, Path], tmp_path: Path) -> None:
    cases: list[tuple[Callable[[], object], str]] = [
        (lambda: identity("agent"), "robot"),
        (lambda: identity("agent", "tracker"), "robot"),
        (lambda: identity("tracker", "r1"), "robot"),
        (lambda: identity("camera"), "role"),
        (lambda: check_endpoint("tcp/127.0.0.1:7447"), "only TLS"),
        (lambda: check_endpoint("tls/127.0.0.1:0"), "port"),
        (lambda: check_endpoint("tls/0.0.0.0:7447", listen=True), "every interface"),
        (lambda: client_json("agent", tmp_path, "tls/127.0.0.1:7447", "r1"), "r1/ca.pem is missing"),
        (lambda: acl_json(["r1", "r1"]), "distinct"),
        (lambda: render("${CERTS}/x", {}), "${CERTS}"),
    ]
    for fn, words in cases:
        with pytest.raises(SecureConfigError) as e:
            fn()
        assert words in str(e.value), (words, str(e.value))
    good = router_json("tls/127.0.0.1:7447", certs[0], ["r1"])
    for path, value, words in [
        (("listen", "endpoints"), ["tcp/127.0.0.1:7447"], "only TLS"),
        (("transport", "link", "tls", "enable_mtls"), False, "enable_mtls"),
        (("access_control", "enabled"), False, "access_control/enabled"),
        (("access_control", "default_permission"), "allow", "default_permission"),
    ]:
        bad = json.loads(json.dumps(good))
        node = bad
        for p in path[:-1]:
            node = node[p]
        node[path[-1]] = value
        with pytest.raises(SecureConfigError) as e:
            check_router(to_zenoh(bad))
        assert words in str(e.value)
    assert check_endpoint("tls/[::1]:7447", listen=True) == "tls/[::1]:7447"
