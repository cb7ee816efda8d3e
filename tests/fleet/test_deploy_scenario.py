"""The ready-to-run hardware scenario deploy/lab_three_robots.toml and its emulated twin.

They must load, give an admissible tube design whose pose_noise covers the camera's
declared (and measured) error, place three robots that cross in a 1.6 m arena, name
links and markers that the link layer and the tracker accept, and the controller
block must matter: the epuck preset's own numbers do not cover a real camera.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from itertools import combinations
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from agent.tube import synthesize
from epuck_link.transport import parse_link
from ground.geometry import controlled_point
from ground.params import preset
from ground.scenario import Scenario, check_geometry, load_scenario, parse_scenario

ROOT = Path(__file__).resolve().parents[2]
REAL = ROOT / "deploy" / "lab_three_robots.toml"
TWIN = ROOT / "deploy" / "lab_three_robots_emulated.toml"
MEASURED_POSITION_ERROR = 0.0004
"""Largest camera position error on synthetic frames [m] (tracker/camera.py, tests/tracker/test_camera.py)."""
MEASURED_HEADING_ERROR = math.radians(0.7)
"""Largest camera heading error on synthetic frames [rad] (same source)."""


def raw(path: Path) -> dict[str, Any]:
    with path.open("rb") as fh:
        return tomllib.load(fh)


@pytest.fixture(scope="module", params=[REAL, TWIN], ids=["real", "emulated"])
def scn(request) -> Scenario:
    return load_scenario(request.param)


def test_design_is_admissible_and_the_scene_fits_it(scn):
    design = synthesize(scn.controller, scn.arena)
    assert design.admissible, design.failures
    assert scn.arena == (-0.8, 0.8, -0.8, 0.8)
    assert 0.12 < design.footprint < 0.14
    check_geometry(scn, design.footprint)  # raises ConfigError on a bad start or goal


def test_the_three_robots_must_cross(scn):
    """Straight to their goals, every pair would come closer than two footprints."""
    design = synthesize(scn.controller, scn.arena)
    ell = scn.controller.lookahead
    assert [r.id for r in scn.robots] == ["r1", "r2", "r3"]
    paths = []
    for r in scn.robots:
        start, goal = controlled_point(r.start, ell), np.array(r.goal)
        heading = np.array([math.cos(r.start[2]), math.sin(r.start[2])])
        assert np.dot(heading, goal - start) / np.linalg.norm(goal - start) > 0.999  # faces its goal
        assert np.linalg.norm(np.array(r.goal) + np.array(r.start[:2])) < 1e-9  # antipodal
        paths.append(start + np.linspace(0.0, 1.0, 201)[:, None] * (goal - start))
    for a, b in combinations(paths, 2):
        assert np.linalg.norm(a - b, axis=1).min() < 2.0 * design.footprint


def test_links_markers_and_fiducials(scn):
    kinds = [parse_link(r.link) for r in scn.robots]
    if scn.source == str(REAL):
        assert [str(k) for k in kinds] == [
            "serial:/dev/rfcomm0",
            "serial:/dev/rfcomm1",
            "serial:/dev/rfcomm2",
        ]
    else:
        assert {k.kind for k in kinds} == {"emulator"}
    cam = scn.camera
    assert cam is not None
    robot_ids = [r.marker for r in scn.robots]
    fiducial_ids = [f.id for f in cam.fiducials]
    assert robot_ids == [1, 2, 3] and fiducial_ids == [40, 41, 42, 43]
    assert len(set(robot_ids + fiducial_ids)) == 7
    assert cam.marker_size == 0.05
    _, xmax, _, ymax = scn.arena
    for f in cam.fiducials:
        x, y = f.position
        # Just outside a corner: outside the arena on both axes, by less than 15 cm.
        assert 0.0 < abs(x) - xmax < 0.15 and 0.0 < abs(y) - ymax < 0.15, f


def test_the_controller_covers_the_camera(scn):
    """pose_noise bounds the camera's declared noise, which bounds what it was measured to do."""
    cam = scn.camera
    assert cam is not None and cam.position_noise is not None and cam.heading_noise is not None
    pos, head = scn.controller.pose_noise
    assert MEASURED_POSITION_ERROR < cam.position_noise <= pos
    assert MEASURED_HEADING_ERROR < cam.heading_noise <= head
    # W covers the pose noise twice over (n⁺ − n) and leaves the robot's own tracking
    # error at least what the epuck preset leaves it.
    default = preset("epuck")
    assert (
        scn.controller.W[0] - 2 * scn.controller.point_noise >= default.W[0] - 2 * default.point_noise - 1e-12
    )
    assert scn.controller.W[1] >= default.W[1]


def test_the_preset_numbers_would_not_do():
    """Without the [controller] overrides the file is either dishonest or refused."""
    data = raw(REAL)
    honest = load_scenario(REAL)
    cam = honest.camera
    assert cam is not None and cam.position_noise is not None and cam.heading_noise is not None

    # The bare preset: admissible, but its pose_noise is below the camera's declared noise.
    bare = {**data, "controller": {"preset": "epuck"}}
    plain = parse_scenario(bare, source=str(REAL))
    assert synthesize(plain.controller, plain.arena).admissible
    assert plain.controller.pose_noise[0] < cam.position_noise
    assert plain.controller.pose_noise[1] < cam.heading_noise

    # The preset's W and ε with the camera's pose_noise: fleet design refuses it.
    noisy = {**data, "controller": {"preset": "epuck", "pose_noise": list(honest.controller.pose_noise)}}
    refused = synthesize(parse_scenario(noisy, source=str(REAL)).controller, honest.arena)
    assert not refused.admissible
    assert any(f.startswith("pose_noise too large") for f in refused.failures), refused.failures

    # And the file's own W alone, with the preset's ε, is refused too (the reference lag).
    no_eps = {**data, "controller": {k: v for k, v in data["controller"].items() if k != "epsilon"}}
    lagging = synthesize(parse_scenario(no_eps, source=str(REAL)).controller, honest.arena)
    assert not lagging.admissible
    assert any(f.startswith("epsilon") for f in lagging.failures), lagging.failures


def test_the_twin_differs_only_in_name_and_links():
    real, twin = load_scenario(REAL), load_scenario(TWIN)
    assert real.name == "lab_three_robots" and twin.name == "lab_three_robots_emulated"
    as_twin = dataclasses.replace(
        real, name=twin.name, source=twin.source,
        robots=tuple(dataclasses.replace(r, link="emulator") for r in real.robots),
    )  # fmt: skip
    assert as_twin == twin
