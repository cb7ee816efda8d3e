"""Scenario files: schema, validation and geometric sanity checks.

A scenario is a TOML file (read with :mod:`tomllib`) describing the arena, the
controller parameters, the simulation options, the robots and the static
obstacles.  Example::

    name = "paper_three_robots"
    duration = 60.0                      # simulated time [s], > 0
    [arena]
    bounds = [-1.0, 1.0, -1.0, 1.0]      # xmin, xmax, ymin, ymax [m]
    [controller]                         # optional
    preset = "epuck"                     # "epuck" (default) | "paper"
    Ts = 0.1                             # any ControllerParams field overrides the preset
    [controller.wheel]                   # optional, WheelGeometry fields
    axle = 0.053
    [simulation]                         # optional
    seed = 1
    disturbance = "uniform"              # "uniform" | "adversarial" | "none"
    plant = "unicycle"                   # "unicycle" | "double_integrator"
    disturbance_fraction = 0.9           # measured-state error (w + pose noise) in f·W, 0 < f <= 1
    [[robots]]
    id = "r1"
    start = [-0.6, 0.0, 0.0]             # axle centre x [m], y [m], heading [rad]
    goal = [0.6, 0.0]                    # controlled point x [m], y [m]
    priority = 0                         # optional, higher goes first
    link = "sim"                         # optional
    marker = 1                           # optional: ArUco id of its marker (camera source)
    [camera]                             # optional: the ArUco camera tracker
    marker_size = 0.05                   # robot markers' printed side [m]
    fiducials = [{ id = 40, position = [-1.1, -1.1] }, { id = 41, position = [1.1, -1.1] },
                 { id = 42, position = [1.1, 1.1] }, { id = 43, position = [-1.1, 1.1] }]
    [[obstacles]]                        # optional; exactly one of circle / polygon
    circle = { center = [0.0, 0.0], radius = 0.15 }
    [[obstacles]]
    polygon = [[0.3, 0.3], [0.5, 0.3], [0.4, 0.5]]   # convex, >= 3 vertices

Every problem is reported as a single :class:`ConfigError` naming the dotted
field path (``controller.R[1]``, ``robots[2].start``, ``file``) and the reason;
:func:`parse_scenario` and :func:`load_scenario` raise nothing else.
:func:`check_geometry` then checks the starts and goals against the footprint
radius of a synthesised tube design.
"""

from __future__ import annotations

import dataclasses
import difflib
import itertools
import math
import numbers
import re
import stat
import tomllib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ground.freespace import free_space_model
from ground.geometry import controlled_point
from ground.params import PRESETS, ControllerParams
from ground.params import preset as _preset
from ground.wire import MAX_RELAYED, ROBOT_ID

GOAL_TOLERANCE = 0.02
"""A robot is at its goal when its controlled point is within this distance of it [m]."""
SETTLE_TIME = 1.0
"""A robot has arrived when its controlled point has stayed within :data:`GOAL_TOLERANCE` of its
goal this long [s]: one pass through the goal is not an arrival."""
AT_GOAL = 1e-3
"""A committed reference whose end point is within this distance of its goal ends there [m]."""
PARKED_RADIUS = 0.05
"""A robot that has reached its goal counts as parked within this distance of it [m] (its
committed end point's distance; farther, it is returning); a robot counts as waiting within it
of its wait point (:mod:`ground.arrival`)."""
GOAL_MARGIN = 0.01
"""Two goals are at least the two footprints plus this apart [m]: the split rule then leaves
both robots slack to settle side by side (docs/method.md §7, "Close goals")."""
MAX_HORIZON = 200
"""Largest MPC horizon N [steps]: the QP has 6N + 4 variables and its matrices grow as N²."""
MAX_MRPI_TERMS = 1000
"""Most terms of the mRPI sum (``mrpi_max_terms``): each adds a zonotope generator block."""
MIN_MRPI_TOL = 1e-12
"""Smallest ``mrpi_tol``: below it the tail bound is lost in rounding and never met."""
MAX_ARENA_SIDE = 20.0
"""Longest arena side [m]: the free-space grid (400 cells along it) then has cells of 5 cm."""
MAX_SCENARIO_BYTES = 1 << 20
"""Largest scenario file read [bytes]."""
MAX_SEED = 2**32 - 1
"""Largest seed: a 32-bit unsigned integer, the same in every process."""
PRIORITY_RANGE = (-(2**31), 2**31 - 1)
"""Priorities the wire carries (``ground.wire.Plan.priority``, a 32-bit signed integer)."""
DISTURBANCES = ("uniform", "adversarial", "none")
"""Accepted values of ``simulation.disturbance``."""
PLANTS = ("unicycle", "double_integrator")
"""Accepted values of ``simulation.plant``."""


Point = Sequence[float] | np.ndarray


# --------------------------------------------------------------------------- errors


class ConfigError(ValueError):
    """An invalid scenario: ``field`` is the dotted path, ``reason`` says why.

    ``str(e) == f"{field}: {reason}"``; the CLI prints that line and exits 2."""

    def __init__(self, field: str, reason: str) -> None:
        self.field = field
        self.reason = reason
        super().__init__(f"{field}: {reason}")

    def __str__(self) -> str:
        return f"{self.field}: {self.reason}"

    def __reduce__(self) -> tuple[type[ConfigError], tuple[str, str]]:
        return (type(self), (self.field, self.reason))


# --------------------------------------------------------------------------- data model


@dataclass(frozen=True)
class RobotSpec:
    """One robot of a scenario."""

    id: str
    """Unique name, non-empty, characters [A-Za-z0-9_-]."""
    start: tuple[float, float, float]
    """Initial pose of the axle centre, world frame: x [m], y [m], heading θ [rad]."""
    goal: tuple[float, float]
    """Goal of the controlled point, world frame: x [m], y [m]."""
    priority: int = 0
    """Coordination priority; the higher goes first."""
    link: str = "sim"
    """Communication link of the robot ("sim" in simulation; used by hardware runs)."""
    waypoints: tuple[tuple[float, float], ...] = ()
    """A mission: points of the controlled point [m], world frame, visited in order before
    settling at ``goal``, the last of them (``fleet.Fleet.mission``); empty: straight to the
    goal."""
    marker: int | None = None
    """ArUco id of the marker on the robot's top (camera source), in
    ``0 .. size-1`` of the camera's dictionary, unique across robots and
    fiducials.  The marker's x axis (its corner 0 → corner 1 edge) points along
    the robot's heading; see :class:`CameraSpec`."""


@dataclass(frozen=True)
class Circle:
    """A static disc obstacle."""

    center: tuple[float, float]
    """Centre x, y [m]."""
    radius: float
    """Radius [m], > 0."""

    def distance(self, point: Point) -> float:
        """Euclidean distance [m] from ``point`` (x, y) to the disc; 0 inside."""
        p = np.asarray(point, dtype=float)[:2]
        return max(0.0, float(np.linalg.norm(p - np.asarray(self.center))) - self.radius)

    def distances(self, points: np.ndarray) -> np.ndarray:
        """:meth:`distance` of each of ``points`` (M, 2) [m]: (M,) [m]."""
        d = np.linalg.norm(np.asarray(points, dtype=float) - np.asarray(self.center), axis=1)
        return np.maximum(d - self.radius, 0.0)

    def closest_point(self, point: Point) -> np.ndarray:
        """Nearest point (2,) [m] of the disc's boundary circle to ``point``.

        For a point outside this is the closest point of the obstacle; for the
        centre itself an arbitrary boundary point is returned."""
        p = np.asarray(point, dtype=float)[:2]
        c = np.asarray(self.center, dtype=float)
        d = p - c
        n = float(np.linalg.norm(d))
        if n < 1e-15:
            return c + np.array([self.radius, 0.0])
        return c + self.radius * d / n


