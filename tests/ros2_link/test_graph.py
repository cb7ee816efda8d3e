"""The ROS 2 face's names and bytes against rmw_zenoh's design document (``ros2/rmw_zenoh``,
``docs/design.md``, Jazzy), whose examples are a ``talker`` and a ``listener`` on ``/chatter``
(``std_msgs/msg/String``) in domain 0, in a session of id ``aac3178e146ba6f1fc6e6a4085e77f21``:

- data key ``0/chatter/std_msgs::msg::dds_::String_/RIHS01_df668c74…``, the hash in full
  below;
- the listener node's token ``@ros2_lv/0/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener``;
- its subscription's token, entity 10, keep last 10:
  ``…/0/10/MS/%/%/listener/%chatter/<type>/<hash>/::,10:,:,:,,``;
- the talker's publisher, keep last 7: ``…/MP/%/%/talker/%chatter/<type>/<hash>/::,7:,:,:,,``;
- an attachment of the sequence number, the source timestamp and the 16-byte GID, 33 bytes.

The type hashes are rosbags', and a second implementation we did not write (``zenoh-ros2-sdk``,
from ``.msg`` text) must agree with them for every type the fleet publishes.
"""

from __future__ import annotations

import struct

import numpy as np
import pytest
from ros2_client import write_msgs

from ros2_link import graph, types

SESSION = "aac3178e146ba6f1fc6e6a4085e77f21"
STRING = "std_msgs/msg/String"
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
STRING_DDS = "std_msgs::msg::dds_::String_"


def test_rosbags_hashes_std_msgs_string_as_the_design_document_does():
    assert types.type_hash(STRING) == STRING_HASH


def test_the_data_key_of_the_chatter_example():
    assert graph.dds_type_name(STRING) == STRING_DDS
    assert graph.topic_key(0, "/chatter", STRING, STRING_HASH) == f"0/chatter/{STRING_DDS}/{STRING_HASH}"
    assert (
        graph.topic_key(3, "/r1/pose", types.POSE_STAMPED, types.type_hash(types.POSE_STAMPED))
        == "3/r1/pose/geometry_msgs::msg::dds_::PoseStamped_/"
        "RIHS01_10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8"
    )


def test_the_liveliness_tokens_of_the_example_nodes():
    listener = graph.Node(domain=0, session_id=SESSION, node_id=0, name="listener")
    assert listener.token() == f"@ros2_lv/0/{SESSION}/0/0/NN/%/%/listener"
    sub = listener.endpoint_token(
        10, graph.SUBSCRIPTION, "/chatter", STRING, STRING_HASH, graph.Qos(depth=10)
    )
    assert (
        sub == f"@ros2_lv/0/{SESSION}/0/10/MS/%/%/listener/%chatter/{STRING_DDS}/{STRING_HASH}/::,10:,:,:,,"
    )
    talker = graph.Node(domain=0, session_id=SESSION, node_id=0, name="talker")
    pub = talker.endpoint_token(10, graph.PUBLISHER, "/chatter", STRING, STRING_HASH, graph.Qos(depth=7))
    assert pub == f"@ros2_lv/0/{SESSION}/0/10/MP/%/%/talker/%chatter/{STRING_DDS}/{STRING_HASH}/::,7:,:,:,,"


def test_qos_fields_differing_from_the_default_are_written():
    best_effort = graph.Qos(reliability=2, durability=1, history=2, depth=1)
    assert best_effort.token() == "2:1:2,1:,:,:,,"


def test_names_are_mangled_and_bad_ones_refused():
    assert graph.mangle("/r1/goal_pose") == "%r1%goal_pose"
    assert graph.mangle("") == "%"
    with pytest.raises(ValueError, match="not a ROS 2 type name"):
        graph.dds_type_name("geometry_msgs/PoseStamped")
    with pytest.raises(ValueError, match="not absolute"):
        graph.topic_key(0, "r1/pose", STRING, STRING_HASH)


def test_the_attachment_is_33_bytes_little_endian():
    gid = bytes(range(16))
    data = graph.attachment(7, 1_700_000_000_123_456_789, gid)
    assert len(data) == graph.ATTACHMENT_SIZE == 33
    assert data[:8] == (7).to_bytes(8, "little")
    assert data[8:16] == struct.pack("<q", 1_700_000_000_123_456_789)
    assert data[16] == 16 and data[17:] == gid
    assert graph.read_attachment(data) == (7, 1_700_000_000_123_456_789, gid)
    with pytest.raises(ValueError):
        graph.read_attachment(data[:-1])
    with pytest.raises(ValueError):
        graph.attachment(1, 2, gid[:8])


