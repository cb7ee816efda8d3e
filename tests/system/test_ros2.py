"""ROS 2 sees and steers a running fleet (``fleet run --ros2``), checked from outside by a client we
did not write (``zenoh-ros2-sdk``, which speaks rmw_zenoh's conventions: tests/ros2_client.py) and
by the bytes on the wire.  A malformed ``goal_pose`` is rejected and counted.

A realtime fleet of the paper's two robots runs with its ROS face on domain 0.  The client joins
as a peer on the fleet's hub, with rmw_zenoh's own session configuration.  It discovers the
fleet's topics and their types through the liveliness tokens, and receives ``/r1/pose`` and
decodes it.  It then publishes three goals on ``/r1/goal_pose``:

- one outside the arena, which the ROS face refuses itself;
- one on r2's goal, which r1's agent refuses;
- a legal one, which r1 then reaches.

Beside it, a raw Zenoh subscriber checks each pose sample's attachment: 33 bytes, a sequence
number that grows by one, one GID.  Every wait is bounded, and every process is ended by pid.
"""

from __future__ import annotations

import json
import os
import queue
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from fleet import Fleet
from fleet.experiment.script import LOG
from ground.params import ControllerParams
from ground.scenario import GOAL_TOLERANCE
from ros2_link import graph, types
from transport.net import NetConfig, free_port, loopback

ROOT = Path(__file__).resolve().parents[2]
WAIT = 90.0
"""Bound of every wait [s]."""
GOAL = (-0.45, 0.6)
"""A legal new goal of r1 [m], away from its way and from r2's goal."""
OUTSIDE = (5.0, 0.0)
ON_R2 = (-0.7, 0.0)
"""r2's goal in the scenario: r1 may not park on it."""


def _lines(stream, q: queue.Queue) -> None:
    for line in stream:
        q.put(line)
    q.put(None)  # the end of the stream


@pytest.mark.realtime
def test_a_ros2_client_discovers_reads_and_steers_the_fleet(tmp_path):
    import zenoh

    scenario = tmp_path / "two.toml"
    scenario.write_text(
        (ROOT / "scenarios" / "paper_two_robots.toml").read_text() + "\n[ros2]\nenabled = true\n"
    )
    hub = loopback(free_port())
    # Launched by a script, the run lasts until the script ends it: the robots cannot finish
    # before the client, however slow the machine, has given its goal.
    ros = loopback(free_port())  # where ROS 2 tools link to the fleet's ROS face
    fleet = Fleet.launch(
        scenario, clock="realtime", processes=True, out=tmp_path / "out", hub=hub, ros_listen=ros
    )
    client = session = None
    try:
        assert "ros2" in fleet.processes
        session = zenoh.open(NetConfig(listen=[loopback(0)], connect=[hub]).zenoh())
        pose_key = graph.topic_key(0, "/r1/pose", types.POSE_STAMPED, types.type_hash(types.POSE_STAMPED))
        got: list[tuple[int, int, bytes, bytes]] = []
        cond = threading.Condition()

        def on_pose(s) -> None:
            with cond:
                a = s.attachment
                got.append(
                    (
                        *graph.read_attachment(a.to_bytes())[::2],
                        len(a.to_bytes()).to_bytes(1, "little"),
                        s.payload.to_bytes(),
                    )
                )
                cond.notify_all()

        sub = session.declare_subscriber(pose_key, on_pose)
        # A malformed goal_pose, once the ROS face's samples reach this session (so its
        # subscription is known here): rejected and counted, and the face goes on.
        with cond:
            assert cond.wait_for(lambda: got, WAIT)
        goal_key = graph.topic_key(
            0, "/r1/goal_pose", types.POSE_STAMPED, types.type_hash(types.POSE_STAMPED)
        )
        session.put(goal_key, b"\x00\x01\x00\x00not a pose", attachment=graph.attachment(1, 0, bytes(16)))
        port = int(ros.rsplit(":", 1)[1])
        cmd = [
            sys.executable, str(ROOT / "tests" / "ros2_client.py"), "--port", str(port), "--robot", "r1",
            "--index", "0", "--goal", *map(str, GOAL), "--bad-goal", *map(str, OUTSIDE), "--bad-goal",
            *map(str, ON_R2), "--msgs", str(tmp_path / "msgs"), "--timeout", str(WAIT),
            "--tolerance", str(ControllerParams().lookahead + GOAL_TOLERANCE + 0.01),
        ]  # fmt: skip
        client_log = tmp_path / "client.log"
        with client_log.open("w") as client_err_file:
            client = subprocess.Popen(
                cmd, stdout=subprocess.PIPE, stderr=client_err_file, text=True, stdin=subprocess.DEVNULL,
                env={**os.environ, "PYTHONPATH": str(ROOT)},
            )  # fmt: skip
        out: queue.Queue[str | None] = queue.Queue()
        threading.Thread(target=_lines, args=(client.stdout, out), daemon=True).start()
        said: dict[str, dict] = {}
        while "arrived" not in said:
            try:
                line = out.get(timeout=WAIT)
            except queue.Empty:
                break
            if line is None:
                break
            m = json.loads(line)
            said[m["event"]] = m
        try:
            rc = client.wait(timeout=WAIT)
        except subprocess.TimeoutExpired:
            rc = None
        client_err = client_log.read_text()
        fleet_log = (tmp_path / "out" / LOG).read_text()
        assert rc == 0 and set(said) == {"topics", "pose", "goal_marker", "arrived"}, (
            said,
            client_err[-3000:],
            fleet_log[-3000:],
        )

        # Discovery: every topic of every robot, with its type.
        topics = said["topics"]["topics"]
        for rid in ("r1", "r2"):
            assert topics[f"/{rid}/pose"] == [types.POSE_STAMPED]
            assert topics[f"/{rid}/plan"] == topics[f"/{rid}/reference"] == [types.PATH]
            assert topics[f"/{rid}/goal_pose"] == [types.POSE_STAMPED]
        assert topics["/fleet/footprints"] == [types.MARKER_ARRAY]
        # The pose as decoded by the client: in the world frame, in the arena.
        pose = said["pose"]
        assert pose["frame"] == "world" and -1 <= pose["x"] <= 1 and -1 <= pose["y"] <= 1
        assert "[ros2] rejected payload from 0/r1/goal_pose/" in fleet_log, fleet_log[-3000:]
        # The three goals: two refused with their reason, the third taken and reached.
        # The reasons are the one goal rule's texts, as the agent and `fleet goal` give them.
        assert (
            "goal_pose (5.000, 0.000) for r1 refused: goal (5.00, 0.00) lies outside the arena" in fleet_log
        )
        why = "goal (-0.70, 0.00) is 0.000 m from r2's goal, closer than the footprints and the margin allow"
        assert f"goal_pose (-0.700, 0.000) for r1 refused: {why}" in fleet_log, fleet_log[-3000:]
        assert "goal_pose (-0.450, 0.600) for r1 accepted by its agent" in fleet_log, fleet_log[-3000:]
        # On the wire: each pose sample carries rmw_zenoh's attachment.
        with cond:
            samples = list(got)
        assert len(samples) >= 10
        seqs = [s[0] for s in samples]
        assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
        assert {s[1] for s in samples} == {samples[0][1]} and len(samples[0][1]) == 16
        assert all(s[3][:4] == b"\x00\x01\x00\x00" for s in samples)
        sub.undeclare()
    finally:
        if client is not None and client.poll() is None:
            client.kill()
            client.wait(timeout=30)
        if session is not None:
            session.close()
        summary = fleet.close()
    assert summary is not None and summary["exit_codes"]["ros2"] == 0, summary