@dataclass(frozen=True)
class Polygon:
    """A static convex polygon obstacle."""

    vertices: tuple[tuple[float, float], ...]
    """Vertices x, y [m], counter-clockwise, strictly convex (no repeated or
    collinear vertices), at least 3."""

    def _array(self) -> np.ndarray:
        return np.asarray(self.vertices, dtype=float)

    def contains(self, point: Point) -> bool:
        """True if ``point`` lies inside the polygon or on its boundary."""
        v = self._array()
        p = np.asarray(point, dtype=float)[:2]
        e = np.roll(v, -1, axis=0) - v
        r = p - v
        cross = e[:, 0] * r[:, 1] - e[:, 1] * r[:, 0]
        return bool(np.all(cross >= -1e-12 * max(1.0, float(np.abs(v).max()) ** 2)))

    def closest_point(self, point: Point) -> np.ndarray:
        """Nearest boundary point (2,) [m] to ``point`` (inside or outside)."""
        v = self._array()
        p = np.asarray(point, dtype=float)[:2]
        a = v
        e = np.roll(v, -1, axis=0) - v
        t = np.clip(np.einsum("ij,ij->i", p - a, e) / np.einsum("ij,ij->i", e, e), 0.0, 1.0)
        q = a + t[:, None] * e
        k = int(np.argmin(np.linalg.norm(q - p, axis=1)))
        return np.asarray(q[k], dtype=float)

    def distance(self, point: Point) -> float:
        """Euclidean distance [m] from ``point`` (x, y) to the polygon; 0 inside."""
        if self.contains(point):
            return 0.0
        p = np.asarray(point, dtype=float)[:2]
        return float(np.linalg.norm(self.closest_point(p) - p))

    def distances(self, points: np.ndarray) -> np.ndarray:
        """:meth:`distance` of each of ``points`` (M, 2) [m]: (M,) [m] (0 inside)."""
        v = self._array()
        e = np.roll(v, -1, axis=0) - v
        r = np.asarray(points, dtype=float)[:, None, :] - v[None]  # (M, E, 2)
        t = np.clip(np.einsum("mij,ij->mi", r, e) / np.einsum("ij,ij->i", e, e), 0.0, 1.0)
        d = np.linalg.norm(r - t[..., None] * e[None], axis=2).min(axis=1)
        inside = np.all(e[None, :, 0] * r[..., 1] - e[None, :, 1] * r[..., 0] >= 0.0, axis=1)
        return np.where(inside, 0.0, d)


Obstacle = Circle | Polygon


@dataclass(frozen=True)
class SimulationSpec:
    """The ``[simulation]`` table."""

    seed: int = 0
    """Seed of the disturbance generator, >= 0."""
    disturbance: str = "uniform"
    """Disturbance model: "uniform" | "adversarial" | "none"."""
    plant: str = "unicycle"
    """Simulated plant: "unicycle" | "double_integrator"."""
    disturbance_fraction: float = 0.9
    """The measured state's one-step error lies in fraction·W, 0 < fraction <= 1:
    the process disturbance gets what the pose noise (2·point_noise per
    position axis) leaves of it."""


ARUCO_DICTIONARIES: dict[str, int] = {
    **{f"DICT_{n}X{n}_{m}": m for n in (4, 5, 6, 7) for m in (50, 100, 250, 1000)},
    "DICT_ARUCO_ORIGINAL": 1024,
    "DICT_APRILTAG_16h5": 30,
    "DICT_APRILTAG_25h9": 35,
    "DICT_APRILTAG_36h10": 2320,
    "DICT_APRILTAG_36h11": 587,
}
"""Accepted values of ``camera.dictionary`` (OpenCV's predefined ArUco
dictionaries) → number of marker ids (ids are ``0 .. n-1``)."""


ROS_DOMAIN_MAX = 232
"""Largest ROS 2 domain id (``ROS_DOMAIN_ID``): 0 … 232."""
ROS_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")
"""A robot id that can be a ROS 2 topic name token (``/<id>/pose``): a letter first, then letters,
digits and underscores; no ``-``, and no ``__`` (checked apart)."""


@dataclass(frozen=True)
class Ros2Spec:
    """The ``[ros2]`` table: the fleet as ROS 2 sees it over rmw_zenoh (docs/ros2.md)."""

    enabled: bool = False
    """Publish the fleet's topics and take RViz goals (``fleet run --ros2`` does the same)."""
    domain: int = 0
    """ROS 2 domain id, 0 … :data:`ROS_DOMAIN_MAX`: the first part of every ROS key."""


def ros2_problem(ids: Sequence[str]) -> str | None:
    """Why these robot ids cannot be ROS 2 topic names (``/<id>/pose``), or None."""
    for rid in ids:
        if not ROS_NAME.fullmatch(rid) or "__" in rid:
            return (
                f"robot id {rid!r} cannot name a ROS 2 topic (/{rid}/pose): it must start with a letter "
                "and hold only letters, digits and single underscores"
            )
    return None


@dataclass(frozen=True)
class Fiducial:
    """A fixed ArUco marker at a known place, for the floor homography."""

    id: int
    """ArUco id, in the camera's dictionary, unique across fiducials and robots."""
    position: tuple[float, float]
    """Centre of the marker, world frame: x [m], y [m].  It must lie in the
    plane of the robots' markers (the homography maps that plane)."""


@dataclass(frozen=True)
class CameraSpec:
    """The ``[camera]`` table: the overhead ArUco camera tracker.

    The tracker maps image pixels to the world plane z = h of the robots'
    markers with a homography fitted to the fiducials' centres (:mod:`tracker.vision`), so
    the fiducials must sit at the markers' height h above the floor: a
    marker at height Δh off that plane appears displaced by Δh/H_cam times its
    distance from the camera's nadir.  Robot marker frame = robot frame: x
    forward (the marker's corner 0 → corner 1 edge), y to the left, viewed
    from above."""

    dictionary: str = "DICT_4X4_50"
    """OpenCV ArUco dictionary, a key of :data:`ARUCO_DICTIONARIES`."""
    marker_size: float = 0.05
    """Printed side length of the robots' markers [m] (outer edge of the black
    border), > 0; detections whose side on the floor is off by more than 25 %
    are rejected as implausible."""
    marker_offset: tuple[float, float] = (0.0, 0.0)
    """Centre of a robot's marker relative to its axle centre, robot frame
    (x forward, y left) [m]."""
    fiducials: tuple[Fiducial, ...] = ()
    """The fixed markers, at least 4, of which 4 are in general position
    (no three on a line)."""
    homography: Path | None = None
    """Calibration file written by ``fleet calibrate`` (JSON, image px → world
    m), resolved against the scenario file's directory; None: the tracker
    calibrates from the fiducials of the first frames."""
    intrinsics: Path | None = None
    """Lens calibration file written by ``fleet calibrate --intrinsics`` (JSON: camera
    matrix [px], distortion (k1, k2, p1, p2, k3), image size [px]), resolved against the
    scenario file's directory; the tracker undistorts marker corners through it.  None:
    lens distortion is not corrected."""
    device: int | None = None
    """Video device index (``/dev/videoN``) used when ``--device`` is not given."""
    position_noise: float | None = None
    """Claimed bound on the camera's position error [m], >= 0; the tracker and
    ``fleet calibrate`` check the calibration's reprojection error against it."""
    heading_noise: float | None = None
    """Claimed bound on the camera's heading error [rad], >= 0 (reported
    against the controller's ``pose_noise``)."""