def test_gids_are_distinct_per_entity_and_repeatable():
    a, b = graph.gid(SESSION, 1), graph.gid(SESSION, 2)
    assert len(a) == 16 and a != b and graph.gid(SESSION, 1) == a


@pytest.mark.parametrize("ros_type", [types.POSE_STAMPED, types.PATH, types.MARKER_ARRAY, STRING])
def test_a_second_implementation_computes_the_same_type_hash(ros_type, tmp_path):
    """zenoh-ros2-sdk hashes the type from its ``.msg`` text and its dependencies' (its own code,
    not rosbags'): a subscriber of it finds our key only if the two agree."""
    from zenoh_ros2_sdk.utils import compute_type_hash_from_msg

    write_msgs(tmp_path, [ros_type])
    defs = {f"{p.parent.parent.name}/msg/{p.stem}": p.read_text() for p in tmp_path.glob("*/msg/*.msg")}
    deps = {t: d for t, d in defs.items() if t != ros_type}
    assert len(deps) >= (0 if ros_type == STRING else 3)
    assert compute_type_hash_from_msg(ros_type, defs[ros_type], deps) == types.type_hash(ros_type)


def _decode(payload: bytes, ros_type: str):
    assert payload[:4] == b"\x00\x01\x00\x00"  # CDR, little-endian encapsulation
    return types.STORE.deserialize_cdr(payload, ros_type)


def test_a_pose_is_a_pose_stamped_in_world_with_the_heading_about_z():
    msg = _decode(types.pose_stamped(12.3, 0.25, -0.5, np.pi / 2), types.POSE_STAMPED)
    assert msg.header.frame_id == "world"
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (12, 300_000_000)
    assert (msg.pose.position.x, msg.pose.position.y, msg.pose.position.z) == (0.25, -0.5, 0.0)
    q = msg.pose.orientation
    assert np.allclose([q.x, q.y, q.z, q.w], [0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5)])


def test_a_path_keeps_every_point_its_time_and_faces_along_it():
    pts = np.array([[0.0, 0.0], [0.1, 0.0], [0.1, 0.1]])
    msg = _decode(types.path(2.0, 0.1, pts), types.PATH)
    assert [(p.pose.position.x, p.pose.position.y) for p in msg.poses] == [tuple(p) for p in pts]
    assert [round(p.header.stamp.nanosec / 1e9 + p.header.stamp.sec, 9) for p in msg.poses] == [2.0, 2.1, 2.2]
    yaw = [2 * np.arctan2(p.pose.orientation.z, p.pose.orientation.w) for p in msg.poses]
    assert np.allclose(yaw, [0.0, np.pi / 2, np.pi / 2])


def test_the_footprints_show_each_robot_and_its_goal():
    robots = [
        types.Footprint(0, "r1", (0.1, 0.2), 0.134, (0.7, 0.0)),
        types.Footprint(1, "r2", (0, 0), 0.1, (-1, 0)),
    ]
    msg = _decode(types.footprints(1.0, robots), types.MARKER_ARRAY)
    got = {(m.ns, m.id): m for m in msg.markers}
    assert set(got) == {("footprint", 0), ("goal", 0), ("footprint", 1), ("goal", 1)}
    disc = got[("footprint", 0)]
    assert disc.type == disc.CYLINDER and disc.header.frame_id == "world"
    assert (disc.pose.position.x, disc.pose.position.y, disc.scale.x) == (0.1, 0.2, 0.268)
    assert (got[("goal", 1)].pose.position.x, got[("goal", 1)].pose.position.y) == (-1.0, 0.0)


def test_a_goal_pose_is_read_and_garbage_is_refused_with_a_value_error():
    gp = types.read_goal_pose(types.pose_stamped(0.0, 0.3, -0.2, 1.0))
    assert (gp.frame, gp.x, gp.y) == ("world", 0.3, -0.2)
    rng = np.random.default_rng(7)
    good = types.pose_stamped(0.0, 0.3, -0.2, 1.0)
    for n in range(300):  # truncations, random bytes and flipped bytes of a good payload
        if n < 60:
            data = good[: int(rng.integers(0, len(good)))]
        elif n < 120:
            data = rng.bytes(int(rng.integers(0, 200)))
        else:
            b = bytearray(good)
            for i in rng.integers(0, len(b), size=3):
                b[i] ^= int(rng.integers(1, 256))
            data = bytes(b)
        try:
            types.read_goal_pose(data)
        except ValueError:
            pass
