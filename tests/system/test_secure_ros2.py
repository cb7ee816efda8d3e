"""The fleet's ROS 2 face behind the secure router: ROS clients read, only the operator gives goals.

A two-robot realtime fleet (``paper_two_robots``) runs behind the mutual-TLS router of
``deploy/`` (``python -m secure_router router``, certificates of ``deploy/make_certs.py`` in
tmp_path, listening on ``tls/127.0.0.1:<free port>`` only, multicast scouting off everywhere),
whose access control has the ROS rights of ROS domain 0 (``router_json(..., ros_domain=0)``).
Every process is a client of the router with the configuration :func:`secure_router.access.client_json`
builds for its identity: the tracker, the supervisor, the agents, and the ROS face ``python -m
ros2_link --ros-domain 0`` with the ``ros2`` certificate.

This test's own process plays a ROS 2 client with the ``ros_client`` certificate (raw Zenoh,
rmw_zenoh's keys): it receives ``/r1/pose`` samples (PoseStamped in frame ``world``, with the
33-byte attachment of rmw_zenoh) and finds the ROS face's node and endpoints by a liveliness
query on ``@ros2_lv/0/**``.  It then writes a goal on ``/r1/goal_pose`` (once its publisher
matches the ROS face's subscription, so the sample does leave for the router), and the operator
writes another one on the same key with the operator's certificate.  The ROS face logs every
goal it receives (``goal_pose (x, y) for r1 accepted by its agent`` or ``refused: <reason>``):
the operator's goal is logged and taken by r1's agent, the client's never is.  The client's goal
was sent first, from a session connected long before the operator's was opened, and the ROS face
handles goals in the order they come: had the router let it through, it would have been logged
before the operator's.  The fleet then runs to its end and every process exits 0.
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import pytest
from netns_util import LOCAL, ROOT, HostProc

from ros2_link import graph, types
from secure_router.access import client_json, router_json
from transport.net import free_port, load_config

SCENARIO = ROOT / "scenarios" / "paper_two_robots.toml"
ROBOTS = ("r1", "r2")
FLEET = "lab"
DOMAIN = 0
STEPS = 250
"""The run: this many steps of the realtime clock (25 s on the wall clock) [steps]."""
READY_S = 60.0
"""Limit for a process to print its readiness line [s] (tube synthesis on two shared cores)."""
DELIVERY_S = 10.0
"""Limit for an allowed message, token or log line to arrive [s]."""
GOAL_S = 20.0
"""Limit for the operator's goal to be logged by the ROS face [s] (the agent answers within 10 s)."""
RUN_S = 120.0
"""Limit for the run, from the tracker's readiness to its exit [s]."""
EXIT_S = 30.0
"""Limit for the other processes to exit after the tracker [s]."""
FORGED = (0.111, -0.222)
"""The ROS client's goal for r1 [m]: a free point, which the agent would accept."""
GOAL = (0.3, 0.5)
"""The operator's goal for r1 [m], clear of r2's goal and of the walls."""
POSE_KEY = graph.topic_key(DOMAIN, "/r1/pose", types.POSE_STAMPED, types.type_hash(types.POSE_STAMPED))
GOAL_KEY = graph.topic_key(DOMAIN, "/r1/goal_pose", types.POSE_STAMPED, types.type_hash(types.POSE_STAMPED))