@dataclass(frozen=True)
class Scenario:
    """A validated scenario."""

    name: str
    """Scenario name."""
    duration: float
    """Simulated time [s], > 0."""
    arena: tuple[float, float, float, float]
    """Arena bounds (xmin, xmax, ymin, ymax) [m]."""
    controller: ControllerParams
    """Controller parameters: the preset with the file's overrides applied."""
    simulation: SimulationSpec
    """Simulation options."""
    robots: tuple[RobotSpec, ...]
    """The robots, in file order (at least one)."""
    obstacles: tuple[Obstacle, ...]
    """Static obstacles, in file order."""
    source: str
    """Where the scenario came from: a file path or "<dict>"."""
    camera: CameraSpec | None = None
    """The ``[camera]`` table, None when absent."""
    ros2: Ros2Spec = Ros2Spec()
    """The ``[ros2]`` table (off when absent)."""


# --------------------------------------------------------------------------- primitive validators


def _show(value: object) -> str:
    """Short rendering of a value for an error message."""
    if isinstance(value, bool | np.bool_):
        return f"{str(bool(value)).lower()} (a boolean)"
    if isinstance(value, str):
        return repr(value) if len(value) <= 40 else repr(value[:37] + "...")
    if isinstance(value, Mapping):
        return "a table"
    if isinstance(value, list | tuple):
        return f"an array of {len(value)} item{'s' if len(value) != 1 else ''}"
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _fmt(x: float) -> str:
    return f"{x:g}"


def _number(
    value: object,
    path: str,
    *,
    gt: float | None = None,
    ge: float | None = None,
    lt: float | None = None,
    le: float | None = None,
) -> float:
    """A finite real number (bools rejected) within the given bounds."""
    if isinstance(value, bool | np.bool_) or not isinstance(value, numbers.Real):
        raise ConfigError(path, f"expected a number, got {_show(value)}")
    x = float(value)
    if not math.isfinite(x):
        raise ConfigError(path, f"expected a finite number, got {_show(x)}")
    if gt is not None and not x > gt:
        raise ConfigError(path, f"must be > {_fmt(gt)}, got {_fmt(x)}")
    if ge is not None and not x >= ge:
        raise ConfigError(path, f"must be >= {_fmt(ge)}, got {_fmt(x)}")
    if lt is not None and not x < lt:
        raise ConfigError(path, f"must be < {_fmt(lt)}, got {_fmt(x)}")
    if le is not None and not x <= le:
        raise ConfigError(path, f"must be <= {_fmt(le)}, got {_fmt(x)}")
    return x


def _integer(value: object, path: str, *, ge: int | None = None, le: int | None = None, why: str = "") -> int:
    """An integer (bools and floats rejected), optionally in [``ge``, ``le``]; ``why`` says
    why the bounds."""
    if isinstance(value, bool | np.bool_) or not isinstance(value, numbers.Integral):
        raise ConfigError(path, f"expected an integer, got {_show(value)}")
    n = int(value)
    if ge is not None and n < ge:
        raise ConfigError(path, f"must be an integer >= {ge}{why}, got {n}")
    if le is not None and n > le:
        raise ConfigError(path, f"must be an integer <= {le}{why}, got {n}")
    return n


def _boolean(value: object, path: str) -> bool:
    if not isinstance(value, bool | np.bool_):
        raise ConfigError(path, f"expected true or false, got {_show(value)}")
    return bool(value)


def _string(value: object, path: str, choices: Sequence[str] | None = None) -> str:
    if not isinstance(value, str):
        raise ConfigError(path, f"expected a string, got {_show(value)}")
    if choices is not None and value not in choices:
        raise ConfigError(path, f"unknown value {value!r} (expected one of {', '.join(choices)})")
    return value


def _array(value: object, path: str, what: str) -> Sequence[Any]:
    if isinstance(value, str) or not isinstance(value, list | tuple | np.ndarray):
        raise ConfigError(path, f"expected an array of {what}, got {_show(value)}")
    return list(value)


def _vector(
    value: object, path: str, length: int, *, gt: float | None = None, ge: float | None = None
) -> tuple[float, ...]:
    """An array of exactly ``length`` finite numbers."""
    items = _array(value, path, f"{length} numbers")
    if len(items) != length:
        raise ConfigError(path, f"expected {length} numbers, got {len(items)}")
    return tuple(_number(x, f"{path}[{i}]", gt=gt, ge=ge) for i, x in enumerate(items))


def _table(value: object, path: str) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise ConfigError(path, f"expected a table, got {_show(value)}")
    return value


def _join(path: str, key: str) -> str:
    return f"{path}.{key}" if path else key


def _check_keys(
    table: Mapping[str, Any], path: str, allowed: Sequence[str], required: Sequence[str] = ()
) -> None:
    """Reject unknown keys, then missing required ones."""
    for key in table:
        if key not in allowed:
            close = difflib.get_close_matches(str(key), list(allowed), n=1)
            hint = f"did you mean {close[0]!r}? " if close else ""
            raise ConfigError(
                _join(path, str(key)), f"unknown key ({hint}expected one of {', '.join(allowed)})"
            )
    for key in required:
        if key not in table:
            raise ConfigError(_join(path, key), "missing required key")


# --------------------------------------------------------------------------- controller rules

Rule = Callable[[object, str], object]


def _positive(value: object, path: str) -> float:
    return _number(value, path, gt=0.0)


def _nonnegative(value: object, path: str) -> float:
    return _number(value, path, ge=0.0)


def _weights(length: int, positive: bool = False) -> Rule:
    def rule(value: object, path: str) -> tuple[float, ...]:
        return _vector(value, path, length, gt=0.0 if positive else None, ge=None if positive else 0.0)

    return rule


def _int_at_least(lo: int, hi: int | None = None, why: str = "") -> Rule:
    def rule(value: object, path: str) -> int:
        return _integer(value, path, ge=lo, le=hi, why=why)

    return rule


def _open_unit(value: object, path: str) -> float:
    return _number(value, path, gt=0.0, lt=1.0)


def _disturbance_box(value: object, path: str) -> tuple[float, ...]:
    w = _vector(value, path, 2, ge=0.0)
    if not any(x > 0.0 for x in w):
        raise ConfigError(path, f"at least one half-width must be > 0, got [{_fmt(w[0])}, {_fmt(w[1])}]")
    return w


