"""The liveness bench's scene families (``fleet/running/scenes.py``): every drawn scene is one the loader
and the tube design accept, each family has the shape its name promises, and the layout check
names the order the layouts that force one force."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fleet.running.scenes import (
    EPUCK_FOOTPRINT,
    LAYOUT_FAMILIES,
    MIN_GOAL_SPACING,
    SCALE_FAMILIES,
    concentric_rings,
    hard_scene,
    pocket,
    single_file,
)
from ground.geometry import controlled_point
from ground.params import preset
from ground.scenario import forced_order, parse_scenario

ROOT = Path(__file__).resolve().parents[2]
ELL = preset("epuck").lookahead


def _points(scene: dict) -> list[np.ndarray]:
    return [controlled_point(np.array(r["start"], dtype=float), ELL) for r in scene["robots"]]


def _goals(scene: dict) -> list[np.ndarray]:
    return [np.array(r["goal"], dtype=float) for r in scene["robots"]]


def test_every_drawn_layout_scene_is_accepted_and_every_family_is_drawn():
    from agent.tube import validated_design

    seen = set()
    for seed in range(25):
        data = hard_scene(seed, LAYOUT_FAMILIES)
        seen.add(LAYOUT_FAMILIES[seed % len(LAYOUT_FAMILIES)])
        validated_design(parse_scenario(data))  # raises, naming the field, if refused
        goals = _goals(data)
        for i, g in enumerate(goals):  # the closest spacing the loader allows, or wider
            for h in goals[i + 1 :]:
                assert np.linalg.norm(g - h) >= MIN_GOAL_SPACING - 1e-9, data["name"]
    assert seen == set(LAYOUT_FAMILIES)


def test_the_scale_families_are_fleets_of_a_hundred_the_loader_accepts():
    """Over the old cap of 64 robots a tick and a digest carried: the loader takes 100, at the
    closest legal goal spacing or wider, and the tube design accepts the scene."""
    from agent.tube import validated_design
    from ground.wire import MAX_ROBOTS

    for seed, family in enumerate(SCALE_FAMILIES):
        data = hard_scene(seed, SCALE_FAMILIES)
        scn = parse_scenario(data)
        validated_design(scn)
        assert len(scn.robots) == 100 < MAX_ROBOTS
        assert data["name"] == f"hard_{seed}_{family.removesuffix('100')}_100"
        goals = np.array(_goals(data))
        d = np.hypot(*(goals[:, None, :] - goals[None, :, :]).transpose(2, 0, 1))
        assert d[np.triu_indices(100, 1)].min() >= MIN_GOAL_SPACING - 1e-9
    side = np.diff(parse_scenario(hard_scene(1, SCALE_FAMILIES)).arena)[::2]
    assert np.allclose(side, 6.0)  # the grid permutation: a 6 m × 6 m arena


def test_a_single_file_shift_sends_each_robot_to_the_next_start_in_a_lane_too_narrow_to_pass():
    scene = single_file(5, "shift", width=0.32)
    pts, goals = _points(scene), _goals(scene)
    for k in range(4):
        assert np.allclose(goals[k], pts[k + 1], atol=1e-6)
    # The lane's walls leave less than two bodies side by side.
    tops = [o["polygon"] for o in scene["obstacles"]]
    ys = sorted({y for poly in tops for _, y in poly})
    lane = min(y for y in ys if y > 0) - max(y for y in ys if y < 0)
    assert 2 * EPUCK_FOOTPRINT < lane < 4 * EPUCK_FOOTPRINT
    with pytest.raises(ValueError, match="single file"):
        single_file(3, "shift", width=0.6)


def test_a_closed_track_sends_each_robot_to_the_next_start_round_the_block():
    scene = single_file(6, "cycle", width=0.34)
    pts, goals = _points(scene), _goals(scene)
    assert all(np.allclose(goals[k], pts[(k + 1) % 6], atol=1e-6) for k in range(6))


def test_concentric_rings_turn_opposite_ways():
    scene = concentric_rings(2)
    pts, goals = _points(scene), _goals(scene)
    turn = [float(p[0] * (g - p)[1] - p[1] * (g - p)[0]) for p, g in zip(pts, goals, strict=True)]
    radii = [float(np.linalg.norm(p)) for p in pts]
    inner = [t for t, r in zip(turn, radii, strict=True) if r < min(radii) + 0.01]
    outer = [t for t, r in zip(turn, radii, strict=True) if r > max(radii) - 0.01]
    assert inner and outer and all(t > 0 for t in inner) and all(t < 0 for t in outer)


def test_the_layout_check_names_the_order_a_filled_pocket_forces():
    scn = parse_scenario(pocket(0.30, depth=3 * MIN_GOAL_SPACING + 0.2, robots=3))
    order = forced_order(scn, EPUCK_FOOTPRINT)
    # The deepest goal's robot must get past the two goals above it: it is named.
    assert "r1" in order and set(order["r1"]["alone"]) >= {"r2"}, order


def test_liveness_bench_runs_the_layout_families_and_refuses_an_unknown_one(tmp_path):
    env = {**os.environ, "OMP_NUM_THREADS": "1", "RERUN_ANALYTICS": "0"}
    out = subprocess.run(
        [sys.executable, "-m", "fleet.cli", "bench", "--liveness", "1", "--families", "file", "--jobs", "1",
         "--seed", "3", "--out", str(tmp_path)],
        capture_output=True, text=True, timeout=600, cwd=ROOT, env=env,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr[-2000:]
    assert "t/floor p50" in out.stdout and "ms/robot-step" in out.stdout, out.stdout
    assert "\nfile " in out.stdout and "alone p50" in out.stdout, out.stdout
    row = json.loads((tmp_path / "liveness.json").read_text())["scenes"][0]
    assert row["family"] == "file" and row["name"].startswith("hard_3_file_")
    assert len(row["alone"]) == len(row["path_efficiency"]) and min(row["alone"]) >= 1.0 - 1e-9, row
    # Where the path goes: its parts by the navigator's mode add up to at least the shortest
    # ways alone of the same robots (no path is shorter, to the goal tolerance).
    assert "make way" in out.stdout and "own / alone" in out.stdout, out.stdout
    ways = row["ways"]
    path = sum(ways[k] for k in ("own", "make way", "escape", "other"))
    assert ways["alone"] > 0 and path >= 0.98 * ways["alone"], ways
    # Steps without room to make way are steps making way: never more of them.
    assert "no room" in out.stdout and 0 <= row["no_room"] <= row["making_way"], row
    bad = subprocess.run(
        [sys.executable, "-m", "fleet.cli", "bench", "--liveness", "1", "--families", "hallway"],
        capture_output=True, text=True, timeout=120, cwd=ROOT, env=env,
    )  # fmt: skip
    assert bad.returncode == 2
    assert bad.stderr.strip().splitlines() == [
        "fleet: error: --families: unknown family 'hallway' (families: dense, ring, grid, swap, "
        "corridor, gap, obstacles, pocket, file, rooms, rings, cluttered, circle100, permutation100, "
        "cluttered100)"
    ]


def test_the_floor_of_path_efficiency_is_the_straight_line_in_the_open_and_more_round_a_pocket(tmp_path):
    """``fleet bench --liveness-floor`` runs nothing and prints, per family, each robot's shortest
    way alone over its straight line: exactly 1 for swaps in an empty arena, more for robots
    whose goal is at the bottom of a pocket whose mouth faces away (the way goes round an arm),
    and never under 1."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "RERUN_ANALYTICS": "0"}
    out = subprocess.run(
        [sys.executable, "-m", "fleet.cli", "bench", "--liveness", "4", "--liveness-floor", "--families",
         "swap,pocket", "--jobs", "1", "--out", str(tmp_path)],
        capture_output=True, text=True, timeout=600, cwd=ROOT, env=env,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr[-2000:]
    assert "alone p50" in out.stdout and "t/floor" not in out.stdout, out.stdout
    rows = json.loads((tmp_path / "liveness.json").read_text())["scenes"]
    swap = [a for r in rows if r["family"] == "swap" for a in r["alone"]]
    pocket_ = [a for r in rows if r["family"] == "pocket" for a in r["alone"]]
    assert swap and max(abs(a - 1.0) for a in swap) < 1e-9, swap
    assert pocket_ and min(pocket_) >= 1.0 - 1e-9 and max(pocket_) > 1.2, pocket_
    assert all("steps" not in r for r in rows)  # nothing was run
