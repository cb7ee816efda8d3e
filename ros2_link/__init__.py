"""The fleet as ROS 2 sees it: rmw_zenoh's key expressions, liveliness tokens, attachments and CDR
payloads on the fleet's own Zenoh network, with no bridge (docs/ros2.md).

:mod:`ros2_link.graph` writes rmw_zenoh's names (pure functions, no Zenoh), :mod:`ros2_link.types`
the ROS messages (CDR and type hashes by ``rosbags``), and :mod:`ros2_link.node` is the process
(``python -m ros2_link``) that ``fleet run --ros2`` starts.  Nothing here runs inside an agent's
step: the process only observes the fleet, and gives a goal to an agent as every goal is given."""