_CONTROLLER_RULES: dict[str, Rule] = {
    "Ts": _positive,
    "horizon": _int_at_least(2, MAX_HORIZON, " (the QP's matrices grow as the horizon squared)"),
    "Q": _weights(4),
    "R": _weights(2, positive=True),
    "gamma": _nonnegative,
    "T": _weights(2),
    "K_Q": _weights(4),
    "K_R": _weights(2, positive=True),
    "ref_Q": _weights(4),
    "ref_R": _weights(2, positive=True),
    "W": _disturbance_box,
    "pose_noise": lambda v, p: _vector(v, p, 2, ge=0.0),
    "epsilon": _positive,
    "delta": _positive,
    "v_max": _positive,
    "a_max": _positive,
    "robot_radius": _positive,
    "lookahead": _nonnegative,
    "v_min": _positive,
    "mrpi_tol": lambda v, p: _number(v, p, ge=MIN_MRPI_TOL),
    "mrpi_max_terms": _int_at_least(1, MAX_MRPI_TERMS, " (each term adds generators to the tube)"),
    "admissibility_margin": lambda v, p: _number(v, p, ge=0.0, lt=1.0),
    "max_iter": _int_at_least(1),
    "max_iter_in": _int_at_least(1),
    "solve_time_budget": _positive,
    "priority_share": _open_unit,
    "deadlock": _boolean,
    "penalty": _boolean,
    "penalty_dlim": _positive,
    "penalty_weight": _nonnegative,
}

_WHEEL_RULES: dict[str, Rule] = {
    "wheel_radius": _positive,
    "axle": _positive,
    "steps_per_rev": _int_at_least(1),
    "max_steps": _positive,
}


def _rule_from_default(default: object) -> Rule:
    """Fallback for a parameter without an explicit rule: typed like its default."""
    if isinstance(default, bool):
        return _boolean
    if isinstance(default, int):
        return lambda v, p: _integer(v, p)
    if isinstance(default, float) or default is None:
        return lambda v, p: _number(v, p)
    if isinstance(default, tuple):
        n = len(default)
        return lambda v, p: _vector(v, p, n)
    if isinstance(default, str):
        return lambda v, p: _string(v, p)
    raise TypeError(f"no scenario rule for a parameter with default {default!r}")  # pragma: no cover


def _parse_dataclass_table(raw: object, path: str, base: Any, rules: Mapping[str, Rule]) -> dict[str, object]:
    """Validate a table of overrides of the dataclass instance ``base``."""
    table = _table(raw, path)
    names = [f.name for f in dataclasses.fields(base)]
    _check_keys(table, path, names)
    out: dict[str, object] = {}
    for key, value in table.items():
        rule = rules.get(key) or _rule_from_default(getattr(base, key))
        out[key] = rule(value, _join(path, key))
    return out


def _parse_controller(raw: object, path: str, preset_override: str | None) -> ControllerParams:
    table = _table(raw, path) if raw is not None else {}
    allowed = ["preset"] + [f.name for f in dataclasses.fields(ControllerParams) if f.name != "preset"]
    _check_keys(table, path, allowed)
    name = "epuck"
    if "preset" in table:
        name = _string(table["preset"], _join(path, "preset"), PRESETS)
    if preset_override is not None:
        if not isinstance(preset_override, str) or preset_override not in PRESETS:
            raise ConfigError(
                _join(path, "preset"),
                f"unknown preset override {preset_override!r} (expected one of {', '.join(PRESETS)})",
            )
        name = preset_override
    base = _preset(name)
    overrides: dict[str, object] = {}
    for key, value in table.items():
        if key == "preset":
            continue
        if key == "wheel":
            wheel = _parse_dataclass_table(value, _join(path, "wheel"), base.wheel, _WHEEL_RULES)
            overrides["wheel"] = dataclasses.replace(base.wheel, **wheel)  # type: ignore[arg-type]
            continue
        rule = _CONTROLLER_RULES.get(key) or _rule_from_default(getattr(base, key))
        overrides[key] = rule(value, _join(path, key))
    return base.replace(**overrides)


# --------------------------------------------------------------------------- tables


def _parse_simulation(raw: object, path: str) -> SimulationSpec:
    table = _table(raw, path) if raw is not None else {}
    _check_keys(table, path, [f.name for f in dataclasses.fields(SimulationSpec)])
    spec = SimulationSpec()
    if "seed" in table:
        spec = dataclasses.replace(spec, seed=_integer(table["seed"], _join(path, "seed"), ge=0, le=MAX_SEED))
    if "disturbance" in table:
        d = _string(table["disturbance"], _join(path, "disturbance"), DISTURBANCES)
        spec = dataclasses.replace(spec, disturbance=d)
    if "plant" in table:
        spec = dataclasses.replace(spec, plant=_string(table["plant"], _join(path, "plant"), PLANTS))
    if "disturbance_fraction" in table:
        f = _number(table["disturbance_fraction"], _join(path, "disturbance_fraction"), gt=0.0, le=1.0)
        spec = dataclasses.replace(spec, disturbance_fraction=f)
    return spec


def _parse_arena(raw: object, path: str) -> tuple[float, float, float, float]:
    table = _table(raw, path)
    _check_keys(table, path, ["bounds"], required=["bounds"])
    bpath = _join(path, "bounds")
    xmin, xmax, ymin, ymax = _vector(table["bounds"], bpath, 4)
    if not xmin < xmax:
        raise ConfigError(bpath, f"xmin {_fmt(xmin)} m must be < xmax {_fmt(xmax)} m")
    if not ymin < ymax:
        raise ConfigError(bpath, f"ymin {_fmt(ymin)} m must be < ymax {_fmt(ymax)} m")
    for side, size in (("x", xmax - xmin), ("y", ymax - ymin)):
        if not size <= MAX_ARENA_SIDE:
            raise ConfigError(
                bpath,
                f"the arena is {_fmt(size)} m along {side}; at most {MAX_ARENA_SIDE:g} m (navigator grid)",
            )
    return (xmin, xmax, ymin, ymax)


_ROBOT_KEYS = ("id", "start", "goal", "waypoints", "priority", "link", "marker")
MAX_WAYPOINTS = 1000
"""Most waypoints of one robot's mission."""


def _parse_robots(raw: object, path: str) -> tuple[RobotSpec, ...]:
    items = _array(raw, path, "robot tables ([[robots]])")
    if not items:
        raise ConfigError(path, "expected at least one robot")
    if len(items) > MAX_RELAYED:
        raise ConfigError(
            path, f"{len(items)} robots; at most {MAX_RELAYED} (a tick and a relayed digest carry that many)"
        )
    robots: list[RobotSpec] = []
    seen: dict[str, int] = {}
    markers: dict[int, int] = {}
    for i, item in enumerate(items):
        rpath = f"{path}[{i}]"
        table = _table(item, rpath)
        _check_keys(table, rpath, _ROBOT_KEYS, required=("id", "start"))
        ipath = _join(rpath, "id")
        rid = _string(table["id"], ipath)
        if not ROBOT_ID.fullmatch(rid):
            raise ConfigError(ipath, f"invalid id {rid!r} (expected 1 to 32 characters of A-Z a-z 0-9 _ -)")
        if rid in seen:
            raise ConfigError(ipath, f"duplicate id {rid!r} (also {path}[{seen[rid]}].id)")
        seen[rid] = i
        sx, sy, sth = _vector(table["start"], _join(rpath, "start"), 3)
        waypoints = _waypoints(table, rpath)
        if "goal" in table:
            gx, gy = _vector(table["goal"], _join(rpath, "goal"), 2)
            if waypoints and (gx, gy) != waypoints[-1]:
                raise ConfigError(
                    _join(rpath, "goal"),
                    f"({gx:g}, {gy:g}) is not the last waypoint {waypoints[-1]}: the goal is where the "
                    "mission ends; omit it or make it the last waypoint",
                )
        elif waypoints:
            gx, gy = waypoints[-1]
        else:
            raise ConfigError(
                _join(rpath, "goal"), "missing (give a goal, or waypoints: the last one is the goal)"
            )
        lo, hi = PRIORITY_RANGE
        priority = 0
        if "priority" in table:
            priority = _integer(
                table["priority"], _join(rpath, "priority"), ge=lo, le=hi, why=" (32 bits on the wire)"
            )
        link = "sim"
        if "link" in table:
            link = _string(table["link"], _join(rpath, "link"))
            if not link:
                raise ConfigError(_join(rpath, "link"), "expected a non-empty string")
        marker = None
        if "marker" in table:
            mpath = _join(rpath, "marker")
            marker = _integer(table["marker"], mpath, ge=0)
            if marker in markers:
                raise ConfigError(
                    mpath, f"duplicate marker id {marker} (also {path}[{markers[marker]}].marker)"
                )
            markers[marker] = i
        robots.append(
            RobotSpec(
                id=rid, start=(sx, sy, sth), goal=(gx, gy), waypoints=waypoints, priority=priority, link=link,
                marker=marker,
            )
        )  # fmt: skip
    return tuple(robots)


