"""Run traces for reports: what happened, as arrays, in ``DIR/trace.npz``.

Both ``fleet simulate`` (:func:`from_simulation`) and the supervisor of ``fleet run``
write the same file, so ``fleet report DIR`` works on either.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


@dataclass
class Trace:
    """Arrays over robots R and samples T (one sample per step, the initial state included)."""

    name: str
    ids: list[str]
    Ts: float
    """Sampling period [s]."""
    poses: Array
    """True axle-centre poses (R, T, 3) [m, m, rad]."""
    refs: Array
    """Committed reference for each sample's time (R, T, 2) [m] (NaN where none yet)."""
    goals: Array
    """Goals (R, 2) [m]."""
    footprint: float
    """Footprint radius r_i [m] (reference separation needs 2 r_i)."""
    robot_radius: float
    """Body radius [m] (true centres must stay 2 of them apart)."""
    arena: tuple[float, float, float, float]
    obstacles: list[Array]
    """Obstacle outlines, each (k, 2) [m]."""

    def save(self, path: Path) -> None:
        """Write the trace to ``path`` as a compressed ``.npz``: the arrays, each obstacle's
        outline, and the rest as JSON (``meta``)."""
        meta = {
            "name": self.name, "ids": self.ids, "Ts": self.Ts, "footprint": self.footprint,
            "robot_radius": self.robot_radius, "arena": list(self.arena), "n_obstacles": len(self.obstacles),
        }  # fmt: skip
        arrays: dict[str, Any] = {f"obstacle_{i}": o for i, o in enumerate(self.obstacles)}
        arrays.update(meta=json.dumps(meta), poses=self.poses, refs=self.refs, goals=self.goals)
        np.savez_compressed(path, **arrays)

    @staticmethod
    def load(path: Path) -> Trace:
        """The trace that :meth:`save` wrote to ``path``."""
        with np.load(path) as z:
            meta = json.loads(str(z["meta"]))
            obstacles = [z[f"obstacle_{i}"] for i in range(meta["n_obstacles"])]
            return Trace(
                name=meta["name"], ids=meta["ids"], Ts=meta["Ts"], poses=z["poses"], refs=z["refs"],
                goals=z["goals"], footprint=meta["footprint"], robot_radius=meta["robot_radius"],
                arena=tuple(meta["arena"]), obstacles=obstacles,
            )  # fmt: skip


def outlines(obstacles: Any, sides: int = 96) -> list[Array]:
    """Drawable outlines (k, 2) of scenario obstacles: circles as polygons, polygons as given."""
    out = []
    for ob in obstacles:
        if hasattr(ob, "radius"):
            ang = np.linspace(0.0, 2.0 * np.pi, sides, endpoint=False)
            out.append(
                np.column_stack(
                    [ob.center[0] + ob.radius * np.cos(ang), ob.center[1] + ob.radius * np.sin(ang)]
                )
            )
        else:
            out.append(np.asarray(ob.vertices, dtype=float))
    return out


def from_simulation(result: Any, scenario: Any) -> Trace:
    """Build a trace from :func:`fleet.running.simulate.run`'s result."""
    ids = list(result.traces)
    poses = np.array([np.array(result.traces[r].pose) for r in ids])
    T = poses.shape[1]
    refs = np.full((len(ids), T, 2), np.nan)
    N = result.design.params.horizon
    for i, r in enumerate(ids):
        tr = result.traces[r]
        # The initial reference stays put at the start for N steps; committed_last[k]
        # (ỹ_{k+N}, appended at step k) is the reference for sample k + N.
        refs[i, : min(N, T)] = tr.point[0]
        cl = np.array(tr.committed_last).reshape(-1, 2)[: max(0, T - N)]
        refs[i, N : N + len(cl)] = cl
    goals = np.array([result.controllers[r].goal for r in ids])
    return Trace(
        name=scenario.name, ids=ids, Ts=result.design.params.Ts, poses=poses, refs=refs, goals=goals,
        footprint=result.design.footprint, robot_radius=result.design.params.robot_radius,
        arena=tuple(scenario.arena), obstacles=outlines(scenario.obstacles),
    )  # fmt: skip
