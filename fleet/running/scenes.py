"""Programmatic scenes: scenario dicts accepted by :func:`ground.scenario.parse_scenario`.

* :func:`antipodal_swap` — n robots on a circle, each crossing to the antipodal point.
* :func:`random_scene` — seeded random starts and goals with a minimum separation.
* :func:`ring`, :func:`mirrored_grid`, :func:`corridor_swap`, :func:`gap_swap`,
  :func:`goals_by_obstacles` — the scenes that stall a crowd: goals at the minimum legal
  spacing, odd rings, narrow passages.  :func:`hard_scene` draws one of them from a seed
  (``fleet bench --liveness``).
* :func:`scene_to_toml` — render such a dict as a scenario file.

The scenes use the default (``epuck``) controller; their defaults are chosen so
that :func:`ground.scenario.check_geometry` accepts them with that preset's
footprint radius (≈ 0.134 m).
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from ground.geometry import axle_centre
from ground.params import preset


def _clean(x: float) -> float:
    """Round to 1 nm / 1 nrad and drop negative zeros (tidy TOML output)."""
    return round(float(x), 9) + 0.0


COMPACT_CONTROLLER: dict[str, float] = {"delta": 0.005, "lookahead": 0.03, "v_max": 0.068, "epsilon": 0.005}
"""``[controller]`` overrides of the 16-robot swap: a tighter tube (footprint 0.113 m
instead of 0.134 m) so that 16 goals fit on a 0.8 m ring in a 2 m arena with room
to pass between parked robots.  Top speed drops from 0.055 to 0.05 m/s per axis."""


def antipodal_swap(
    n: int,
    radius: float = 0.8,
    duration: float | None = None,
    seed: int = 0,
    *,
    arena: tuple[float, float, float, float] = (-1.0, 1.0, -1.0, 1.0),
    angle_offset: float = 0.0,
) -> dict[str, Any]:
    """n robots evenly spaced on a circle of ``radius`` [m] about the arena centre.

    Robot k (id ``r{k+1}``) starts at angle ``angle_offset + 2πk/n`` [rad],
    heading at its goal, the antipodal point (goal = −start position about the
    arena centre).  ``duration`` defaults to 15·n s; ``seed`` goes to
    ``[simulation] seed``.

    With the epuck preset (footprint ≈ 0.134 m, look-ahead 0.04 m) the default
    radius 0.8 m passes :func:`~ground.scenario.check_geometry` up to n = 16:
    the start controlled points lie on a 0.76 m circle, 2·0.76·sin(π/16) ≈
    0.297 m apart (≥ 0.268 m), and the goals are 0.2 m from the walls."""
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    if radius <= 0:
        raise ValueError(f"radius must be > 0, got {radius}")
    cx = 0.5 * (arena[0] + arena[1])
    cy = 0.5 * (arena[2] + arena[3])
    robots = []
    for k in range(n):
        phi = angle_offset + 2.0 * math.pi * k / n
        dx, dy = _clean(radius * math.cos(phi)), _clean(radius * math.sin(phi))
        theta = _clean(math.atan2(0.0 - dy, 0.0 - dx))  # 0.0 - x: no -0.0, so θ = +π on the −x side
        robots.append(
            {
                "id": f"r{k + 1}",
                "start": [_clean(cx + dx), _clean(cy + dy), theta],
                "goal": [_clean(cx - dx), _clean(cy - dy)],
            }
        )
    return {
        "name": f"swap_{n}",
        "duration": float(duration) if duration is not None else 15.0 * n,
        "arena": {"bounds": [float(b) for b in arena]},
        "simulation": {"seed": int(seed)},
        "robots": robots,
    }


def _far_enough(p: np.ndarray, others: list[np.ndarray], sep: float) -> bool:
    return all(float(np.linalg.norm(p - q)) >= sep for q in others)


def random_scene(
    seed: int,
    n: int = 10,
    min_separation: float = 0.42,
    arena: tuple[float, float, float, float] = (-1.0, 1.0, -1.0, 1.0),
    duration: float = 150.0,
    *,
    margin: float = 0.16,
    lookahead: float | None = None,
    max_tries: int = 100_000,
) -> dict[str, Any]:
    """n robots with random starts, headings and goals (``numpy.random.default_rng(seed)``).

    Contract: the start axle centres, the start controlled points (look-ahead
    ``lookahead`` [m], default the epuck preset's) and the goals each lie at
    least ``margin`` [m] from every wall and are pairwise at least
    ``min_separation`` [m] apart (starts among starts, goals among goals).
    Sequential rejection sampling, restarted when stuck; raises RuntimeError
    after ``max_tries`` candidate draws in total."""
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    ell = preset("epuck").lookahead if lookahead is None else float(lookahead)
    xmin, xmax, ymin, ymax = (float(b) for b in arena)
    lo = np.array([xmin + margin, ymin + margin])
    hi = np.array([xmax - margin, ymax - margin])
    if np.any(hi < lo):
        raise ValueError(f"margin {margin} m leaves no room in the arena {arena}")
    rng = np.random.default_rng(seed)
    tries = 0
    stuck_limit = max(200, max_tries // 50)

    def inside(p: np.ndarray) -> bool:
        return bool(np.all(p >= lo) and np.all(p <= hi))

    def draw_starts() -> list[tuple[np.ndarray, np.ndarray, float]]:
        nonlocal tries
        out: list[tuple[np.ndarray, np.ndarray, float]] = []
        stuck = 0
        while len(out) < n:
            tries += 1
            if tries > max_tries:
                raise RuntimeError(f"random_scene: no placement of {n} starts after {max_tries} draws")
            c = rng.uniform(lo, hi)
            th = float(rng.uniform(-math.pi, math.pi))
            axle = axle_centre(c, th, ell)
            if (
                inside(axle)
                and _far_enough(c, [o[0] for o in out], min_separation)
                and _far_enough(axle, [o[1] for o in out], min_separation)
            ):
                out.append((c, axle, th))
                stuck = 0
            else:
                stuck += 1
                if stuck > stuck_limit:
                    out, stuck = [], 0
        return out

    def draw_goals() -> list[np.ndarray]:
        nonlocal tries
        out: list[np.ndarray] = []
        stuck = 0
        while len(out) < n:
            tries += 1
            if tries > max_tries:
                raise RuntimeError(f"random_scene: no placement of {n} goals after {max_tries} draws")
            g = rng.uniform(lo, hi)
            if _far_enough(g, out, min_separation):
                out.append(g)
                stuck = 0
            else:
                stuck += 1
                if stuck > stuck_limit:
                    out, stuck = [], 0
        return out

    starts = draw_starts()
    goals = draw_goals()
    robots = [
        {
            "id": f"r{k + 1}",
            "start": [float(axle[0]), float(axle[1]), th],
            "goal": [float(g[0]), float(g[1])],
        }
        for k, ((_, axle, th), g) in enumerate(zip(starts, goals, strict=True))
    ]
    return {
        "name": f"random_{n}_seed{seed}",
        "duration": float(duration),
        "arena": {"bounds": [xmin, xmax, ymin, ymax]},
        "simulation": {"seed": int(seed)},
        "robots": robots,
    }


# --------------------------------------------------------------------------- hard scenes

EPUCK_FOOTPRINT = 0.13405
"""The epuck preset's footprint radius r [m] (robot, look-ahead and tube), rounded up."""
MIN_GOAL_SPACING = 0.2782
"""Goal spacing of the hard scenes [m]: the epuck preset's two footprints (2 × 0.13404 m) plus
:data:`ground.scenario.GOAL_MARGIN`, rounded up: the closest goals the loader accepts."""


def _robot(
    k: int, point: Sequence[float], goal: Sequence[float], lookahead: float | None = None
) -> dict[str, Any]:
    """Robot ``r{k+1}`` whose controlled point (``lookahead`` [m] ahead of the axle) starts at
    ``point`` [m], heading at its goal; ``lookahead`` defaults to the epuck preset's."""
    ell = preset("epuck").lookahead if lookahead is None else lookahead
    dx, dy = goal[0] - point[0], goal[1] - point[1]
    th = math.atan2(dy, dx) if math.hypot(dx, dy) > 1e-9 else 0.0
    axle = axle_centre(np.asarray(point, dtype=float), th, ell)
    return {
        "id": f"r{k + 1}",
        "start": [_clean(axle[0]), _clean(axle[1]), _clean(th)],
        "goal": [_clean(goal[0]), _clean(goal[1])],
    }


def _scene(
    name: str, robots: list[dict[str, Any]], duration: float, seed: int, **extra: Any
) -> dict[str, Any]:
    bounds = extra.pop("arena", (-1.0, 1.0, -1.0, 1.0))
    return {
        "name": name,
        "duration": float(duration),
        "arena": {"bounds": [float(b) for b in bounds]},
        "simulation": {"seed": int(seed)},
        "robots": robots,
        **extra,
    }


def ring(
    n: int, spacing: float = 0.317, shift: int = 1, duration: float = 150.0, seed: int = 0
) -> dict[str, Any]:
    """n robots on a circle, ``spacing`` [m] apart; robot k heads for robot k + ``shift``'s start."""
    radius = spacing / (2.0 * math.sin(math.pi / n))
    pts = [(radius * math.cos(2 * math.pi * k / n), radius * math.sin(2 * math.pi * k / n)) for k in range(n)]
    robots = [_robot(k, pts[k], pts[(k + shift) % n]) for k in range(n)]
    return _scene(f"ring_{n}_shift{shift}", robots, duration, seed)


def mirrored_grid(
    rows: int, cols: int, spacing: float = MIN_GOAL_SPACING, duration: float = 200.0, seed: int = 0
) -> dict[str, Any]:
    """A rows × cols grid of robots ``spacing`` [m] apart, each heading for its mirror image
    through the centre (the centre robot of an odd grid stays)."""
    pts = [
        ((i - (rows - 1) / 2) * spacing, (j - (cols - 1) / 2) * spacing)
        for i in range(rows)
        for j in range(cols)
    ]
    robots = [_robot(k, p, (-p[0], -p[1])) for k, p in enumerate(pts)]
    return _scene(f"grid_{rows}x{cols}", robots, duration, seed)


def corridor_swap(
    n: int, length: float = 3.0, width: float = 0.6, duration: float = 300.0, seed: int = 0
) -> dict[str, Any]:
    """n robots in a ``length`` × ``width`` [m] arena, half at each end, each crossing to the
    other end: they must pass head-on in a corridor barely two robots wide."""
    half, x0, y = n // 2, 0.5 * length - 0.2, 0.07
    left = [(-x0 + 0.3 * k, y * (-1) ** k) for k in range(half)]
    right = [(x0 - 0.3 * k, y * (-1) ** k) for k in range(n - half)]
    robots = [
        _robot(k, left[k], (right[k][0] if k < len(right) else x0 - 0.3 * k, -left[k][1]))
        for k in range(half)
    ]
    robots += [_robot(half + k, right[k], (-x0 + 0.3 * k, -right[k][1])) for k in range(n - half)]
    arena = (-0.5 * length, 0.5 * length, -0.5 * width, 0.5 * width)
    return _scene(f"corridor_{n}", robots, duration, seed, arena=arena)


def gap_swap(n: int, gap: float = 0.36, duration: float = 240.0, seed: int = 0) -> dict[str, Any]:
    """Two walls of polygons across the arena at x = 0, leaving a ``gap`` [m] at the centre;
    n robots on each side, each crossing to the mirror point on the other side."""
    g = 0.5 * gap
    walls = [
        {"polygon": [[-0.06, g], [0.06, g], [0.06, 1.0], [-0.06, 1.0]]},
        {"polygon": [[-0.06, -1.0], [0.06, -1.0], [0.06, -g], [-0.06, -g]]},
    ]
    ys = [(k - (n - 1) / 2) * 0.3 for k in range(n)]
    robots = [_robot(k, (-0.6, y), (0.6, -y)) for k, y in enumerate(ys)]
    robots += [_robot(n + k, (0.6, y), (-0.6, -y)) for k, y in enumerate(ys)]
    return _scene(f"gap_{2 * n}", robots, duration, seed, obstacles=walls)


def _box(x0: float, x1: float, y0: float, y1: float) -> dict[str, Any]:
    """A rectangular polygon obstacle [m]."""
    corners = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    return {"polygon": [[_clean(x), _clean(y)] for x, y in corners]}


def pocket(
    width: float = 0.28, depth: float = 0.8, robots: int = 1, wall: float = 0.02, duration: float = 120.0,
    seed: int = 0,
) -> dict[str, Any]:  # fmt: skip
    """A dead-end pocket ``width`` [m] wide and ``depth`` [m] deep, walled by thin arms ``wall``
    [m] thick and open at the top, and ``robots`` robots whose goals fill it from the bottom,
    the closest the loader allows.  They start in a row below and beside it, so each straight
    line to a goal crosses an arm."""
    fp = EPUCK_FOOTPRINT
    h = 0.5 * width
    top = max(0.4, depth - 0.5)  # a deep pocket reaches up: its bottom stays clear of the row below
    bottom = top - depth
    walls = [
        _box(-h - wall, -h, bottom - wall, top),
        _box(h, h + wall, bottom - wall, top),
        _box(-h, h, bottom - wall, bottom),
    ]
    first = bottom + fp + 0.02
    team = [_robot(k, (0.7 - 0.3 * k, -0.75), (0.0, first + k * MIN_GOAL_SPACING)) for k in range(robots)]
    name = f"pocket_{round(width * 1000)}mm" + (f"_{robots}" if robots > 1 else "")
    return _scene(name, team, duration, seed, obstacles=walls)


def lane_crossing(duration: float = 120.0, seed: int = 0) -> dict[str, Any]:
    """Two robots in a corridor 0.32 m wide, a single robot wide, across a 2 m arena, each bound
    for a point 0.3 m past the middle on the other's way: each goal walls in the other's way, so
    each must be home before the other parks, which no order does."""
    walls = [_box(-1.0, 1.0, 0.16, 1.0), _box(-1.0, 1.0, -1.0, -0.16)]
    robots = [_robot(0, (-0.85, 0.0), (0.3, 0.0)), _robot(1, (0.85, 0.0), (-0.3, 0.0))]
    return _scene("lane_crossing", robots, duration, seed, obstacles=walls)


def goals_by_obstacles(n: int, seed: int = 0, duration: float = 200.0) -> dict[str, Any]:
    """Three circular obstacles, each with goals packed around it 1 cm past the footprint
    (0.14 m from its edge); up to n ≤ 12 robots from starts on the left."""
    rng = np.random.default_rng(seed)
    centres = [(0.45, 0.5), (0.45, -0.5), (-0.2, 0.0)]
    radius = 0.12
    goals: list[tuple[float, float]] = []
    for cx, cy in centres:
        d = radius + 0.14
        for a in np.linspace(0.0, 2 * math.pi, 7, endpoint=False) + rng.uniform(0, math.pi):
            q = (cx + d * math.cos(a), cy + d * math.sin(a))
            if (
                all(math.hypot(q[0] - o[0], q[1] - o[1]) >= MIN_GOAL_SPACING for o in goals)
                and max(map(abs, q)) < 0.85
            ):
                goals.append(q)
    goals = [goals[i] for i in rng.permutation(len(goals))[:n]]
    slots = [(x, -0.75 + 0.3 * j) for j in range(6) for x in (-0.8, -0.5)]  # 0.3 m apart
    starts = [slots[i] for i in sorted(rng.permutation(len(slots))[: len(goals)])]
    robots = [_robot(k, a, b) for k, (a, b) in enumerate(zip(starts, goals, strict=True))]
    obstacles = [{"circle": {"center": list(c), "radius": radius}} for c in centres]
    return _scene(f"obstacle_goals_{len(goals)}", robots, duration, seed, obstacles=obstacles)


def single_file(
    n: int, kind: str = "shift", width: float = 0.36, duration: float = 300.0, seed: int = 0
) -> dict[str, Any]:
    """Robots in a corridor ``width`` [m] wide, too narrow for two to pass (2·footprint < width <
    4·footprint), in slots 0.3 m apart.  ``kind``:

    * ``"shift"``: a row of n along a straight corridor, each goal the next robot's start and the
      last robot's a free slot beyond: the front robot must go first;
    * ``"trains"``: two trains of n // 2 and n − n // 2 at the two ends of a straight corridor,
      each bound for the other end, with a bay in the middle where one train can wait;
    * ``"cycle"``: n robots on a closed track around a block, each bound for the next start
      along it: they must all move together, as a ring turns."""
    fp = EPUCK_FOOTPRINT
    if not 2 * fp < width < 4 * fp:
        raise ValueError(f"single_file: width {width} m is not single file for a footprint of {fp} m")
    h = 0.5 * width
    if kind in ("shift", "trains"):
        # The arena is wide enough for the tube design (two robots can pass in it); walls make
        # the lane.
        length = 0.3 * (n + 1) + 0.6 + (0.9 if kind == "trains" else 0.0)
        half, side = 0.5 * length, 0.5
        arena = (-half, half, -side, side)
        walls: list[dict[str, Any]] = [_box(-half, half, -side, -h)]
        if kind == "shift":
            walls.append(_box(-half, half, h, side))
            slots = [(-half + 0.3 + 0.3 * k, 0.0) for k in range(n + 1)]
            robots = [_robot(k, slots[k], slots[k + 1]) for k in range(n)]
        else:
            # A bay above the middle of the lane: room for a robot beside it, a footprint clear.
            walls += [_box(-half, -0.45, h, side), _box(0.45, half, h, side)]
            left, right = n // 2, n - n // 2
            lslots = [(-half + 0.3 + 0.3 * k, 0.0) for k in range(max(left, right))]
            rslots = [(half - 0.3 - 0.3 * k, 0.0) for k in range(max(left, right))]
            robots = [_robot(k, lslots[k], rslots[k]) for k in range(left)]
            robots += [_robot(left + k, rslots[k], lslots[k]) for k in range(right)]
        return _scene(f"file_{kind}_{n}", robots, duration, seed, arena=arena, obstacles=walls)
    if kind != "cycle":
        raise ValueError(f"single_file: kind {kind!r} is not shift, trains or cycle")
    # A rectangular track: the block leaves a lane of ``width`` along every wall.
    per_side = max(1, math.ceil(n / 2))
    half_x, half_y = 0.3 * per_side + 0.3, 0.3 + h
    arena = (-half_x - h, half_x + h, -half_y - h, half_y + h)
    block = _box(-half_x + h, half_x - h, -half_y + h, half_y - h)
    top = [(0.3 * (k - 0.5 * (per_side - 1)), half_y) for k in range(per_side)]  # left to right
    bottom = [(-x, -half_y) for x, _ in top]  # right to left: the track's order
    slots = (top + bottom)[:n]
    robots = [_robot(k, slots[k], slots[(k + 1) % n]) for k in range(n)]
    return _scene(f"file_cycle_{n}", robots, duration, seed, arena=arena, obstacles=[block])


def rooms(per_room: int, door: float = 0.30, duration: float = 400.0, seed: int = 0) -> dict[str, Any]:
    """Two rooms of 1.2 m × 1.2 m joined by a doorway ``door`` [m] wide in a wall 0.1 m thick;
    ``per_room`` robots in each room, each bound for the mirror image of its start in the other."""
    wall = [_box(-0.05, 0.05, 0.5 * door, 0.6), _box(-0.05, 0.05, -0.6, -0.5 * door)]
    pts = [(-1.05 + 0.3 * (k // 3), -0.3 + 0.3 * (k % 3)) for k in range(per_room)]
    robots = [_robot(k, p, (-p[0], -p[1])) for k, p in enumerate(pts)]
    robots += [_robot(per_room + k, (-p[0], p[1]), (p[0], -p[1])) for k, p in enumerate(pts)]
    arena = (-1.25, 1.25, -0.6, 0.6)
    return _scene(f"rooms_{2 * per_room}", robots, duration, seed, arena=arena, obstacles=wall)


def concentric_rings(
    rings: int, spacing: float = MIN_GOAL_SPACING, duration: float = 400.0, seed: int = 0
) -> dict[str, Any]:
    """``rings`` concentric rings ``spacing`` [m] apart, each as full as the spacing allows, every
    robot bound for the next start along its ring, the rings turning in turn one way and the
    other: the rigid rotation is the one way home."""
    robots: list[dict[str, Any]] = []
    r0 = spacing
    for i in range(rings):
        radius = r0 + i * spacing
        n = max(3, int(math.pi / math.asin(min(1.0, spacing / (2 * radius)))))
        angles = [2 * math.pi * k / n for k in range(n)]
        pts = [(radius * math.cos(a), radius * math.sin(a)) for a in angles]
        step = 1 if i % 2 == 0 else -1
        base = len(robots)
        robots += [_robot(base + k, pts[k], pts[(k + step) % n]) for k in range(n)]
    half = r0 + (rings - 1) * spacing + 0.35
    return _scene(f"rings_{rings}x_{len(robots)}", robots, duration, seed, arena=(-half, half, -half, half))


def cluttered(
    n: int, obstacles: int = 6, duration: float = 400.0, seed: int = 0, half: float = 1.0
) -> dict[str, Any]:
    """n robots with random starts and goals among ``obstacles`` random discs in an arena of
    half side ``half`` [m] (2 m by default), the goals at the closest legal spacing; drawn again
    (from the same generator) until the loader accepts every goal as reachable."""
    from ground.scenario import ConfigError, parse_scenario

    rng = np.random.default_rng(seed)
    fp = EPUCK_FOOTPRINT
    inner, edge = half - 0.3, half - 0.15
    for _ in range(200):
        discs = [(rng.uniform(-inner, inner, 2), float(rng.uniform(0.06, 0.14))) for _ in range(obstacles)]

        def clear(p: np.ndarray, discs: list = discs) -> bool:
            return all(float(np.linalg.norm(p - c)) >= r + fp + 0.02 for c, r in discs)

        goals: list[np.ndarray] = []
        starts: list[np.ndarray] = []
        for out, sep in ((goals, MIN_GOAL_SPACING), (starts, 0.3)):
            for _ in range(max(4000, 100 * n)):
                if len(out) == n:
                    break
                q = rng.uniform(-edge, edge, 2)
                if clear(q) and _far_enough(q, out, sep):
                    out.append(q)
        if len(goals) < n or len(starts) < n:
            continue
        robots = [_robot(k, starts[k].tolist(), goals[k].tolist()) for k in range(n)]
        obs = [{"circle": {"center": [_clean(c[0]), _clean(c[1])], "radius": _clean(r)}} for c, r in discs]
        box = (-half, half, -half, half)
        d = _scene(f"cluttered_{n}", robots, duration, seed, obstacles=obs, arena=box)
        try:
            parse_scenario(d)
        except ConfigError:
            continue
        return d
    raise RuntimeError(f"cluttered: no accepted layout of {n} robots among {obstacles} discs in 200 draws")


def grid_permutation(
    rows: int, cols: int, spacing: float = 0.5, duration: float = 600.0, seed: int = 0
) -> dict[str, Any]:
    """A rows × cols grid of robots ``spacing`` [m] apart in an arena 1 m wider than the grid,
    each heading for the start of another, a random permutation drawn from ``seed``."""
    pts = [
        ((i - (rows - 1) / 2) * spacing, (j - (cols - 1) / 2) * spacing)
        for i in range(rows)
        for j in range(cols)
    ]
    perm = np.random.default_rng(seed).permutation(len(pts))
    robots = [_robot(k, p, pts[int(perm[k])]) for k, p in enumerate(pts)]
    hx, hy = (rows - 1) / 2 * spacing + 0.5, (cols - 1) / 2 * spacing + 0.5
    return _scene(f"permutation_{rows}x{cols}", robots, duration, seed, arena=(-hx, hx, -hy, hy))


def hundred(kind: str, seed: int = 0) -> dict[str, Any]:
    """A scene of 100 robots: ``circle`` (an antipodal swap on a circle of 4.6 m in a 10 m
    arena), ``permutation`` (a 10 × 10 grid 5/9 m apart in a 6 m arena, goals permuted) or
    ``cluttered`` (random starts and goals at the closest legal spacing among 40 random discs,
    6 m arena)."""
    if kind == "circle":
        d = antipodal_swap(100, radius=4.6, duration=900.0, seed=seed, arena=(-5.0, 5.0, -5.0, 5.0))
    elif kind == "permutation":
        d = grid_permutation(10, 10, spacing=5.0 / 9.0, duration=900.0, seed=seed)
    elif kind == "cluttered":
        d = cluttered(100, obstacles=40, duration=900.0, seed=seed, half=3.0)
    else:
        raise ValueError(f"hundred: unknown kind {kind!r}")
    d["name"] = f"{kind}_100"
    return d


HARD_FAMILIES = ("dense", "ring", "grid", "swap", "corridor", "gap", "obstacles")
"""The families :func:`hard_scene` draws from, in turn, by default."""

LAYOUT_FAMILIES = ("pocket", "file", "rooms", "rings", "cluttered")
"""Families whose layouts force an order of arrival or a joint move, beyond the seven
(:func:`hard_scene` ``families``): dead-end pockets filled from the bottom, single-file lanes
(a shift, two trains and a bay, a closed track that must turn as one), two rooms swapping
through a doorway at the legal minimum, concentric rings turning opposite ways, and dense
scenes among random obstacles."""


SCALE_FAMILIES = ("circle100", "permutation100", "cluttered100")
"""Families of 100 robots (:func:`hundred`): an antipodal circle in a 10 m arena, a 10 × 10 grid
permutation, and a dense random scene among 40 obstacles."""


def hard_scene(seed: int, families: Sequence[str] = HARD_FAMILIES) -> dict[str, Any]:
    """One scene of family ``families[seed % len(families)]`` (of :data:`HARD_FAMILIES`,
    :data:`LAYOUT_FAMILIES` and :data:`SCALE_FAMILIES`), its size and layout drawn from ``seed``."""
    rng = np.random.default_rng(seed)
    family = families[seed % len(families)]
    if family in SCALE_FAMILIES:
        d = hundred(family.removesuffix("100"), seed=seed)
    elif family in LAYOUT_FAMILIES:
        d = _layout_scene(family, rng, seed)
    elif family == "dense":
        n = int(rng.integers(8, 17))
        d = random_scene(seed, n=n, min_separation=MIN_GOAL_SPACING, duration=300.0, margin=0.15)
    elif family == "ring":
        n = int(rng.choice([3, 5, 7, 9]))
        d = ring(
            n,
            spacing=float(rng.uniform(MIN_GOAL_SPACING + 0.001, 0.34)),
            shift=int(rng.integers(1, n)),
            seed=seed,
        )
    elif family == "grid":
        rows, cols = (int(v) for v in rng.choice([(2, 2), (2, 3), (3, 3), (3, 4), (4, 4)]))
        d = mirrored_grid(rows, cols, seed=seed, duration=300.0)
    elif family == "swap":
        n = int(rng.integers(4, 25))
        compact = n > 12
        spacing = 0.238 if compact else MIN_GOAL_SPACING
        ell = COMPACT_CONTROLLER["lookahead"] if compact else preset("epuck").lookahead
        radius = max(0.4, spacing / (2 * math.sin(math.pi / n)) + ell + 0.001)  # the axle is ℓ outside
        half = max(1.0, radius + 0.25)
        d = antipodal_swap(n, radius=radius, duration=20.0 * n, seed=seed, arena=(-half, half, -half, half))
        if compact:
            d["controller"] = dict(COMPACT_CONTROLLER)
    elif family == "corridor":
        d = corridor_swap(int(rng.choice([2, 4, 6])), seed=seed)
    elif family == "gap":
        d = gap_swap(int(rng.integers(1, 5)), seed=seed)
    else:
        d = goals_by_obstacles(int(rng.integers(4, 13)), seed=seed)
    d["name"] = f"hard_{seed}_{d['name']}"
    return d


def _layout_scene(family: str, rng: np.random.Generator, seed: int) -> dict[str, Any]:
    """A scene of one of :data:`LAYOUT_FAMILIES`, drawn with ``rng``."""
    if family == "pocket":
        robots = int(rng.integers(1, 4))
        width = float(rng.uniform(0.28, 0.40))
        return pocket(width, depth=robots * MIN_GOAL_SPACING + 0.2, robots=robots, duration=300.0, seed=seed)
    if family == "file":
        kind = str(rng.choice(["shift", "trains", "cycle"]))
        n = int(rng.integers(3, 7))
        return single_file(n, kind, width=float(rng.uniform(0.29, 0.40)), duration=400.0, seed=seed)
    if family == "rooms":
        return rooms(int(rng.integers(2, 6)), door=float(rng.uniform(0.285, 0.34)), duration=500.0, seed=seed)
    if family == "rings":
        return concentric_rings(int(rng.integers(2, 4)), duration=600.0, seed=seed)
    if family == "cluttered":
        n, discs = int(rng.integers(8, 17)), int(rng.integers(3, 8))
        return cluttered(n, obstacles=discs, duration=500.0, seed=seed)
    raise ValueError(f"hard_scene: unknown family {family!r}")


# --------------------------------------------------------------------------- TOML output

_BARE_KEY = re.compile(r"^[A-Za-z0-9_-]+$")


def _key(k: str) -> str:
    return k if _BARE_KEY.match(k) else json.dumps(k)


def _value(v: object) -> str:
    if isinstance(v, bool | np.bool_):
        return "true" if v else "false"
    if isinstance(v, int | np.integer):
        return str(int(v))
    if isinstance(v, float | np.floating):
        x = float(v)
        if math.isnan(x):
            return "nan"
        if math.isinf(x):
            return "inf" if x > 0 else "-inf"
        return repr(x)
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False)
    if isinstance(v, Mapping):
        return "{ " + ", ".join(f"{_key(str(k))} = {_value(x)}" for k, x in v.items()) + " }"
    if isinstance(v, Sequence | np.ndarray):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def _is_table_array(v: object) -> bool:
    return isinstance(v, list | tuple) and len(v) > 0 and all(isinstance(x, Mapping) for x in v)


def _emit_table(lines: list[str], header: str, table: Mapping[str, Any]) -> None:
    plain = {k: v for k, v in table.items() if not isinstance(v, Mapping)}
    subs = {k: v for k, v in table.items() if isinstance(v, Mapping)}
    lines.append(f"[{header}]")
    lines.extend(f"{_key(k)} = {_value(v)}" for k, v in plain.items())
    for k, v in subs.items():
        lines.append("")
        _emit_table(lines, f"{header}.{_key(k)}", v)


def scene_to_toml(data: Mapping[str, Any], comment: str = "") -> str:
    """Render a scenario dict as TOML text (``tomllib.loads`` gives ``data`` back).

    ``comment`` lines are written at the top as ``#`` comments."""
    lines = [f"# {line}".rstrip() for line in comment.splitlines()]
    if lines:
        lines.append("")
    scalars = {k: v for k, v in data.items() if not isinstance(v, Mapping) and not _is_table_array(v)}
    tables = {k: v for k, v in data.items() if isinstance(v, Mapping)}
    arrays = {k: v for k, v in data.items() if _is_table_array(v)}
    lines.extend(f"{_key(k)} = {_value(v)}" for k, v in scalars.items())
    for k, v in tables.items():
        lines.append("")
        _emit_table(lines, _key(k), v)
    for k, items in arrays.items():
        for item in items:
            lines.append("")
            lines.append(f"[[{_key(k)}]]")
            lines.extend(f"{_key(str(kk))} = {_value(vv)}" for kk, vv in item.items())
    return "\n".join(lines) + "\n"