def _waypoints(table: Mapping[str, Any], rpath: str) -> tuple[tuple[float, float], ...]:
    """A robot's ``waypoints``: [[x, y], ...] [m], at least one, at most :data:`MAX_WAYPOINTS`."""
    if "waypoints" not in table:
        return ()
    wpath = _join(rpath, "waypoints")
    items = _array(table["waypoints"], wpath, "points [[x, y], ...]")
    if not 1 <= len(items) <= MAX_WAYPOINTS:
        raise ConfigError(wpath, f"{len(items)} points; give 1 to {MAX_WAYPOINTS}")
    out = []
    for j, item in enumerate(items):
        x, y = _vector(item, f"{wpath}[{j}]", 2)
        out.append((x, y))
    return tuple(out)


def _convex_ccw(points: Sequence[tuple[float, float]], path: str) -> tuple[tuple[float, float], ...]:
    """Check that ``points`` form a convex polygon; return it counter-clockwise,
    without collinear vertices."""
    v = np.asarray(points, dtype=float)
    n = len(v)
    if n < 3:
        raise ConfigError(path, f"expected at least 3 vertices, got {n}")
    scale = max(1.0, float(np.abs(v).max()))
    for i in range(n):
        for j in range(i + 1, n):
            if np.linalg.norm(v[i] - v[j]) <= 1e-12 * scale:
                raise ConfigError(
                    path,
                    f"vertex {j} ({v[j, 0]:.3g}, {v[j, 1]:.3g}) repeats vertex {i}; "
                    "vertices must be distinct",
                )
    e_in = v - np.roll(v, 1, axis=0)  # edge arriving at vertex k
    e_out = np.roll(v, -1, axis=0) - v  # edge leaving vertex k
    cross = e_in[:, 0] * e_out[:, 1] - e_in[:, 1] * e_out[:, 0]
    dot = np.einsum("ij,ij->i", e_in, e_out)
    tol = 1e-12 * scale * scale
    left, right = int(np.sum(cross > tol)), int(np.sum(cross < -tol))
    if left == 0 and right == 0:
        raise ConfigError(path, "vertices are collinear (the polygon has zero area)")
    area2 = float(np.sum(v[:, 0] * np.roll(v[:, 1], -1) - np.roll(v[:, 0], -1) * v[:, 1]))
    if abs(area2) > tol:
        sign = 1.0 if area2 > 0 else -1.0
    else:
        sign = 1.0 if left >= right else -1.0
    bad = np.flatnonzero(sign * cross < -tol)
    if bad.size:
        k = int(bad[0])
        raise ConfigError(
            path,
            f"not convex: the boundary turns the other way at vertex {k} ({v[k, 0]:.3g}, {v[k, 1]:.3g}) "
            "(split a concave obstacle into convex polygons)",
        )
    turns = float(np.sum(np.arctan2(cross, dot)))
    winding = round(abs(turns) / (2.0 * math.pi))
    if winding != 1:
        raise ConfigError(path, f"not convex: the boundary crosses itself (it winds {winding} times)")
    keep = np.abs(cross) > tol
    strict = v[keep]
    if sign < 0:
        strict = strict[::-1]
    return tuple((float(x), float(y)) for x, y in strict)


def _parse_obstacles(raw: object, path: str) -> tuple[Obstacle, ...]:
    if raw is None:
        return ()
    items = _array(raw, path, "obstacle tables ([[obstacles]])")
    obstacles: list[Obstacle] = []
    for i, item in enumerate(items):
        opath = f"{path}[{i}]"
        table = _table(item, opath)
        _check_keys(table, opath, ("circle", "polygon"))
        kinds = [k for k in ("circle", "polygon") if k in table]
        if len(kinds) != 1:
            got = "neither" if not kinds else "both"
            raise ConfigError(opath, f"expected exactly one of circle, polygon, got {got}")
        if kinds[0] == "circle":
            cpath = _join(opath, "circle")
            circle = _table(table["circle"], cpath)
            _check_keys(circle, cpath, ("center", "radius"), required=("center", "radius"))
            cx, cy = _vector(circle["center"], _join(cpath, "center"), 2)
            radius = _number(circle["radius"], _join(cpath, "radius"), gt=0.0)
            obstacles.append(Circle(center=(cx, cy), radius=radius))
        else:
            ppath = _join(opath, "polygon")
            verts = _array(table["polygon"], ppath, "[x, y] vertices")
            pts = []
            for j, vert in enumerate(verts):
                x, y = _vector(vert, f"{ppath}[{j}]", 2)
                pts.append((x, y))
            obstacles.append(Polygon(vertices=_convex_ccw(pts, ppath)))
    return tuple(obstacles)


_CAMERA_KEYS = (
    "dictionary", "marker_size", "marker_offset", "fiducials", "homography", "intrinsics", "device",
    "position_noise", "heading_noise",
)  # fmt: skip


def _general_position(points: Sequence[tuple[float, float]]) -> bool:
    """Some 4 of ``points`` [m] have no three on a line (a homography is determined)."""
    v = np.asarray(points, dtype=float)
    scale = max(1e-9, float(np.ptp(v, axis=0).max()))

    def collinear(a: int, b: int, c: int) -> bool:
        e1, e2 = v[b] - v[a], v[c] - v[a]
        return abs(float(e1[0] * e2[1] - e1[1] * e2[0])) <= 1e-6 * scale * scale

    for quad in itertools.combinations(range(len(v)), 4):
        if not any(collinear(*tri) for tri in itertools.combinations(quad, 3)):
            return True
    return False


