"""Programmatic scenes: scenario dicts accepted by :func:`ground.scenario.parse_scenario`.

* :func:`antipodal_swap` — n robots on a circle, each crossing to the antipodal point.
* :func:`random_scene` — seeded random starts and goals with a minimum separation.
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
