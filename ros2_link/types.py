"""The ROS 2 messages of the fleet's ROS face, serialised by ``rosbags`` (CDR, little-endian, with
its 4-byte encapsulation header) from its Jazzy type store, whose RIHS01 type hashes are those
rmw_zenoh puts in its keys.  Frame ``world`` is the scenario's arena frame; units are SI.

- ``/<id>/pose`` (``geometry_msgs/msg/PoseStamped``): the measured pose of the axle centre, the
  heading θ as the quaternion (0, 0, sin θ/2, cos θ/2) about z.
- ``/<id>/plan`` and ``/<id>/reference`` (``nav_msgs/msg/Path``): positions of the controlled point
  (the look-ahead point the MPC steers, docs/method.md), each pose facing along the path.
- ``/fleet/footprints`` (``visualization_msgs/msg/MarkerArray``): each robot's footprint disc at its
  measured position and its goal.

Stamps are on the fleet clock (seconds since the run's step 0), as the fleet's own messages are.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

FRAME = "world"
"""The frame of every message: the arena's."""
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
PATH = "nav_msgs/msg/Path"
MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"
DISC_HEIGHT = 0.01
"""Height of a footprint or goal disc in RViz [m]."""
GOAL_RADIUS = 0.02
"""Radius of a goal's disc in RViz [m] (the goal tolerance)."""


def _store() -> Any:
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


STORE = _store()
"""rosbags' type store of ROS 2 Jazzy."""
T = STORE.types


def type_hash(ros_type: str) -> str:
    """The RIHS01 hash of ``ros_type`` (``RIHS01_<64 hex>``), as rosbags computes it."""
    return str(STORE.hash_rihs01(ros_type))


def _stamp(t: float) -> Any:
    sec = math.floor(t)
    return T["builtin_interfaces/msg/Time"](sec=int(sec), nanosec=min(round((t - sec) * 1e9), 999_999_999))


def _header(t: float) -> Any:
    return T["std_msgs/msg/Header"](stamp=_stamp(max(t, 0.0)), frame_id=FRAME)


def _pose(x: float, y: float, theta: float) -> Any:
    point = T["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=0.0)
    q = T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(theta / 2), w=math.cos(theta / 2))
    return T["geometry_msgs/msg/Pose"](position=point, orientation=q)


def pose_stamped(t: float, x: float, y: float, theta: float) -> bytes:
    """``/<id>/pose``: position [m] and heading [rad] in ``world`` at time ``t`` [s]."""
    msg = T[POSE_STAMPED](header=_header(t), pose=_pose(x, y, theta))
    return bytes(STORE.serialize_cdr(msg, POSE_STAMPED))


def path(t0: float, Ts: float, points: np.ndarray) -> bytes:
    """A path through ``points`` (M, 2) [m], point i at time ``t0 + i·Ts`` [s]; each pose faces
    the next point (the last the one before it)."""
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    d = np.diff(pts, axis=0)
    heading = np.arctan2(d[:, 1], d[:, 0]) if len(d) else np.zeros(0)
    heading = np.append(heading, heading[-1] if len(heading) else 0.0)
    poses = [
        T[POSE_STAMPED](header=_header(t0 + i * Ts), pose=_pose(p[0], p[1], h))
        for i, (p, h) in enumerate(zip(pts, heading, strict=True))
    ]
    msg = T[PATH](header=_header(t0), poses=poses)
    return bytes(STORE.serialize_cdr(msg, PATH))


@dataclass(frozen=True)
class Footprint:
    """One robot in ``/fleet/footprints``."""

    index: int
    """The marker id (the robot's place in the scenario)."""
    robot: str
    position: tuple[float, float]
    """Measured position [m], world frame."""
    radius: float
    """Footprint radius [m]."""
    goal: tuple[float, float]
    """Goal [m], world frame."""


def _marker(
    t: float, ns: str, index: int, xy: tuple[float, float], radius: float, rgba: tuple[float, ...]
) -> Any:
    m = T["visualization_msgs/msg/Marker"]
    return m(
        header=_header(t), ns=ns, id=index, type=m.CYLINDER, action=m.ADD, pose=_pose(xy[0], xy[1], 0.0),
        scale=T["geometry_msgs/msg/Vector3"](x=2 * radius, y=2 * radius, z=DISC_HEIGHT),
        color=T["std_msgs/msg/ColorRGBA"](r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3]),
        lifetime=T["builtin_interfaces/msg/Duration"](sec=0, nanosec=0), frame_locked=False, points=[],
        colors=[], texture_resource="", texture=T["sensor_msgs/msg/CompressedImage"](
            header=_header(t), format="", data=np.zeros(0, dtype=np.uint8)
        ),
        uv_coordinates=[], text="", mesh_resource="",
        mesh_file=T["visualization_msgs/msg/MeshFile"](filename="", data=np.zeros(0, dtype=np.uint8)),
        mesh_use_embedded_materials=False,
    )  # fmt: skip


def footprints(t: float, robots: Sequence[Footprint]) -> bytes:
    """``/fleet/footprints``: per robot a disc of its footprint (namespace ``footprint``) and a small
    disc at its goal (namespace ``goal``); marker id = the robot's index."""
    markers = []
    for r in robots:
        markers.append(_marker(t, "footprint", r.index, r.position, r.radius, (0.2, 0.4, 0.9, 0.5)))
        markers.append(_marker(t, "goal", r.index, r.goal, GOAL_RADIUS, (0.1, 0.7, 0.2, 0.9)))
    msg = T[MARKER_ARRAY](markers=markers)
    return bytes(STORE.serialize_cdr(msg, MARKER_ARRAY))


@dataclass(frozen=True)
class GoalPose:
    """A ``goal_pose`` as received: the frame it names and the position [m] (z and the
    orientation are not used: a goal is a point)."""

    frame: str
    x: float
    y: float


def read_goal_pose(payload: bytes) -> GoalPose:
    """Decode a ``geometry_msgs/msg/PoseStamped`` CDR payload; ValueError if it is not one."""
    try:
        msg = STORE.deserialize_cdr(payload, POSE_STAMPED)
    except Exception as e:  # rosbags raises several kinds on a malformed buffer
        raise ValueError(f"not a PoseStamped in CDR ({type(e).__name__}: {e})") from None
    return GoalPose(
        frame=str(msg.header.frame_id), x=float(msg.pose.position.x), y=float(msg.pose.position.y)
    )
