"""The ROS 2 face of a running fleet: ``python -m ros2_link --scenario S [--ros-domain N] …``.

It joins the fleet's Zenoh network as one more participant and declares, in rmw_zenoh's
conventions (:mod:`ros2_link.graph`), a ROS 2 node ``fleet_<fleet>`` with, for every robot
``<id>``, the publishers ``/<id>/pose``, ``/<id>/plan`` and ``/<id>/reference``, the subscription
``/<id>/goal_pose``, and the publisher ``/fleet/footprints`` (:mod:`ros2_link.types`).  It
republishes each measured pose, each plan and, once per tick, the footprints.  A ``goal_pose``
(RViz's "2D Goal Pose") is checked by the one goal rule (:func:`ground.scenario.goal_problem`)
here, with the footprint, place and neighbours' goals its plans have told, then by the robot's
agent, to which it goes as a goal query; a refused goal is logged with its reason and changes
nothing.  It ends with the run (the tracker's stop tick), or on SIGTERM or SIGINT.

It observes only: it takes no part in any step, and no agent waits for it.
"""

from __future__ import annotations

import argparse
import re
import signal
import sys
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from ground.scenario import ROS_DOMAIN_MAX, ConfigError, Scenario, goal_problem, load_scenario, ros2_problem
from ground.wire import MAX_PAYLOAD, Goal, Keys, Plan, Pose, Tick, WireError
from ros2_link import graph
from transport.bus import Inbox, ask_goal, open_session
from transport.process import add_common_args, announce, domain_arg, log

ROLE = "ros2"
MAX_PENDING_GOALS = 16
"""Goals received and not yet handled; more are dropped (and counted) until these are done."""


def node_name(fleet: str) -> str:
    """The ROS node's name for fleet ``fleet``: ``fleet_<fleet>``, other characters as ``_``."""
    return "fleet_" + re.sub(r"[^A-Za-z0-9]", "_", fleet).strip("_")


@dataclass
class _Topic:
    """A publisher in rmw_zenoh's form: its Zenoh publisher, GID and sequence number."""

    pub: Any
    gid: bytes
    seq: int = 0

    def put(self, payload: bytes) -> None:
        self.seq += 1
        stamp = time.time_ns()
        self.pub.put(payload, attachment=graph.attachment(self.seq, stamp, self.gid))


