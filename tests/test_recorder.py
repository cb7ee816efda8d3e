"""The supervisor's Rerun recording of a large fleet: per-robot nearest distances, not pairs."""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from fleet.scenario import load_scenario
from fleet.wire import Plan, Pose
from supervisor.recorder import PAIR_SERIES_MAX, Recorder

ROOT = Path(__file__).resolve().parent.parent


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
    rec = Recorder(tmp_path / "r.rrd", scn, footprint=0.1, rho=0.01, radius=0.037)
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
