"""The camera test scene both tracker test files draw: fiducials and robot markers."""

FIDUCIALS = {
    40: (-1.1, -1.1),
    41: (0.0, -1.1),
    42: (1.1, -1.1),
    43: (1.1, 1.1),
    44: (0.0, 1.1),
    45: (-1.1, 1.1),
}
"""Fiducial id → world position (x, y) [m]: corners and side midpoints of a 2.2 m square."""
OFFSET = (0.012, -0.004)
"""Marker centre in the robot frame [m]."""
SIZE = 0.05
"""Robot marker side [m]."""
