"""An rmw_zenoh client we did not write (the ``zenoh-ros2-sdk`` package), pointed at a running
fleet, as a ROS 2 tool on a lab machine would be: ``python tests/ros2_client.py --port P ...``.

It prints one JSON line per finding on stdout, for the test that started it to read:

- ``{"event": "topics", "topics": {name: [types]}}``: what discovery (the ``@ros2_lv`` liveliness
  tokens, as ``ros2 topic list -t`` reads them) shows;
- ``{"event": "pose", ...}``: the first ``/<robot>/pose`` it decoded;
- ``{"event": "goal_marker", ...}``: ``/fleet/footprints`` shows the robot's goal where it sent it;
- ``{"event": "arrived", ...}``: ``/<robot>/pose`` is within the tolerance of that goal.

It publishes each ``--bad-goal`` once and then ``--goal`` on ``/<robot>/goal_pose`` (frame
``world``) once a second until the footprints show it.  The SDK computes the type hashes itself,
from ``.msg`` definitions written here from rosbags' Jazzy store (the only copy on this machine,
which has no ROS 2; the SDK would otherwise fetch them with git).  Every wait is bounded.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import threading
import time
from pathlib import Path

TYPES = ("geometry_msgs/msg/PoseStamped", "visualization_msgs/msg/MarkerArray")


def _field(store, desc) -> str:
    from rosbags.interfaces import Nodetype

    kind, rest = desc
    if kind == Nodetype.BASE:
        name, bound = rest
        return f"{name}<={bound}" if bound else name
    if kind == Nodetype.NAME:
        pkg, _, name = rest.split("/")
        return f"{pkg}/{name}"
    inner, n = rest
    if kind == Nodetype.ARRAY:
        return f"{_field(store, inner)}[{n}]"
    return f"{_field(store, inner)}[<={n}]" if n else f"{_field(store, inner)}[]"


def write_msgs(root: Path, types: tuple[str, ...] | list[str] = TYPES) -> None:
    """``root/<pkg>/msg/<Name>.msg`` for ``types`` and everything they use."""
    from rosbags.interfaces import Nodetype
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    todo, done = list(types), set()
    while todo:
        t = todo.pop()
        if t in done:
            continue
        done.add(t)
        consts, fields = store.fielddefs[t]
        lines = [f"{typ} {name}={value}" for name, typ, value in consts]
        for name, desc in fields:
            lines.append(f"{_field(store, desc)} {name}")
            d = desc
            while d[0] in (Nodetype.ARRAY, Nodetype.SEQUENCE):
                d = d[1][0]
            if d[0] == Nodetype.NAME:
                todo.append(d[1])
        pkg, _, name = t.split("/")
        path = root / pkg / "msg" / f"{name}.msg"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("\n".join(lines) + "\n")


def say(**line) -> None:
    print(json.dumps(line), flush=True)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", type=int, required=True)
    ap.add_argument("--domain", type=int, default=0)
    ap.add_argument("--robot", required=True)
    ap.add_argument(
        "--index", type=int, required=True, help="the robot's place in the scenario (its marker id)"
    )
    ap.add_argument("--goal", type=float, nargs=2, required=True)
    ap.add_argument("--bad-goal", type=float, nargs=2, action="append", default=[])
    ap.add_argument("--msgs", required=True, help="a directory for the .msg files")
    ap.add_argument("--tolerance", type=float, default=0.03)
    ap.add_argument("--timeout", type=float, default=120.0)
    args = ap.parse_args()
    # rmw_zenoh's own session configuration, listening on loopback only (not every interface).
    os.environ["ZENOH_CONFIG_OVERRIDE"] = 'listen/endpoints=["tcp/127.0.0.1:0"]'
    write_msgs(Path(args.msgs))
    import zenoh_ros2_sdk as sdk

    sdk.get_registry(args.msgs)
    sdk.ZenohSession.get_instance("127.0.0.1", args.port)
    end = time.monotonic() + args.timeout
    wanted = {f"/{args.robot}/pose", f"/{args.robot}/goal_pose", "/fleet/footprints"}
    topics: dict[str, list[str]] = {}
    while time.monotonic() < end and not wanted <= set(topics):
        topics = dict(sdk.get_topic_names_and_types(domain_id=args.domain, timeout=2.0))
    say(event="topics", topics=topics)
    if not wanted <= set(topics):
        return 1

    got = threading.Condition()
    seen: dict[str, object] = {}

    def on_pose(msg) -> None:
        with got:
            p = msg.pose.position
            seen.setdefault("first", (msg.header.frame_id, p.x, p.y, msg.header.stamp.sec))
            seen["pose"] = (p.x, p.y)
            got.notify_all()

    def on_markers(msg) -> None:
        with got:
            for m in msg.markers:
                if m.ns == "goal":
                    seen.setdefault("goals", {})[m.id] = (m.pose.position.x, m.pose.position.y)  # type: ignore[union-attr]
            got.notify_all()

    sub = sdk.ROS2Subscriber(
        f"/{args.robot}/pose", TYPES[0], on_pose, domain_id=args.domain, router_port=args.port
    )
    markers = sdk.ROS2Subscriber(
        "/fleet/footprints", TYPES[1], on_markers, domain_id=args.domain, router_port=args.port
    )
    with got:
        got.wait_for(lambda: "first" in seen, max(0.0, end - time.monotonic()))
    if "first" not in seen:
        return 1
    frame, x, y, sec = seen["first"]  # type: ignore[misc]
    say(event="pose", frame=frame, x=x, y=y, sec=sec)

    pub = sdk.ROS2Publisher(
        f"/{args.robot}/goal_pose", TYPES[0], domain_id=args.domain, router_port=args.port
    )
    Header = pub.session_mgr.store.types["std_msgs/msg/Header"]
    Time = pub.session_mgr.store.types["builtin_interfaces/msg/Time"]
    Pose = pub.session_mgr.store.types["geometry_msgs/msg/Pose"]
    Point = pub.session_mgr.store.types["geometry_msgs/msg/Point"]
    Quat = pub.session_mgr.store.types["geometry_msgs/msg/Quaternion"]

    def send(x: float, y: float) -> None:
        pub.publish(
            header=Header(stamp=Time(sec=0, nanosec=0), frame_id="world"),
            pose=Pose(position=Point(x=x, y=y, z=0.0), orientation=Quat(x=0.0, y=0.0, z=0.0, w=1.0)),
        )

    index, (gx, gy) = args.index, args.goal

    def shown() -> bool:
        g = seen.get("goals", {}).get(index)  # type: ignore[union-attr]
        return g is not None and math.hypot(g[0] - gx, g[1] - gy) < 1e-9

    for bx, by in args.bad_goal:
        send(bx, by)
    while time.monotonic() < end:
        send(gx, gy)
        with got:
            if got.wait_for(shown, 1.0):
                break
    if not shown():
        return 1
    say(event="goal_marker", x=gx, y=gy)
    with got:
        ok = got.wait_for(
            lambda: math.hypot(seen["pose"][0] - gx, seen["pose"][1] - gy) < args.tolerance,  # type: ignore[index]
            max(0.0, end - time.monotonic()),
        )
    if not ok:
        return 1
    say(event="arrived", x=seen["pose"][0], y=seen["pose"][1])  # type: ignore[index]
    for s in (sub, markers, pub):
        s.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
