"""Pose sources: the simulated tracker (and, later, the ArUco camera tracker)."""
