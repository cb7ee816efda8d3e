"""The supervisor's Rerun recording of a large fleet: per-robot nearest distances, not pairs."""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from ground.scenario import load_scenario
from ground.wire import Plan, Pose
from supervisor.recorder import PAIR_SERIES_MAX, Recorder

ROOT = Path(__file__).resolve().parents[2]


def _series(rrd: Path) -> dict[str, list[tuple[int, list[float]]]]:
    """entity path → [(step, scalars)] of every Scalars row in the recording."""
    from rerun.chunk import RrdReader

    out: dict[str, list[tuple[int, list[float]]]] = {}
    for ch in RrdReader(rrd).stream():
        batch = ch.to_record_batch()
        if "Scalars:scalars" not in batch.schema.names or "step" not in batch.schema.names:
            continue
        rows = zip(batch.column("step").to_pylist(), batch.column("Scalars:scalars").to_pylist(), strict=True)
        out.setdefault(str(ch.entity_path), []).extend((s, v) for s, v in rows if v is not None)
    return out


def test_a_fleet_above_the_pair_limit_logs_each_robots_nearest_distance(tmp_path):
    os.environ["RERUN_ANALYTICS"] = "0"
    scn = load_scenario(ROOT / "scenarios" / "swap_16.toml")
    ids = [r.id for r in scn.robots]
    assert len(ids) > PAIR_SERIES_MAX
    rng = np.random.default_rng(4)
    rec = Recorder(tmp_path / "r.rrd", scn)
    truth_at, ends_at = {}, {}
    for k in range(3):
        pts = rng.uniform(-0.8, 0.8, (len(ids), 2))
        ends = rng.uniform(-0.8, 0.8, (len(ids), 2))
        truth = {
            r: Pose(robot=r, seq=k, t=0.1 * k, x=float(p[0]), y=float(p[1]), theta=0.0)
            for r, p in zip(ids, pts, strict=True)
        }
        plans = {
            r: Plan(
                robot=r,
                step=k,
                t0=0.1 * (k + 1),
                Ts=0.1,
                committed=np.vstack([e, e]),
                nominal=np.vstack([e, e, e]),
                footprint=0.1,
                priority=0,
                rank=i,
                phase=0,
                target=e,
                goal=e,
                status="PROXQP_SOLVED",
                solve_time=1e-4,
                tube_ok=True,
            )
            for i, (r, e) in enumerate(zip(ids, ends, strict=True))
        }
        rec.truth(k, 0.1, truth, truth)
        rec.plans(k, 0.1, plans)
        truth_at[k], ends_at[k + 1] = pts, ends  # plans are logged at step k + 1
    rec.close()
    series = _series(tmp_path / "r.rrd")
    assert not [e for e in series if e.startswith("/separation/true/r")], "no per-pair series above the limit"

    def brute(p: np.ndarray) -> list[float]:
        return [min(math.dist(p[i], p[j]) for j in range(len(p)) if j != i) for i in range(len(p))]

    for entity, expected in (
        ("/separation/true/nearest", truth_at),
        ("/separation/reference/nearest", ends_at),
    ):
        rows = dict(series[entity])
        assert set(rows) == set(expected), entity
        for step, pts in expected.items():
            assert np.allclose(rows[step], brute(pts), atol=1e-6), (entity, step)


def _rows(rrd: Path, column: str) -> dict[str, dict[int, Any]]:
    """entity path → {step: value of ``column``} of every row that has it."""
    from rerun.chunk import RrdReader

    out: dict[str, dict[int, Any]] = {}
    for ch in RrdReader(rrd).stream():
        batch = ch.to_record_batch()
        if column not in batch.schema.names or "step" not in batch.schema.names:
            continue
        rows = zip(batch.column("step").to_pylist(), batch.column(column).to_pylist(), strict=True)
        out.setdefault(str(ch.entity_path), {}).update((s, v) for s, v in rows if v is not None)
    return out


def test_each_robot_s_plans_and_poses_land_at_their_own_steps(tmp_path):
    """Rows are sent a flush at a time, entities sharing time columns and strips of one shape
    sent as one array: every robot's reference, plan and true position is still at its step,
    also for a robot whose plan of a step is missing, and for a plan of another length."""
    os.environ["RERUN_ANALYTICS"] = "0"
    scn = load_scenario(ROOT / "scenarios" / "paper_three_robots.toml")
    ids = [r.id for r in scn.robots]
    rng = np.random.default_rng(7)
    rec = Recorder(tmp_path / "r.rrd", scn)
    sent: dict[tuple[str, str], dict[int, np.ndarray]] = {}
    for k in range(4):
        truth = {r: Pose(robot=r, seq=k, t=0.1 * k, x=float(x), y=float(y), theta=0.0)
                 for r, (x, y) in zip(ids, rng.uniform(-1, 1, (len(ids), 2)), strict=True)}  # fmt: skip
        plans = {}
        for i, r in enumerate(ids):
            sent.setdefault((r, "true"), {})[k] = np.array([[truth[r].x, truth[r].y]])
            if (k, r) == (1, ids[2]):
                continue  # no plan of this robot at this step
            nominal = np.zeros((0, 2)) if (k, r) == (2, ids[1]) else rng.uniform(-1, 1, (6, 2))
            plans[r] = Plan(
                robot=r, step=k, t0=0.1 * (k + 1), Ts=0.1, committed=rng.uniform(-1, 1, (5, 2)),
                nominal=nominal, footprint=0.1, priority=0, rank=i, phase=0, target=np.zeros(2),
                goal=np.array(scn.robots[i].goal, float), status="PROXQP_SOLVED", solve_time=1e-4,
                tube_ok=True,
            )  # fmt: skip
            sent.setdefault((r, "reference"), {})[k + 1] = plans[r].committed
            sent.setdefault((r, "plan"), {})[k + 1] = nominal
        rec.truth(k, 0.1, truth, truth)
        rec.plans(k, 0.1, plans)
        if k == 1:
            rec.flush()
    rec.close()
    strips = _rows(tmp_path / "r.rrd", "LineStrips2D:strips")
    points = _rows(tmp_path / "r.rrd", "Points2D:positions")
    for (r, part), by_step in sent.items():
        got = (points if part == "true" else strips)[f"/world/robots/{r}/{part}"]
        assert set(got) == set(by_step), (r, part)
        for k, want in by_step.items():
            value = np.array(got[k] if part == "true" else got[k][0], float).reshape(-1, 2)
            assert np.allclose(value, want), (r, part, k)