def _parse_camera(raw: object, path: str, base_dir: Path | None) -> CameraSpec:
    """The ``[camera]`` table; ``homography`` and ``intrinsics`` are resolved against ``base_dir``."""
    table = _table(raw, path)
    _check_keys(table, path, _CAMERA_KEYS, required=("fiducials",))
    spec = CameraSpec()
    if "dictionary" in table:
        d = _string(table["dictionary"], _join(path, "dictionary"))
        if d not in ARUCO_DICTIONARIES:
            close = difflib.get_close_matches(d, list(ARUCO_DICTIONARIES), n=1)
            hint = f"did you mean {close[0]!r}? " if close else ""
            raise ConfigError(
                _join(path, "dictionary"),
                f"unknown ArUco dictionary {d!r} ({hint}expected one of {', '.join(ARUCO_DICTIONARIES)})",
            )
        spec = dataclasses.replace(spec, dictionary=d)
    n_ids = ARUCO_DICTIONARIES[spec.dictionary]
    if "marker_size" in table:
        size = _number(table["marker_size"], _join(path, "marker_size"), gt=0.0, le=1.0)
        spec = dataclasses.replace(spec, marker_size=size)
    if "marker_offset" in table:
        ox, oy = _vector(table["marker_offset"], _join(path, "marker_offset"), 2)
        spec = dataclasses.replace(spec, marker_offset=(ox, oy))
    fpath = _join(path, "fiducials")
    items = _array(table["fiducials"], fpath, "fiducial tables { id = ..., position = [x, y] }")
    fiducials: list[Fiducial] = []
    ids: dict[int, int] = {}
    for i, item in enumerate(items):
        ipath = f"{fpath}[{i}]"
        ft = _table(item, ipath)
        _check_keys(ft, ipath, ("id", "position"), required=("id", "position"))
        fid = _integer(ft["id"], _join(ipath, "id"), ge=0)
        if fid >= n_ids:
            raise ConfigError(
                _join(ipath, "id"), f"marker id {fid} is not in {spec.dictionary} (ids 0..{n_ids - 1})"
            )
        if fid in ids:
            raise ConfigError(_join(ipath, "id"), f"duplicate marker id {fid} (also {fpath}[{ids[fid]}].id)")
        ids[fid] = i
        x, y = _vector(ft["position"], _join(ipath, "position"), 2)
        for j, other in enumerate(fiducials):
            if math.hypot(x - other.position[0], y - other.position[1]) < spec.marker_size:
                raise ConfigError(
                    _join(ipath, "position"),
                    f"({_fmt(x)}, {_fmt(y)}) m is closer than marker_size {_fmt(spec.marker_size)} m "
                    f"to {fpath}[{j}]",
                )
        fiducials.append(Fiducial(id=fid, position=(x, y)))
    if len(fiducials) < 4:
        raise ConfigError(
            fpath, f"expected at least 4 fiducials for the floor homography, got {len(fiducials)}"
        )
    if not _general_position([f.position for f in fiducials]):
        raise ConfigError(
            fpath,
            "no 4 fiducials in general position (three or more on a line): the homography is undetermined",
        )
    spec = dataclasses.replace(spec, fiducials=tuple(fiducials))
    for key in ("homography", "intrinsics"):
        if key in table:
            hpath = _join(path, key)
            h = _string(table[key], hpath)
            if not h.strip():
                raise ConfigError(hpath, "expected a non-empty file path")
            hp = Path(h).expanduser()
            if not hp.is_absolute() and base_dir is not None:
                hp = base_dir / hp
            if key == "homography":
                spec = dataclasses.replace(spec, homography=hp)
            else:
                spec = dataclasses.replace(spec, intrinsics=hp)
    if "device" in table:
        spec = dataclasses.replace(spec, device=_integer(table["device"], _join(path, "device"), ge=0))
    if "position_noise" in table:
        pn = _number(table["position_noise"], _join(path, "position_noise"), ge=0.0)
        spec = dataclasses.replace(spec, position_noise=pn)
    if "heading_noise" in table:
        hn = _number(table["heading_noise"], _join(path, "heading_noise"), ge=0.0)
        spec = dataclasses.replace(spec, heading_noise=hn)
    return spec


def _check_markers(robots: Sequence[RobotSpec], camera: CameraSpec | None) -> None:
    """Robot marker ids exist in the camera's dictionary and are not fiducials."""
    spec = camera if camera is not None else CameraSpec()
    n_ids = ARUCO_DICTIONARIES[spec.dictionary]
    fids = {f.id: k for k, f in enumerate(spec.fiducials)}
    for i, r in enumerate(robots):
        if r.marker is None:
            continue
        mpath = f"robots[{i}].marker"
        if r.marker >= n_ids:
            raise ConfigError(mpath, f"marker id {r.marker} is not in {spec.dictionary} (ids 0..{n_ids - 1})")
        if r.marker in fids:
            raise ConfigError(mpath, f"marker id {r.marker} is also camera.fiducials[{fids[r.marker]}].id")


_TOP_KEYS = ("name", "duration", "arena", "controller", "simulation", "robots", "obstacles", "camera", "ros2")


def parse_scenario(
    data: Mapping[str, Any], source: str = "<dict>", preset_override: str | None = None
) -> Scenario:
    """Validate a scenario given as a (TOML-shaped) dict.

    ``preset_override`` replaces ``[controller] preset``; the other controller
    keys still override the preset's values.  Raises :class:`ConfigError`."""
    table = _table(data, "scenario")
    _check_keys(table, "", _TOP_KEYS, required=("name", "duration", "arena", "robots"))
    name = _string(table["name"], "name")
    if not name.strip():
        raise ConfigError("name", "expected a non-empty string")
    duration = _number(table["duration"], "duration", gt=0.0)
    arena = _parse_arena(table["arena"], "arena")
    controller = _parse_controller(table.get("controller"), "controller", preset_override)
    simulation = _parse_simulation(table.get("simulation"), "simulation")
    robots = _parse_robots(table["robots"], "robots")
    obstacles = _parse_obstacles(table.get("obstacles"), "obstacles")
    camera = None
    if "camera" in table:
        base_dir = Path(source).parent if source != "<dict>" else None
        camera = _parse_camera(table["camera"], "camera", base_dir)
    _check_markers(robots, camera)
    ros2 = _parse_ros2(table.get("ros2"), "ros2", [r.id for r in robots])
    return Scenario(
        name=name,
        duration=duration,
        arena=arena,
        controller=controller,
        simulation=simulation,
        robots=robots,
        obstacles=obstacles,
        source=source,
        camera=camera,
        ros2=ros2,
    )


def _parse_ros2(raw: object, path: str, ids: Sequence[str]) -> Ros2Spec:
    table = _table(raw, path) if raw is not None else {}
    _check_keys(table, path, [f.name for f in dataclasses.fields(Ros2Spec)])
    spec = Ros2Spec()
    if "enabled" in table:
        spec = dataclasses.replace(spec, enabled=_boolean(table["enabled"], _join(path, "enabled")))
    if "domain" in table:
        domain = _integer(table["domain"], _join(path, "domain"), ge=0, le=ROS_DOMAIN_MAX)
        spec = dataclasses.replace(spec, domain=domain)
    problem = ros2_problem(ids) if spec.enabled else None
    if problem is not None:
        raise ConfigError(_join(path, "enabled"), problem)
    return spec