class RosFace:
    """Everything ROS 2 sees of one fleet, on one Zenoh session."""

    def __init__(self, scn: Scenario, session: Any, keys: Keys, inbox: Inbox, domain: int, fleet: str):
        from ros2_link import types

        self.types, self.scn, self.session, self.keys, self.inbox = types, scn, session, keys, inbox
        self.ids = [r.id for r in scn.robots]
        zid = str(session.info.zid())
        self.node = graph.Node(domain=domain, session_id=zid, node_id=0, name=node_name(fleet))
        self.tokens = [session.liveliness().declare_token(self.node.token())]
        self.subs: list[Any] = []
        self.entities = 0
        self.pose: dict[str, _Topic] = {}
        self.plan: dict[str, _Topic] = {}
        self.reference: dict[str, _Topic] = {}
        for rid in self.ids:
            self.pose[rid] = self._publisher(graph.robot_topic(rid, graph.POSE), types.POSE_STAMPED)
            self.plan[rid] = self._publisher(graph.robot_topic(rid, graph.PLAN), types.PATH)
            self.reference[rid] = self._publisher(graph.robot_topic(rid, graph.REFERENCE), types.PATH)
            self._subscription(graph.robot_topic(rid, graph.GOAL_POSE), types.POSE_STAMPED, rid)
        self.footprints = self._publisher(graph.FOOTPRINTS, types.MARKER_ARRAY)
        self.goals: deque[tuple[str, bytes]] = deque()
        self.dropped_goals = 0
        self.sent_pose: dict[str, int] = {}
        self.sent_plan: dict[str, int] = {}
        self.sent_tick = -1

    def _endpoint(self, kind: str, topic: str, ros_type: str) -> tuple[int, str]:
        self.entities += 1
        h = self.types.type_hash(ros_type)
        token = self.node.endpoint_token(self.entities, kind, topic, ros_type, h, graph.Qos())
        self.tokens.append(self.session.liveliness().declare_token(token))
        return self.entities, graph.topic_key(self.node.domain, topic, ros_type, h)

    def _publisher(self, topic: str, ros_type: str) -> _Topic:
        eid, key = self._endpoint(graph.PUBLISHER, topic, ros_type)
        # Congestion control "drop" (Zenoh's default): a slow ROS client never holds up this
        # process, let alone the fleet.
        return _Topic(self.session.declare_publisher(key), graph.gid(self.node.session_id, eid))

    def _subscription(self, topic: str, ros_type: str, robot: str) -> None:
        _, key = self._endpoint(graph.SUBSCRIPTION, topic, ros_type)

        def on_sample(sample: Any) -> None:
            payload = sample.payload.to_bytes()
            with self.inbox.cond:
                if len(self.goals) >= MAX_PENDING_GOALS:
                    self.dropped_goals += 1
                else:
                    self.goals.append((robot, payload))
                self.inbox.cond.notify_all()

        self.subs.append(self.session.declare_subscriber(key, on_sample))

    # ------------------------------------------------------------------ the loop's work

    def news(self) -> bool:
        """Something to publish or a goal to handle (inbox.cond held)."""
        inbox = self.inbox
        if self.goals:
            return True
        tick = inbox.get(Tick, "tracker")
        if tick is not None and tick.step > self.sent_tick:
            return True
        for rid in self.ids:
            p, pl = inbox.get(Pose, rid), inbox.get(Plan, rid)
            if p is not None and p.seq > self.sent_pose.get(rid, -1):
                return True
            if pl is not None and pl.step > self.sent_plan.get(rid, -1):
                return True
        return False

    def publish(self) -> Tick | None:
        """Republish what came since the last call; the newest tick, if new."""
        types, inbox = self.types, self.inbox
        with inbox.cond:
            poses = {r: m for r in self.ids if (m := inbox.get(Pose, r)) is not None}
            plans = {r: n for r in self.ids if (n := inbox.get(Plan, r)) is not None}
            tick = inbox.get(Tick, "tracker")
        for rid, p in poses.items():
            if p.seq > self.sent_pose.get(rid, -1):
                self.sent_pose[rid] = p.seq
                self.pose[rid].put(types.pose_stamped(p.t, p.x, p.y, p.theta))
        for rid, pl in plans.items():
            if pl.step > self.sent_plan.get(rid, -1):
                self.sent_plan[rid] = pl.step
                self.plan[rid].put(types.path(pl.t0 - pl.Ts, pl.Ts, pl.nominal))
                self.reference[rid].put(types.path(pl.t0, pl.Ts, pl.committed))
        if tick is None or tick.step <= self.sent_tick:
            return None
        self.sent_tick = tick.step
        robots = [  # the footprint and the goal come with a robot's plans
            types.Footprint(
                index=i, robot=rid, position=(poses[rid].x, poses[rid].y), radius=plans[rid].footprint,
                goal=(float(plans[rid].goal[0]), float(plans[rid].goal[1])),
            )
            for i, rid in enumerate(self.ids)
            if rid in poses and rid in plans
        ]  # fmt: skip
        self.footprints.put(types.footprints(tick.t, robots))
        return tick

    def handle_goals(self) -> None:
        """Give every goal received to its agent, one at a time; log what became of it."""
        for _ in range(MAX_PENDING_GOALS):
            with self.inbox.cond:
                if not self.goals:
                    return
                robot, payload = self.goals.popleft()
            self._goal(robot, payload)

    def _goal(self, robot: str, payload: bytes) -> None:
        topic = graph.robot_topic(robot, graph.GOAL_POSE)
        source = graph.topic_key(self.node.domain, topic, self.types.POSE_STAMPED, "…")
        try:
            if len(payload) > MAX_PAYLOAD:
                raise ValueError(f"{len(payload)} bytes, more than {MAX_PAYLOAD}")
            gp = self.types.read_goal_pose(payload)
        except ValueError as e:
            with self.inbox.cond:
                self.inbox.rejects.reject(source, WireError(str(e)))
            return
        target = np.array([gp.x, gp.y])
        shown = f"({gp.x:.3f}, {gp.y:.3f})" if np.all(np.isfinite(target)) else f"({gp.x}, {gp.y})"
        if gp.frame not in (self.types.FRAME, ""):
            log(
                ROLE, f"goal_pose {shown} for {robot} refused: frame {gp.frame!r} is not {self.types.FRAME!r}"
            )
            return
        with self.inbox.cond:
            own = self.inbox.get(Plan, robot)
            plans = [pl for r in self.ids if r != robot and (pl := self.inbox.get(Plan, r)) is not None]
        # The one goal rule, with what this face has heard: the robot's footprint and where it is
        # come with its plan (without one, a point: finite, in the arena, outside every obstacle);
        # its agent applies the rule again, with what it knows, and has the last word.
        problem = (
            goal_problem(self.scn, 0.0, target, [])
            if own is None
            else goal_problem(self.scn, own.footprint, target, plans, at=own.committed[-1])
        )
        if problem is not None:
            log(ROLE, f"goal_pose {shown} for {robot} refused: {problem}")
            return
        ok, reason = ask_goal(self.session, self.keys, Goal(robot=robot, goal=target))
        if ok:
            log(ROLE, f"goal_pose {shown} for {robot} accepted by its agent")
        else:
            log(ROLE, f"goal_pose {shown} for {robot} refused: {reason}")

    def close(self) -> None:
        """Undeclare the liveliness tokens (the ROS 2 graph's entities) and the subscribers."""
        for t in self.tokens:
            t.undeclare()
        for s in self.subs:
            s.undeclare()


