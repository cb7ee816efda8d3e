"""rmw_zenoh's conventions, as its design document (``ros2/rmw_zenoh``, ``docs/design.md``, the
Jazzy branch) specifies them: the data key expression of a topic, the liveliness tokens through
which ``ros2 topic list`` and ``ros2 node list`` discover the graph, the QoS field of a token, and
the attachment every publication carries.  Pure functions: nothing here opens Zenoh.

- **Topic key**: ``<domain>/<topic without its leading />/<DDS type name>/<type hash>``, e.g.
  ``0/r1/pose/geometry_msgs::msg::dds_::PoseStamped_/RIHS01_10f3…``.
- **Liveliness token**: ``@ros2_lv/<domain>/<session id>/<node id>/<entity id>/<kind>/<enclave>/
  <namespace>/<node name>``, followed for a publisher (``MP``) or a subscription (``MS``) by
  ``/<topic>/<DDS type name>/<type hash>/<QoS>``; a node's own token (``NN``) has its node id twice.
  Names are mangled (``/`` becomes ``%``), and an empty namespace or enclave is ``%``.
- **Attachment**: the sequence number (int64), the source timestamp (int64, ns since the Unix
  epoch) and the publisher's 16-byte GID as a sequence (its length as one byte, 16, then the
  bytes): 33 bytes, little-endian, as zenoh-ext's serializer writes them.
"""

from __future__ import annotations

import hashlib
import re
import struct
from dataclasses import dataclass

ADMIN_SPACE = "@ros2_lv"
"""The key prefix of rmw_zenoh's liveliness tokens."""
GID_SIZE = 16
"""Bytes of a publisher's GID (``RMW_GID_STORAGE_SIZE`` on Jazzy)."""
ATTACHMENT_SIZE = 8 + 8 + 1 + GID_SIZE
"""Bytes of a publication's attachment: 33."""
NODE, PUBLISHER, SUBSCRIPTION = "NN", "MP", "MS"
"""Entity kinds of the liveliness tokens this fleet declares."""
POSE, PLAN, REFERENCE, GOAL_POSE = "pose", "plan", "reference", "goal_pose"
"""The fleet's topics of each robot ``<id>``: ``/<id>/pose``, ``/<id>/plan`` and ``/<id>/reference``
are published, ``/<id>/goal_pose`` is subscribed."""
ROBOT_TOPICS = (POSE, PLAN, REFERENCE)
"""The topics the fleet's ROS face publishes for every robot."""
FOOTPRINTS = "/fleet/footprints"
"""The fleet's one topic of all robots (their footprints and goals)."""
_TYPE = re.compile(r"^([A-Za-z][A-Za-z0-9_]*)/(msg|srv|action)/([A-Za-z][A-Za-z0-9_]*)$")


def mangle(name: str) -> str:
    """A ROS name as a token field: every ``/`` becomes ``%``; the empty name is ``%``."""
    return name.replace("/", "%") if name else "%"


def dds_type_name(ros_type: str) -> str:
    """``geometry_msgs/msg/PoseStamped`` → ``geometry_msgs::msg::dds_::PoseStamped_``."""
    m = _TYPE.fullmatch(ros_type)
    if m is None:
        raise ValueError(f"{ros_type!r} is not a ROS 2 type name (package/msg/Name)")
    package, kind, name = m.groups()
    return f"{package}::{kind}::dds_::{name}_"


def robot_topic(robot: str, topic: str) -> str:
    """``/<robot>/<topic>``, e.g. ``/r1/pose``."""
    return f"/{robot}/{topic}"


def topic_key(domain: int, topic: str, ros_type: str, type_hash: str) -> str:
    """The key expression a topic's samples travel on (``topic`` absolute, e.g. ``/r1/pose``)."""
    if not topic.startswith("/"):
        raise ValueError(f"topic {topic!r} is not absolute")
    return f"{domain}/{topic[1:]}/{dds_type_name(ros_type)}/{type_hash}"


