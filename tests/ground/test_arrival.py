"""The order of arrival made to hold (ground.arrival): who waits for whom, where, and the lemma
it rests on, checked on the loader's own model of free space (docs/method.md §7, "The order of
arrival")."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fleet.running.scenes import (
    lane_crossing,
    mirrored_grid,
    pocket,
    random_scene,
    scene_to_toml,
    single_file,
)
from ground.arrival import Arrival, arrival
from ground.freespace import free_space_model
from ground.geometry import controlled_point
from ground.scenario import GOAL_MARGIN, PARKED_RADIUS, Scenario, load_scenario

FP = 0.13405
"""The epuck preset's footprint [m]."""
SLACK = PARKED_RADIUS
"""How far off its goal or wait point a robot parked or waiting may stand [m]."""
ROOT = Path(__file__).resolve().parents[2]


def _load(tmp_path: Path, scene: dict) -> Scenario:
    path = tmp_path / f"{scene['name']}.toml"
    path.write_text(scene_to_toml(scene))
    return load_scenario(path)


def _points(scn: Scenario) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    ell = scn.controller.lookahead
    starts = {r.id: controlled_point(r.start, ell) for r in scn.robots}
    goals = {r.id: np.asarray(r.goal, dtype=float) for r in scn.robots}
    return starts, goals


def test_a_pocket_is_filled_from_the_bottom(tmp_path) -> None:
    """Three goals down a dead-end pocket 0.30 m wide: the middle robot waits for the deepest, the
    mouth's for both, each outside the pocket, as far from every goal as two robots off their
    points need; the deepest waits for nobody; nobody is left without the lemma."""
    scn = _load(tmp_path, pocket(0.30, robots=3))
    arr = arrival(scn, FP, SLACK)
    assert {rid: g.waits_for for rid, g in arr.gates.items()} == {"r2": ("r1",), "r3": ("r1", "r2")}
    assert (arr.unordered, arr.unproven, arr.no_wait_point) == ((), (), ())
    _, goals = _points(scn)
    inner = 0.15  # the pocket's half width: its arms stand at x = ±0.15 m
    for rid, g in arr.gates.items():
        w = g.wait_point
        assert abs(w[0]) > inner + FP or w[1] > 0.45 + 2 * FP  # beside or above the pocket, not in it
        for other, q in goals.items():
            if other != rid:
                assert np.linalg.norm(w - q) >= 2 * FP + 2 * SLACK + GOAL_MARGIN - 1e-9
    assert arr.lines() == [
        f"r2 waits at ({arr.gates['r2'].wait_point[0]:.2f}, {arr.gates['r2'].wait_point[1]:.2f}) "
        "until r1 is past its goal",
        f"r3 waits at ({arr.gates['r3'].wait_point[0]:.2f}, {arr.gates['r3'].wait_point[1]:.2f}) "
        "until r1, r2 are past its goal",
    ]


def test_a_robot_is_past_once_beyond_the_goals_that_wall_its_way(tmp_path) -> None:
    """The deepest robot of the pocket is past the middle goal once below it, not above it: at
    its own goal it is past, at its start (outside the pocket) and at the mouth it is not."""
    scn = _load(tmp_path, pocket(0.30, robots=3))
    gate = arrival(scn, FP, SLACK).gates["r2"]
    starts, goals = _points(scn)
    assert gate.past(0, goals["r1"])
    assert not gate.past(0, starts["r1"])
    assert not gate.past(0, goals["r3"])  # the mouth: the middle goal still lies ahead


