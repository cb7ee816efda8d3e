"""Rerun logging of the fleet (the supervisor is the only logger).

Entity paths (2-D, world frame, metres):

* ``world/arena``, ``world/obstacles/<k>`` — static; ``world/goals`` from
  step 0, logged again when an agent takes a new goal (with an event);
* ``world/robots/<id>/true`` (centre, body radius), ``.../heading``,
  ``.../measured``, ``.../footprint`` (r_i around the current reference),
  ``.../tube`` (ρ around the current reference: where the robot must be),
  ``.../reference`` (the committed ỹ), ``.../plan`` (nominal x̂);
* ``separation/true/<a>-<b>`` and ``separation/true/collision`` (2 body radii),
  ``separation/reference/<a>-<b>`` and ``separation/reference/required``
  (paper Fig. 7 and 9).  Above PAIR_SERIES_MAX robots, one series per robot
  instead of one per pair: ``separation/true/nearest`` and
  ``separation/reference/nearest``, each robot's distance to its nearest
  other robot (or appended reference point), named by robot id;
* ``solve_ms/<id>``; ``events`` (fallbacks, tube exits, stale plans, rejections).

Timelines: ``step`` (sequence) and ``sim_time`` (duration).
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Mapping
from itertools import combinations
from pathlib import Path
from typing import Any

import numpy as np

from ground.scenario import Scenario
from ground.wire import Plan, Pose
from supervisor.judge import SOLVED
from supervisor.trace import outlines

PALETTE = [
    (31, 119, 180), (44, 160, 44), (214, 39, 40), (148, 103, 189), (140, 86, 75),
    (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207),
]  # fmt: skip
"""Robot colours (RGB), in scenario order and cycled: one colour per robot on every entity of it."""


PAIR_SERIES_MAX = 8
"""Most robots whose separations are logged pair by pair [robots]: 28 series.  Beyond, each
robot's nearest distance (n series in one entity): the pair series grow as n², each costs a
``send_columns`` call per flush, and no one reads a hundred lines."""
FLUSH_ROBOTS = 8
"""The recording is flushed every 0.25 s per this many robots: each entity costs a
``send_columns`` call per flush, whatever its number of rows, so larger fleets flush less
often (a live viewer lags by at most the flush period)."""


def robot_colour(rank: int) -> tuple[int, int, int]:
    """The colour of the robot at ``rank`` in the scenario."""
    return PALETTE[rank % len(PALETTE)]


class Recorder:
    """Writes ``DIR/recording.rrd``; :meth:`close` flushes it completely."""

    def __init__(self, path: Path, scn: Scenario, viewer: bool = False):
        os.environ.setdefault("RERUN_ANALYTICS", "0")
        import rerun as rr

        self.rr = rr
        self.ids = [r.id for r in scn.robots]
        p = scn.controller
        self.radius = p.robot_radius
        """Body radius [m]."""
        self.body = p.robot_radius + p.lookahead
        """The body disc around the controlled point [m]: a footprint r_i is this plus ρ_i."""
        self.rec = rr.RecordingStream("epuck-fleet", recording_id=scn.name)
        if viewer:
            # The viewer listens on 127.0.0.1; the file is written as well.
            rr.spawn(connect=False)
            self.rec.set_sinks(rr.FileSink(str(path)), rr.GrpcSink())
        else:
            self.rec.save(str(path))
        xmin, xmax, ymin, ymax = scn.arena
        log = self.rec.log
        box = [[xmin, ymin], [xmax, ymin], [xmax, ymax], [xmin, ymax], [xmin, ymin]]
        log("world/arena", rr.LineStrips2D([box]), static=True)
        for k, ol in enumerate(outlines(scn.obstacles)):
            log(f"world/obstacles/{k}", rr.LineStrips2D([np.vstack([ol, ol[:1]])], colors=[[120, 120, 120]]),
                static=True)  # fmt: skip
        self.colour = {rid: robot_colour(i) for i, rid in enumerate(self.ids)}
        self.pending: dict[str, tuple[Any, list[tuple[int, float, dict[str, Any]]]]] = {}
        self.pending_rows = 0
        self.last_flush = time.monotonic()
        self._static_styles()
        self.rec.send_blueprint(self._blueprint())
        self.goals = {r.id: tuple(r.goal) for r in scn.robots}
        self._time(0, 0.0)
        self._log_goals()
        self.pairs = list(combinations(self.ids, 2)) if len(self.ids) <= PAIR_SERIES_MAX else []
        self.flush_period = 0.25 * max(1.0, len(self.ids) / FLUSH_ROBOTS)
        """Wall time between flushes [s]: what a live viewer lags by at most."""

    def _time(self, step: int, Ts: float) -> None:
        self.rec.set_time("step", sequence=step)
        self.rec.set_time("sim_time", duration=step * Ts)

    def _static_styles(self) -> None:
        """What does not change per step is logged once: colours, radii, labels."""
        rr, log = self.rr, self.rec.log
        for rid in self.ids:
            c = [self.colour[rid]]
            base = f"world/robots/{rid}"
            log(
                f"{base}/true",
                rr.Points2D.from_fields(radii=self.radius, labels=[rid], colors=c),
                static=True,
            )
            log(f"{base}/heading", rr.Arrows2D.from_fields(colors=c), static=True)
            log(f"{base}/measured", rr.Points2D.from_fields(radii=0.005), static=True)
            log(f"{base}/footprint", rr.Ellipses2D.from_fields(colors=c), static=True)
            log(f"{base}/tube", rr.Ellipses2D.from_fields(colors=c), static=True)
            log(f"{base}/reference", rr.LineStrips2D.from_fields(colors=c), static=True)
            log(f"{base}/plan", rr.LineStrips2D.from_fields(colors=c), static=True)
            log(f"solve_ms/{rid}", rr.SeriesLines(colors=c), static=True)
        if len(self.ids) > PAIR_SERIES_MAX:
            cs = [self.colour[r] for r in self.ids]
            for kind in ("true", "reference"):
                log(f"separation/{kind}/nearest", rr.SeriesLines(colors=cs, names=self.ids), static=True)

    def _row(self, entity: str, archetype: Any, step: int, Ts: float, **fields: Any) -> None:
        """Queue one step's value of ``entity``; :meth:`flush` sends each entity's rows as columns."""
        rows = self.pending.setdefault(entity, (archetype, []))[1]
        rows.append((step, step * Ts, fields))
        self.pending_rows += 1

    def flush(self) -> None:
        """Send the queued rows: one ``send_columns`` per entity instead of one ``log`` per value
        (a log call per value would cost more than the rest of the supervisor's work)."""
        rr = self.rr
        indexes: dict[tuple[tuple[int, float], ...], list[Any]] = {}
        """Time columns by (step, time) rows: most entities share them, so each is made once."""
        for entity, (archetype, rows) in self.pending.items():
            at = tuple((r[0], r[1]) for r in rows)
            index = indexes.get(at)
            if index is None:
                index = indexes[at] = [
                    rr.TimeColumn("step", sequence=[r[0] for r in rows]),
                    rr.TimeColumn("sim_time", duration=[r[1] for r in rows]),
                ]
            cols = {k: _column([v for r in rows for v in r[2][k]]) for k in rows[0][2]}
            rr.send_columns(
                entity,
                indexes=index,
                columns=archetype.columns(**cols).partition(
                    lengths=[len(next(iter(r[2].values()))) for r in rows]
                ),
                recording=self.rec,
            )
        self.pending.clear()
        self.pending_rows = 0

    def flush_if_due(self, period: float | None = None) -> None:
        """Flush when the oldest queued row is ``period`` [s] of wall time old (live
        viewing; default :attr:`flush_period`)."""
        period = self.flush_period if period is None else period
        now = time.monotonic()
        if not self.pending_rows:
            self.last_flush = now
        elif now - self.last_flush >= period:
            self.flush()
            self.last_flush = now

    def truth(
        self, step: int, Ts: float, truth: Mapping[str, Pose], measured: Mapping[str, Pose | None]
    ) -> None:
        """Queue one step of ground truth and camera poses (sent by :meth:`flush`)."""
        rr, row = self.rr, self._row
        for rid in self.ids:
            p = truth[rid]
            row(f"world/robots/{rid}/true", rr.Points2D, step, Ts, positions=[[p.x, p.y]])
            head = [[0.06 * math.cos(p.theta), 0.06 * math.sin(p.theta)]]
            row(f"world/robots/{rid}/heading", rr.Arrows2D, step, Ts, origins=[[p.x, p.y]], vectors=head)
            m = measured.get(rid)
            if m is not None:
                row(f"world/robots/{rid}/measured", rr.Points2D, step, Ts, positions=[[m.x, m.y]])
        for a, b in self.pairs:
            d = math.hypot(truth[a].x - truth[b].x, truth[a].y - truth[b].y)
            row(f"separation/true/{a}-{b}", rr.Scalars, step, Ts, scalars=[d])
        if not self.pairs:
            pts = np.array([[truth[r].x, truth[r].y] for r in self.ids])
            row("separation/true/nearest", rr.Scalars, step, Ts, scalars=nearest(pts))
        row("separation/true/collision", rr.Scalars, step, Ts, scalars=[2.0 * self.radius])

    def plans(self, step: int, Ts: float, plans: dict[str, Plan]) -> None:
        """Queue one step of plans (sent by :meth:`flush`); events are logged at once."""
        rr, row = self.rr, self._row
        k = step + 1  # committed[0] is the reference for the next sample
        for rid, pl in plans.items():
            y = pl.committed[0]
            base = f"world/robots/{rid}"
            row(f"{base}/footprint", rr.Ellipses2D, k, Ts, centers=[y], half_sizes=[[pl.footprint] * 2])
            rho = pl.footprint - self.body
            row(f"{base}/tube", rr.Ellipses2D, k, Ts, centers=[y], half_sizes=[[rho, rho]])
            row(f"{base}/reference", rr.LineStrips2D, k, Ts, strips=[pl.committed])
            row(f"{base}/plan", rr.LineStrips2D, k, Ts, strips=[pl.nominal])
            row(f"solve_ms/{rid}", rr.Scalars, k, Ts, scalars=[pl.solve_time * 1e3])
        self._time(k, Ts)
        for rid, pl in plans.items():
            if pl.status != SOLVED:
                self.event(f"{rid}: fallback at step {step} ({pl.status})", "WARN")
            if not pl.tube_ok:
                self.event(f"{rid}: tube exit at step {step}", "WARN")
        changed = [r for r in plans if tuple(plans[r].goal.tolist()) != self.goals[r]]
        for rid in changed:
            self.goals[rid] = tuple(plans[rid].goal.tolist())
            self.event(f"{rid}: new goal ({self.goals[rid][0]:.3f}, {self.goals[rid][1]:.3f}) at step {step}")
        if changed:
            self._log_goals()
        for a, b in self.pairs:
            if a not in plans or b not in plans:
                continue
            d = float(np.linalg.norm(plans[a].committed[-1] - plans[b].committed[-1]))
            row(f"separation/reference/{a}-{b}", rr.Scalars, k, Ts, scalars=[d])
        if not self.pairs and len(plans) == len(self.ids):  # one row holds every robot's series
            ends = np.array([plans[r].committed[-1] for r in self.ids])
            row("separation/reference/nearest", rr.Scalars, k, Ts, scalars=nearest(ends))
        if plans:
            required = 2.0 * max(pl.footprint for pl in plans.values())
            row("separation/reference/required", rr.Scalars, k, Ts, scalars=[required])

    def _blueprint(self) -> Any:
        """The layout: the arena large on the left; separations, solve times and events on the right."""
        import rerun.blueprint as rrb

        return rrb.Blueprint(
            rrb.Horizontal(
                rrb.Spatial2DView(origin="world", name="arena"),
                rrb.Vertical(
                    rrb.TimeSeriesView(origin="separation/true", name="true distances vs collision"),
                    rrb.TimeSeriesView(
                        origin="separation/reference", name="reference separation vs required"
                    ),
                    rrb.TimeSeriesView(origin="solve_ms", name="solve time [ms]"),
                    rrb.TextLogView(origin="events", name="events"),
                ),
                column_shares=[3, 2],
            ),
            collapse_panels=True,
        )

    def _log_goals(self) -> None:
        pts = [self.goals[r] for r in self.ids]
        self.rec.log("world/goals", self.rr.Points2D(pts, labels=self.ids, radii=0.01))

    def event(self, text: str, level: str = "INFO") -> None:
        """Log ``text`` to the recording's event log (``events``) at ``level`` (e.g. ``INFO``,
        ``WARN``), at once rather than queued for :meth:`flush`."""
        self.rec.log("events", self.rr.TextLog(text, level=level))

    def close(self) -> None:
        """Flush the queued rows and the recording, and disconnect it."""
        self.flush()
        self.rec.flush()
        self.rec.disconnect()


def _column(values: list[Any]) -> Any:
    """One field's values over the rows of a flush, as ``send_columns`` takes them fastest:
    line strips of one shape (a committed reference or a nominal plan, every step) as one
    (rows, points, 2) array, which rerun converts at once instead of strip by strip."""
    first = values[0] if values else None
    if isinstance(first, np.ndarray) and first.ndim == 2:
        shape = first.shape
        if all(isinstance(v, np.ndarray) and v.shape == shape for v in values):
            return np.stack(values)
    return values


def nearest(points: np.ndarray) -> list[float]:
    """Each point's distance [m] to the nearest other one, for points (n, 2) [m], n ≥ 2."""
    d = np.linalg.norm(points[:, None, :] - points[None, :, :], axis=-1)
    np.fill_diagonal(d, np.inf)
    return [float(v) for v in d.min(axis=1)]


def read_events(rrd: Path) -> list[tuple[float, str]]:
    """The events a recording holds (its ``/events`` text log): (log time [s, time.time], text),
    in order."""
    from rerun.chunk import RrdReader

    rows = []
    for ch in RrdReader(rrd).stream():
        if str(ch.entity_path) != "/events":
            continue
        batch = ch.to_record_batch()
        times_ns = batch.column("log_time").cast("int64").to_pylist()
        for when, texts in zip(times_ns, batch.column("TextLog:text").to_pylist(), strict=True):
            rows += [(when * 1e-9, text) for text in texts]
    return sorted(rows)