@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("pki")
    res = subprocess.run(
        [sys.executable, str(ROOT / "deploy" / "make_certs.py"), str(d), "--scenario", str(SCENARIO)],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert (d / "ros2" / "cert.pem").is_file() and (d / "ros_client" / "cert.pem").is_file()
    return d


class Net:
    """The router and the processes of the test, each ended by its pid on exit (SIGTERM for the
    router; the fleet's processes should have exited by themselves) with its exit code kept."""

    def __init__(self, stack: ExitStack, certs: Path, tmp: Path):
        self.certs, self.tmp = certs, tmp
        self.logs = tmp / "logs"
        self.logs.mkdir()
        self.procs: dict[str, HostProc] = {}
        self.codes: dict[str, int] = {}
        self.endpoint = ""
        stack.callback(self.stop_all)

    def stop_all(self) -> None:
        for name, p in reversed(self.procs.items()):
            self.codes[name] = p.stop()

    def start(self, name: str, args: list[str]) -> HostProc:
        p = HostProc(name, LOCAL, "local", args, self.logs)
        self.procs[name] = p
        return p

    def router(self) -> None:
        """A router on tls/127.0.0.1:<free port> with the ROS rights of domain DOMAIN; a port
        taken meanwhile is tried again."""
        for attempt in range(3):
            self.endpoint = f"tls/127.0.0.1:{free_port()}"
            conf = router_json(
                self.endpoint, self.certs, list(ROBOTS), FLEET, sim_tracker=True, ros_domain=DOMAIN
            )
            path = self.tmp / f"router-{attempt}.json5"
            path.write_text(json.dumps(conf, indent=2))
            p = self.start(f"router-{attempt}", ["-m", "secure_router", "router", "--config", str(path)])
            ev = p.wait_for(lambda e: e["event"] in ("ready", "eof"), READY_S)
            if ev is not None and ev["event"] == "ready":
                assert ev["listen"] == [self.endpoint]
                return
            code = p.stop()
            del self.procs[p.name]
            if code != 1 or "cannot start" not in p.tail():
                break
        raise AssertionError(f"the router did not start: {p.tail()}")

    def config(self, role: str, robot: str | None = None) -> str:
        path = self.tmp / f"{role}{'-' + robot if robot else ''}.json5"
        if not path.exists():
            path.write_text(json.dumps(client_json(role, self.certs, self.endpoint, robot), indent=2))
        return str(path)


@pytest.fixture
def net(certs: Path, tmp_path: Path) -> Iterator[Net]:
    with ExitStack() as stack:
        yield Net(stack, certs, tmp_path)


class Received:
    """Samples a subscriber of this process got: (key, payload, attachment), with a condition."""

    def __init__(self) -> None:
        self.cond = threading.Condition()
        self.samples: list[tuple[str, bytes, bytes | None]] = []

    def __call__(self, s: Any) -> None:
        att = None if s.attachment is None else s.attachment.to_bytes()
        with self.cond:
            self.samples.append((str(s.key_expr), s.payload.to_bytes(), att))
            self.cond.notify_all()

    def first(self, timeout: float) -> tuple[str, bytes, bytes | None] | None:
        with self.cond:
            self.cond.wait_for(lambda: bool(self.samples), timeout)
            return self.samples[0] if self.samples else None


def _matched(pub: Any, timeout: float) -> bool:
    """Wait (bounded) until ``pub`` has a matching subscriber (its session learnt the route)."""
    cond, got = threading.Condition(), {"m": bool(pub.matching_status.matching)}

    def on_status(status: Any) -> None:
        with cond:
            got["m"] = got["m"] or bool(status.matching)
            cond.notify_all()

    listener = pub.declare_matching_listener(on_status)
    try:
        with cond:
            got["m"] = got["m"] or bool(pub.matching_status.matching)
            return cond.wait_for(lambda: got["m"], timeout)
    finally:
        listener.undeclare()


def _goal(session: Any, x: float, y: float, gid: bytes) -> None:
    """A PoseStamped goal for r1 on /r1/goal_pose, as RViz writes it, once the ROS face's
    subscription is known to ``session``."""
    import zenoh

    pub = session.declare_publisher(GOAL_KEY, congestion_control=zenoh.CongestionControl.BLOCK, express=True)
    assert _matched(pub, DELIVERY_S), f"no subscriber of {GOAL_KEY} reached this session"
    pub.put(types.pose_stamped(0.0, x, y, 0.0), attachment=graph.attachment(1, time.time_ns(), gid))


def _goal_lines(ros2: HostProc) -> list[str]:
    return [ln for ln in ros2.lines() if "goal_pose (" in ln]


@pytest.mark.realtime
def test_ros_clients_read_the_fleet_and_only_the_operator_gives_it_goals(net: Net) -> None:
    import zenoh

    t0 = time.monotonic()
    net.router()
    common = ["--scenario", str(SCENARIO), "--clock", "realtime"]
    ros2 = net.start("ros2", ["-m", "ros2_link", "--scenario", str(SCENARIO), "--ros-domain", str(DOMAIN),
                              "--zenoh-config", net.config("ros2")])  # fmt: skip
    face = ros2.ready(READY_S)
    tracker = net.start("tracker", ["-m", "tracker", *common, "--source", "sim", "--steps", str(STEPS),
                                    "--zenoh-config", net.config("tracker")])  # fmt: skip
    net.start("supervisor", ["-m", "supervisor", *common, "--out", str(net.tmp / "out"),
                             "--zenoh-config", net.config("supervisor")])  # fmt: skip
    for rid in ROBOTS:
        net.start(f"agent {rid}", ["-m", "agent", *common, "--robot", rid,
                                   "--zenoh-config", net.config("agent", rid)])  # fmt: skip
    fleet = [n for n in net.procs if n in ("tracker", "supervisor") or n.startswith("agent ")]
    for name in fleet:
        net.procs[name].ready(READY_S)

    client = zenoh.open(load_config(net.config("ros_client")))
    try:
        # A ROS client reads /r1/pose, as rmw_zenoh writes it.
        poses = Received()
        sub = client.declare_subscriber(f"{DOMAIN}/r1/pose/**", poses)
        got = poses.first(DELIVERY_S)
        assert got is not None, f"no /r1/pose sample reached the ROS client: {ros2.tail()}"
        key, payload, att = got
        assert key == POSE_KEY
        assert att is not None and len(att) == graph.ATTACHMENT_SIZE == 33, att
        seq, stamp, gid = graph.read_attachment(att)
        assert seq >= 1 and abs(stamp - time.time_ns()) < 60e9 and len(gid) == graph.GID_SIZE
        pose = types.read_goal_pose(payload)  # a PoseStamped
        assert pose.frame == types.FRAME and -1.0 < pose.x < 1.0 and -1.0 < pose.y < 1.0, pose

        # It finds the ROS face's node and endpoints in the graph.
        node = graph.Node(domain=DOMAIN, session_id=face["session"], node_id=0, name=face["node"])
        replies = client.liveliness().get(f"{graph.ADMIN_SPACE}/{DOMAIN}/**", timeout=DELIVERY_S)
        tokens = {str(r.ok.key_expr) for r in replies if r.ok is not None}
        assert node.token() in tokens, sorted(tokens)
        mine = [t for t in tokens if t.startswith(f"@ros2_lv/{DOMAIN}/{face['session']}/")]
        assert any("/MP/" in t and "%r1%pose/" in t for t in mine), mine
        assert any("/MS/" in t and "%r1%goal_pose/" in t for t in mine), mine

        # Its goal is dropped at the router; the operator's, sent after it, is taken.
        forged_at = time.monotonic()
        _goal(client, *FORGED, graph.gid(str(client.info.zid()), 1))
        operator = zenoh.open(load_config(net.config("operator")))
        try:
            _goal(operator, *GOAL, graph.gid(str(operator.info.zid()), 1))
            shown = f"goal_pose ({GOAL[0]:.3f}, {GOAL[1]:.3f}) for r1 "
            logged = ros2.wait_stderr(lambda ln: shown in ln, GOAL_S, after=forged_at)
            assert logged is not None, f"the operator's goal was not logged: {ros2.tail()}"
        finally:
            operator.close()
        sub.undeclare()
    finally:
        client.close()
    lines = _goal_lines(ros2)
    assert [ln for ln in lines if f"({FORGED[0]:.3f}, {FORGED[1]:.3f})" in ln] == [], lines
    assert lines == [f"[ros2] {shown}accepted by its agent"], lines

    assert tracker.wait(RUN_S) is not None, f"the run did not end within {RUN_S} s: {tracker.tail()}"
    for name in [*fleet, "ros2"]:
        assert net.procs[name].wait(EXIT_S) is not None, f"{name} still running {EXIT_S} s after the tracker"
    net.stop_all()
    print("secure ROS face:", json.dumps({"goal_lines": _goal_lines(ros2), "codes": net.codes,
                                          "wall_s": round(time.monotonic() - t0, 1)}))  # fmt: skip
    bad = {n: c for n, c in net.codes.items() if c != 0}
    assert not bad, "exit codes " + "; ".join(f"{n}: {c}: {net.procs[n].tail(8)}" for n, c in bad.items())
    assert _goal_lines(ros2) == lines  # nothing came later either
    assert [ln for ln in ros2.lines() if "rejected payloads" in ln or "rejected payload from" in ln] == []
    took = [ln for ln in net.procs["agent r1"].lines() if f"new goal {list(GOAL)} at step" in ln]
    assert len(took) == 1, net.procs["agent r1"].tail()