def _open_for_every_order(scn: Scenario, arr: Arrival, seed: int, orders: int) -> tuple[int, int]:
    """Park the robots one by one in random orders the gates allow (a robot parks only once
    every robot it waits for has parked), the rest waiting at their wait points, and count
    the times a robot not yet parked, for which the lemma holds, finds its way home shut."""
    rng = np.random.default_rng(seed)
    starts, goals = _points(scn)
    model = free_space_model(scn.arena, scn.obstacles, FP)
    reach = 2 * FP
    ids = [r.id for r in scn.robots]
    unsure = set(arr.unproven) | set(arr.unordered) | set(arr.no_wait_point)
    shut = checked = 0
    for _ in range(orders):
        parked: list[str] = []
        left = list(ids)
        while left:
            ready = [r for r in left if r not in arr.gates or set(arr.gates[r].waits_for) <= set(parked)]
            assert ready, "the gates left no robot free to park: a cycle of waits"
            nxt = ready[int(rng.integers(len(ready)))]
            for i in left:
                if i in unsure:
                    continue
                discs = [(goals[k], reach) for k in parked if np.linalg.norm(goals[k] - starts[i]) >= reach]
                discs += [(g.wait_point, reach + SLACK) for k, g in arr.gates.items() if k in left and k != i]
                legs = [(starts[i], goals[i])]
                if i in arr.gates:  # by its wait point
                    legs = [(starts[i], arr.gates[i].wait_point), (arr.gates[i].wait_point, goals[i])]
                shut += any(model.walled_in(a, b, discs) for a, b in legs)
                checked += 1
            parked.append(nxt)
            left.remove(nxt)
    return shut, checked


@pytest.mark.parametrize(
    "scene",
    [
        pocket(0.30, robots=3),
        pocket(0.36, robots=3, seed=1),
        mirrored_grid(4, 4),
        random_scene(3, n=15, min_separation=0.2782, duration=300.0, margin=0.15),
        single_file(4, "trains", width=0.34),
    ],
    ids=["pocket", "pocket-wide", "grid", "dense", "trains"],
)
def test_no_order_the_gates_allow_shuts_a_way_home(tmp_path, scene) -> None:
    """The lemma (B made to hold): whatever order the gates allow robots to park in, with the
    rest at their wait points, the way home of every robot the lemma covers stays open."""
    scn = _load(tmp_path, scene)
    arr = arrival(scn, FP, SLACK)
    shut, checked = _open_for_every_order(scn, arr, seed=7, orders=10)
    assert shut == 0 and checked >= 10 * len(scn.robots)


def test_without_the_gates_a_pocket_can_be_shut(tmp_path) -> None:
    """The same count with no gate (any order of parking) finds the pocket shut: the check
    above can fail."""
    scn = _load(tmp_path, pocket(0.30, robots=3))
    assert _open_for_every_order(scn, Arrival({}), seed=7, orders=10)[0] > 0


def test_a_cycle_of_waits_gets_no_gate(tmp_path) -> None:
    """Two robots in a corridor a single robot wide, each goal on the other's way: each must be
    home before the other parks, which no order does; both are named, and neither waits."""
    scene = lane_crossing()
    arr = arrival(_load(tmp_path, scene), FP, SLACK)
    assert set(arr.unordered) == {"r1", "r2"} and arr.gates == {}
    assert "r1, r2: their waits form a cycle; no order of arrival does it" in arr.lines()


_GATES = """
import json, sys
from ground.arrival import arrival
from ground.scenario import load_scenario
arr = arrival(load_scenario(sys.argv[1]), float(sys.argv[2]))
print(json.dumps({r: [list(g.waits_for), [float(v).hex() for v in g.wait_point],
                      [int(b.sum()) for b in g.beyond]] for r, g in arr.gates.items()}))
"""


def test_every_agent_works_out_the_same_gates(tmp_path) -> None:
    """Worked out in two processes with different hash seeds, as two agents would, the gates are
    the same to the bit: whom each robot waits for, its wait point and the cells past."""
    scene = random_scene(3, n=15, min_separation=0.2782, duration=300.0, margin=0.15)
    path = tmp_path / "dense.toml"
    path.write_text(scene_to_toml(scene))
    outs = []
    for seed in ("1", "2"):
        res = subprocess.run(
            [sys.executable, "-c", _GATES, str(path), str(FP)], cwd=ROOT, capture_output=True, text=True,
            timeout=120, env={**os.environ, "PYTHONHASHSEED": seed},
        )  # fmt: skip
        assert res.returncode == 0, res.stderr
        outs.append(json.loads(res.stdout))
    assert outs[0] == outs[1] and outs[0]