def load_scenario(path: str | Path, preset_override: str | None = None) -> Scenario:
    """Read and validate a scenario TOML file.  Raises :class:`ConfigError`
    (field ``file`` for an unreadable file or a TOML syntax error)."""
    p = Path(path)
    try:
        st = p.stat()
        if stat.S_ISDIR(st.st_mode):
            raise IsADirectoryError
        if not stat.S_ISREG(st.st_mode):
            raise ConfigError("file", f"{p}: not a regular file (a device, pipe or socket)")
        with p.open("rb") as fh:
            text = fh.read(MAX_SCENARIO_BYTES + 1)
        if len(text) > MAX_SCENARIO_BYTES:
            raise ConfigError(
                "file", f"{p}: more than {MAX_SCENARIO_BYTES} bytes; a scenario is at most that"
            )
        data = tomllib.loads(text.decode("utf-8"))
    except FileNotFoundError:
        raise ConfigError("file", f"{p}: no such file") from None
    except IsADirectoryError:
        raise ConfigError("file", f"{p}: is a directory, not a scenario file") from None
    except OSError as exc:
        raise ConfigError("file", f"{p}: cannot read ({exc.strerror or exc})") from None
    except UnicodeDecodeError as exc:
        raise ConfigError("file", f"{p}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError("file", f"{p}: invalid TOML: {exc}") from None
    return parse_scenario(data, source=str(p), preset_override=preset_override)


# --------------------------------------------------------------------------- geometry


def _pair(a: float, b: float) -> tuple[str, str]:
    """Format two lengths with enough digits that they print differently."""
    for digits in range(3, 8):
        sa, sb = f"{a:.{digits}f}", f"{b:.{digits}f}"
        if sa != sb:
            return sa, sb
    return f"{a:.8g}", f"{b:.8g}"


def _xy(p: np.ndarray) -> str:
    return f"({p[0]:.2f}, {p[1]:.2f})"


def _describe(obs: Obstacle) -> str:
    if isinstance(obs, Circle):
        return f"circle of radius {obs.radius:g} m at ({obs.center[0]:.2f}, {obs.center[1]:.2f}) m"
    xs = [v[0] for v in obs.vertices]
    ys = [v[1] for v in obs.vertices]
    return (
        f"polygon of {len(obs.vertices)} vertices spanning "
        f"[{min(xs):.2f}, {max(xs):.2f}] × [{min(ys):.2f}, {max(ys):.2f}] m"
    )


def check_point(scn: Scenario, p: np.ndarray, footprint: float, field: str, label: str = "goal") -> None:
    """Check that a controlled point ``p`` (2,) [m] clears the walls and obstacles by ``footprint`` [m].

    Raises :class:`ConfigError` naming ``field``; used for the scenario's
    starts and goals and for goals given at run time."""
    xmin, xmax, ymin, ymax = scn.arena
    fp = float(footprint)
    x, y = float(p[0]), float(p[1])
    if not (math.isfinite(x) and math.isfinite(y)):
        raise ConfigError(field, f"{label} must be finite, got ({x}, {y})")
    if not (xmin <= x <= xmax and ymin <= y <= ymax):
        raise ConfigError(
            field,
            f"{label} {_xy(p)} lies outside the arena [{xmin:g}, {xmax:g}] × [{ymin:g}, {ymax:g}] m",
        )
    walls = [
        (x - xmin, f"x = {xmin:g}"),
        (xmax - x, f"x = {xmax:g}"),
        (y - ymin, f"y = {ymin:g}"),
        (ymax - y, f"y = {ymax:g}"),
    ]
    d, wall = min(walls, key=lambda w: w[0])
    if d < fp:
        sd, sf = _pair(d, fp)
        raise ConfigError(
            field,
            f"{label} {_xy(p)} is {sd} m from the arena wall {wall}, less than the footprint radius {sf} m",
        )
    for k, obs in enumerate(scn.obstacles):
        d = obs.distance(p)
        if d <= 0.0:
            raise ConfigError(field, f"{label} {_xy(p)} lies inside obstacles[{k}] ({_describe(obs)})")
        if d < fp:
            sd, sf = _pair(d, fp)
            raise ConfigError(
                field,
                f"{label} {_xy(p)} is {sd} m from obstacles[{k}], less than the footprint radius {sf} m",
            )


def check_geometry(scn: Scenario, footprint: float) -> None:
    """Check starts and goals against the footprint radius [m] of the design.

    Raises :class:`ConfigError` when a start's controlled point or a waypoint lies outside the
    arena or closer than ``footprint`` to a wall or an obstacle, when two starts are closer than
    ``2·footprint``, when no passage joins a waypoint to the start, or when a goal fails the
    one goal rule (:func:`goal_problem`: in the arena and clear of the walls and obstacles, reached
    from the start, and ``2·footprint`` plus :data:`GOAL_MARGIN` from every goal listed before it)."""
    ell = scn.controller.lookahead
    starts = [controlled_point(r.start, ell) for r in scn.robots]
    goals = [np.asarray(r.goal, dtype=float) for r in scn.robots]
    fp = float(footprint)

    for i in range(len(scn.robots)):
        check_point(scn, starts[i], fp, f"robots[{i}].start", "controlled point")
        for j, wp in enumerate(scn.robots[i].waypoints):
            field, at = f"robots[{i}].waypoints[{j}]", np.asarray(wp, dtype=float)
            check_point(scn, at, fp, field, "waypoint")
            for o, g in enumerate(goals):
                d = float(np.linalg.norm(at - g))
                if o != i and d < 2.0 * fp + GOAL_MARGIN:
                    # The robot would wait there for ever for the other to leave its goal.
                    raise ConfigError(
                        field,
                        f"waypoint {_xy(at)} of {scn.robots[i].id!r} is {d:.3f} m from the goal of "
                        f"{scn.robots[o].id!r}, closer than their footprints allow "
                        f"(2 × {fp:.3f} + {GOAL_MARGIN:g} = {2.0 * fp + GOAL_MARGIN:.3f} m)",
                    )

    for j in range(len(starts)):
        for i in range(j):
            d = float(np.linalg.norm(starts[j] - starts[i]))
            if d < 2.0 * fp:
                sd, sf = _pair(d, 2.0 * fp)
                raise ConfigError(
                    f"robots[{j}].start",
                    f"controlled point {_xy(starts[j])} of {scn.robots[j].id!r} is {sd} m from that of "
                    f"robots[{i}] ({scn.robots[i].id!r}), closer than their footprints allow "
                    f"(2 × {fp:.3f} = {sf} m)",
                )
    joined = free_space(scn, fp)
    for i, r in enumerate(scn.robots):
        for j, w in enumerate(r.waypoints):
            if not joined(starts[i], np.asarray(w, float)):
                raise ConfigError(f"robots[{i}].waypoints[{j}]", _no_passage("waypoint", w, starts[i], fp))
        # The goals by the one goal rule, each against the goals before it.
        earlier = [(scn.robots[k].id, goals[k], fp) for k in range(i)]
        why = _goal_reason(scn, fp, goals[i], earlier, starts[i])
        if why is not None:
            raise ConfigError(f"robots[{i}].goal", why)


def _no_passage(label: str, p: Any, at: Any, fp: float) -> str:
    """The one text of a point (2,) [m] that a disc of radius ``fp`` [m] cannot reach from ``at``."""
    return (
        f"{label} {_xy(p)} cannot be reached from {_xy(at)}: the walls and obstacles leave no "
        f"passage for a footprint of radius {fp:.3f} m"
    )


def free_space(scn: Scenario, fp: float) -> Callable[[np.ndarray, np.ndarray], bool]:
    """Whether a disc of radius ``fp`` [m] can go from one point (2,) [m] to another past the
    scenario's walls and static obstacles (the robots aside): a function of the two points
    (:class:`~ground.freespace.FreeSpace`)."""
    return free_space_model(scn.arena, scn.obstacles, fp).joined


def forced_order(scn: Scenario, footprint: float) -> dict[str, dict[str, list[str]]]:
    """Whose goals wall in each robot's way home, once they are parked there (each goal a disc
    of radius r_i + r_j = 2·``footprint`` [m] that a controlled point may not enter), past the
    walls and obstacles.  Per robot so walled in: ``"alone"``, the robots each of whose goals
    walls it in by itself, and ``"together"``, when none does alone, the robots whose goals wall
    it in together (those about the goal, or the start, that is shut in:
    :meth:`~ground.freespace.FreeSpace.walled_in`).  A goal that covers the
    robot's own start is left out: that robot leaves before the other can park there.

    A layout with none is well-formed in the sense of Čáp, Novák, Kleiner and Selecký
    ("Prioritized planning algorithms for trajectory coordination of multiple mobile robots",
    IEEE T-ASE 2015), for goals: every robot can get home past every robot already home, and no
    parked robot ever has to step aside.  Otherwise an order is forced: a robot named must get
    past the goal of each robot of its ``alone`` before that one parks, and past the goals of
    its ``together`` before all of them have parked, or they step aside for it.  Waypoints are
    not checked here."""
    ell = scn.controller.lookahead
    starts = [controlled_point(r.start, ell) for r in scn.robots]
    goals = [np.asarray(r.goal, dtype=float) for r in scn.robots]
    model = free_space_model(scn.arena, scn.obstacles, footprint)
    reach = 2.0 * float(footprint)
    splits = [model.splits(g, reach) for g in goals]
    forced: dict[str, dict[str, list[str]]] = {}
    for i, r in enumerate(scn.robots):
        a, b = starts[i], goals[i]
        if not model.joined(a, b):
            continue
        others = [j for j in range(len(goals)) if j != i and np.hypot(*(goals[j] - a)) >= reach]
        alone = []
        for j in others:
            lab = splits[j]
            if lab is None:
                continue
            pa, pb = model.piece_in(lab, a), model.piece_in(lab, b)
            if pa is not None and pb is not None and pa != pb:
                alone.append(scn.robots[j].id)
        together: list[str] = []
        if not alone:
            walls = model.walled_in(a, b, [(goals[j], reach) for j in others])
            together = [scn.robots[others[k]].id for k in walls]
        if alone or together:
            forced[r.id] = {"alone": alone, "together": together}
    return forced


def forced_order_lines(forced: Mapping[str, Mapping[str, Sequence[str]]]) -> list[str]:
    """The lines that say :func:`forced_order`: one per robot named, then one per cycle of
    robots each of which must be home before another of them parks (no order does it: one of
    them must step aside for another)."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import connected_components

    lines = []
    for rid, by in forced.items():
        if by["alone"]:
            who = ", ".join(by["alone"])
            lines.append(f"{rid} must get past the goals of {who} before they park: each walls in its way")
        else:
            who = ", ".join(by["together"])
            lines.append(
                f"{rid} must get past the goals of {who} before all of them park: "
                "together they wall in its way"
            )
    alone = {r: list(by["alone"]) for r, by in forced.items() if by["alone"]}
    ids = sorted({*alone, *(b for by in alone.values() for b in by)})
    if ids:
        at = {r: k for k, r in enumerate(ids)}
        edges = [(at[r], at[b]) for r, by in alone.items() for b in by]
        rows, cols = zip(*edges, strict=True)
        graph = csr_matrix(([1] * len(edges), (rows, cols)), shape=(len(ids), len(ids)))
        n, label = connected_components(graph, directed=True, connection="strong")
        for c in range(n):
            members = [ids[k] for k in range(len(ids)) if label[k] == c]
            if len(members) > 1:
                lines.append(
                    f"{', '.join(members)}: each must be home before another of them parks; no order "
                    "does it, so one of them must step aside for another"
                )
    return lines


def settle_samples(Ts: float) -> int:
    """Consecutive samples, ``Ts`` [s] apart, that span :data:`SETTLE_TIME`: the first and the
    last of them included."""
    return math.ceil(SETTLE_TIME / Ts - 1e-9) + 1


def settled_since(errors: Sequence[float], Ts: float) -> int | None:
    """The sample from which a robot has stayed at its goal to the end, if it has arrived
    (stayed :data:`SETTLE_TIME` at least); ``errors`` are its distances to the goal per sample
    [m], ``Ts`` [s] apart.  None if it has not arrived."""
    n = len(errors)
    k = n
    while k > 0 and errors[k - 1] <= GOAL_TOLERANCE:
        k -= 1
    return k if n - k >= settle_samples(Ts) else None


def home(end: np.ndarray, point: np.ndarray, goal: np.ndarray) -> bool:
    """A robot is home when its committed reference ends at its goal (within :data:`AT_GOAL`) and
    its controlled point is within half the goal tolerance of it; ``end``, ``point`` and ``goal``
    are (2,) [m].  A run whose robots have all been home for :func:`settle_samples` samples in a
    row stops early (so each has arrived, :func:`settled_since`)."""
    return bool(np.linalg.norm(end - goal) < AT_GOAL and np.linalg.norm(point - goal) <= 0.5 * GOAL_TOLERANCE)


def goal_problem(
    scn: Scenario, footprint: float, goal: np.ndarray, plans: Sequence[Any],
    batch: Mapping[str, np.ndarray] | None = None, at: np.ndarray | None = None,
) -> str | None:  # fmt: skip
    """Why a goal (2,) [m] given at run time cannot be accepted, or None: the one goal rule,
    which the agent (the authority), ``fleet goal``, the experiment API and the ROS face apply.

    It must be finite, in the arena and clear the walls and obstacles by the footprint radius [m];
    if ``at`` (2,) [m], where the robot is now, is given, the walls and obstacles must leave a
    passage to it from there; and it must park at least the two footprints and
    :data:`GOAL_MARGIN` away from every other robot's current goal: ``plans`` are their latest
    :class:`~ground.wire.Plan` (``robot``, ``goal`` (2,) [m], ``footprint`` [m]).  ``batch`` are
    the goals given to other robots together with this one (robot id → (2,) [m], not the robot
    itself): each replaces that robot's current goal, so that robots may trade goals in one batch;
    a robot of the batch without a plan counts with ``footprint`` (one design for the fleet).

    The scenario loader judges each robot's goal by the same rule (:func:`check_geometry`), from
    its start and against the goals of the robots listed before it, so a goal is refused with
    the same text at load and at run time."""
    given = dict(batch or {})
    others = [(pl.robot, given.pop(pl.robot, pl.goal), pl.footprint) for pl in plans]
    others += [(rid, g, footprint) for rid, g in given.items()]
    return _goal_reason(scn, footprint, goal, others, at)


def _goal_reason(
    scn: Scenario, footprint: float, goal: Any, others: Sequence[tuple[str, Any, float]], at: Any | None
) -> str | None:
    """The rule of :func:`goal_problem`: ``others`` are (robot id, goal (2,) [m], footprint [m])."""
    goal = np.asarray(goal, dtype=float)
    try:
        check_point(scn, goal, footprint, "goal")
    except ConfigError as e:
        return e.reason
    if at is not None and not free_space(scn, footprint)(np.asarray(at, dtype=float), goal):
        return _no_passage("goal", goal, at, footprint)
    for rid, theirs, fp in others:
        d = float(np.linalg.norm(goal - np.asarray(theirs, dtype=float)))
        need = footprint + fp + GOAL_MARGIN
        if d < need:
            sd, sn = _pair(d, need)
            return (
                f"goal {_xy(goal)} is {sd} m from {rid}'s goal, closer than the footprints and the "
                f"margin allow ({footprint:.3f} + {fp:.3f} + {GOAL_MARGIN:g} = {sn} m)"
            )
    return None