def main(argv: list[str] | None = None) -> int:
    """``python -m ros2_link``: the ROS 2 face of a running fleet until the run ends, or SIGTERM or
    SIGINT (see the module docstring); returns the exit code (0 once stopped, 2 bad input or without
    rosbags)."""
    ap = argparse.ArgumentParser(prog="python -m ros2_link", description=__doc__.splitlines()[0])
    add_common_args(ap)
    ap.add_argument(
        "--ros-domain", type=domain_arg, default=None, metavar="N",
        help=f"ROS 2 domain id, 0 … {ROS_DOMAIN_MAX} (default: the scenario's [ros2] domain, else 0)",
    )  # fmt: skip
    args = ap.parse_args(argv)
    try:
        scn = load_scenario(args.scenario)
    except ConfigError as e:
        print(f"{ROLE}: error: {e}", file=sys.stderr)
        return 2
    problem = ros2_problem([r.id for r in scn.robots])
    if problem is not None:
        print(f"{ROLE}: error: robots: {problem}", file=sys.stderr)
        return 2
    try:
        import rosbags  # noqa: F401
    except ImportError:
        print(f"{ROLE}: error: --ros2 needs rosbags: pip install 'epuck-fleet[ros2]'", file=sys.stderr)
        return 2
    domain = scn.ros2.domain if args.ros_domain is None else args.ros_domain
    keys = Keys(args.fleet)
    session = open_session(args)
    inbox = Inbox(keys, ROLE)
    subs = [
        inbox.subscribe(session, keys.pose(), Pose),
        inbox.subscribe(session, keys.plan(), Plan),
        inbox.subscribe(session, keys.clock, Tick),
    ]
    stopping = False

    def on_term(signum: int, frame: Any) -> None:
        nonlocal stopping
        stopping = True
        with inbox.cond:
            inbox.cond.notify_all()

    signal.signal(signal.SIGTERM, on_term)
    signal.signal(signal.SIGINT, on_term)  # Ctrl-C of a face started by hand: the same clean end
    face = RosFace(scn, session, keys, inbox, domain, args.fleet)
    announce(ROLE, domain=domain, node=face.node.name, session=face.node.session_id)
    log(ROLE, f"ROS 2 node /{face.node.name} on domain {domain}: /<id>/pose, plan, reference, goal_pose")
    try:
        while not stopping:
            with inbox.cond:
                inbox.cond.wait_for(lambda: stopping or face.news(), 0.5)
            tick = face.publish()
            face.handle_goals()
            if tick is not None and tick.stop:
                break
    finally:
        if face.dropped_goals or inbox.rejects.total:
            log(
                ROLE,
                f"{face.dropped_goals} goals dropped (too many at once), "
                f"{inbox.rejects.total} rejected payloads",
            )
        face.close()
        for s in subs:
            s.undeclare()
        session.close()
    return 0