@dataclass(frozen=True)
class Qos:
    """A ROS 2 QoS profile as far as a liveliness token tells it (rmw's enum values)."""

    reliability: int = 1
    """1 reliable (the default), 2 best effort."""
    durability: int = 2
    """1 transient local, 2 volatile (the default)."""
    history: int = 1
    """1 keep last (the default), 2 keep all."""
    depth: int = 10
    """History depth (keep last)."""

    def token(self) -> str:
        """rmw_zenoh's QoS field: ``<reliability>:<durability>:<history>,<depth>:<deadline s>,
        <deadline ns>:<lifespan s>,<lifespan ns>:<liveliness>,<lease s>,<lease ns>``, where a value
        equal to rmw's default profile (reliable, volatile, keep last) is left empty, the depth
        always written, and deadline, lifespan and liveliness are the defaults here."""
        default = Qos()
        rel = "" if self.reliability == default.reliability else str(self.reliability)
        dur = "" if self.durability == default.durability else str(self.durability)
        hist = "" if self.history == default.history else str(self.history)
        return f"{rel}:{dur}:{hist},{self.depth}:,:,:,,"


@dataclass(frozen=True)
class Node:
    """A ROS 2 node of this fleet's ROS link, in a Zenoh session."""

    domain: int
    session_id: str
    """The Zenoh session's id, as hex (``str(session.info.zid())``)."""
    node_id: int
    name: str
    namespace: str = ""
    """Absolute, or empty for the root namespace."""
    enclave: str = ""

    def token(self) -> str:
        """The node's liveliness token (kind ``NN``)."""
        return "/".join(
            (
                ADMIN_SPACE, str(self.domain), self.session_id, str(self.node_id), str(self.node_id), NODE,
                mangle(self.enclave), mangle(self.namespace), mangle(self.name),
            )
        )  # fmt: skip

    def endpoint_token(
        self, entity_id: int, kind: str, topic: str, ros_type: str, type_hash: str, qos: Qos
    ) -> str:
        """A publisher's (``MP``) or subscription's (``MS``) liveliness token."""
        if kind not in (PUBLISHER, SUBSCRIPTION):
            raise ValueError(f"kind {kind!r} is not {PUBLISHER} or {SUBSCRIPTION}")
        head = "/".join(
            (
                ADMIN_SPACE, str(self.domain), self.session_id, str(self.node_id), str(entity_id), kind,
                mangle(self.enclave), mangle(self.namespace), mangle(self.name),
            )
        )  # fmt: skip
        return f"{head}/{mangle(topic)}/{dds_type_name(ros_type)}/{type_hash}/{qos.token()}"


def gid(session_id: str, entity_id: int) -> bytes:
    """A publisher's 16-byte GID: the first bytes of SHA-256 over its session id and entity id,
    unique in the graph and the same for the same session (no random numbers)."""
    return hashlib.sha256(f"{session_id}/{entity_id}".encode()).digest()[:GID_SIZE]


def attachment(sequence: int, timestamp_ns: int, gid_bytes: bytes) -> bytes:
    """The 33-byte attachment of a publication (see the module's docstring)."""
    if len(gid_bytes) != GID_SIZE:
        raise ValueError(f"a GID is {GID_SIZE} bytes, got {len(gid_bytes)}")
    return struct.pack("<qqB", sequence, timestamp_ns, GID_SIZE) + gid_bytes


def read_attachment(data: bytes) -> tuple[int, int, bytes]:
    """(sequence number, source timestamp [ns], GID) of an attachment; ValueError if malformed."""
    if len(data) != ATTACHMENT_SIZE or data[16] != GID_SIZE:
        raise ValueError(f"an attachment is {ATTACHMENT_SIZE} bytes with a {GID_SIZE}-byte GID")
    seq, stamp, _ = struct.unpack_from("<qqB", data)
    return seq, stamp, bytes(data[17:])
