"""The wire contract: Zenoh key expressions and msgpack message schemas.

Every message is a msgpack map ``{"schema": SCHEMA_VERSION, "type": <name>, ...fields}``.
Arrays travel as ``{"dtype": "<f8", "shape": [...], "data": <raw bytes>}``, about
ten times cheaper than nested lists.  Decoding is strict: anything malformed
(garbage bytes, another schema version, a missing or unknown field, a wrong
type, NaN or infinity, an array value beyond :data:`MAX_MAGNITUDE`, a wrong or huge
shape, a plan that claims another robot's id) raises :class:`WireError` with a short
reason, and nothing else: no exception of another kind, and no warning.
A process counts the rejection (:class:`RejectCounter`) and carries on.

Keys, for a fleet named ``F`` and a robot id ``R``:

=========================  ==============================================
``fleet/F/pose/R``         tracker → all: measured pose (:class:`Pose`)
``fleet/F/truth/R``        tracker → supervisor: true pose (the camera's, on real robots)
``fleet/F/odom/R``         robot side → agent: inner-loop velocity (:class:`Odom`)
``fleet/F/plan/R``         agent → all: committed reference (:class:`Plan`)
``fleet/F/near/C/R``       agent → agents near: the same plan, by the cell C of its last committed
                           point (``--exchange place``; cells of :mod:`ground.geometry`)
``fleet/F/cmd/R``          agent → robot side: acceleration (:class:`Command`)
``fleet/F/goal/R``         operator → agent: new goal (:class:`Goal`); put, or a query the agent answers
``fleet/F/script``         script → tracker: permits steps, ends the run (:class:`Script`)
``fleet/F/clock``          tracker → all: the clock's tick (:class:`Tick`)
``fleet/F/outcome``        tracker → agents: what the robot sides did over a step, once decided
                           (:class:`Outcome`; with delay compensation)
``fleet/F/digest``         tracker → agents: one step's plans, relayed (:class:`Digest`)
``fleet/F/alive/R``        liveliness token of agent R (also ``supervisor``, :data:`SCRIPT`, and
                           ``tracker`` in a scripted run)
``fleet/F/at/R/C/S``       liveliness token of agent R (``--exchange place``): its last committed
                           point has been in cell C since its plan of step S
``fleet/F/wheels/R``       ``epuck_link`` → all: wheel odometry (:class:`Wheels`)
``fleet/F/applied/R``      ``epuck_link`` → tracker: what the robot did over a step (:class:`Applied`)
``fleet/F/emu/R``          e-puck emulator → tracker (``--source emulator``): its true pose
=========================  ==============================================

Units are SI; positions and headings are in the world frame.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable
from dataclasses import dataclass, field, fields
from typing import Any, ClassVar, TypeVar

import msgpack
import numpy as np
from numpy.typing import NDArray

from ground.geometry import Cell, parse_cell

SCHEMA_VERSION = 9
"""The version of every message's layout; a message of another version is rejected.

2: :class:`Command` carries the shifted candidate and :class:`Tick` what the robot side applied;
3: :class:`Command` carries the ancillary gain K, so the robot side needs no tube design;
4: :class:`Goal` carries the goals given together with it (``batch``), checked in their place,
and :class:`Script` lets a script hold the lockstep clock and end the run;
5: :class:`Plan` and :class:`Digest` carry the age of each robot's precedence phase (``phase_age``);
6: :class:`Plan` carries its agent's count of places heard late (``late``);
7: :class:`Plan` carries the discs its agent kept clear of (``discs``) and the robot whose stopped
disc covers its goal (``blocked``), and :class:`Command` may ask the robot side to brake
(``brake``);
8: :class:`Plan` and :class:`Digest` may carry the phase :data:`WAITING`;
9: :class:`Plan` carries the robot whose corridor its robot found no room to leave (``no_room``)."""
UNDER_WAY, RETURNING, PARKED, WAITING = 0, 1, 2, 3
"""A plan's precedence phase (:attr:`Plan.phase`): under way (its goal never reached), returning
(reached once, now displaced), parked (at its goal), waiting (at its wait point, before it first
goes home, for robots whose way its goal would wall in: :mod:`ground.arrival`).  Lower goes
first (docs/method.md §7)."""
MAX_AGE = 2**31
"""Largest ``phase_age`` a plan carries [steps] (an agent's count stops there)."""
MAX_PAYLOAD = 64 * 1024
"""Largest accepted message [bytes]."""
MAX_HORIZON = 200
"""Largest accepted committed-reference length [points]."""
MAX_ROBOTS = 256
"""Most robots a fleet may have, and so the most entries of any array or map a message carries
(:func:`decode`'s msgpack limits): a digest's rows, a tick's ``fallback`` and ``braked``, a plan's
``discs``, a goal's ``batch``.  A bound, so that a hostile message cannot make a process allocate
without limit; each message's byte cap (``MAX_BYTES``) fits this many robots."""
MAX_RELAYED = MAX_ROBOTS
"""Most plans one :class:`Digest` carries [robots]."""
ROBOT_ID = re.compile(r"^[A-Za-z0-9_-]{1,32}$")
SCRIPT = "script"
"""The id of a script driving a fleet (``fleet.Fleet``): the sender of :class:`Script`, and its
liveliness token ``fleet/F/alive/script``."""
MAX_BATCH = MAX_ROBOTS
"""Most goals one :class:`Goal` may carry in its ``batch`` [robots]."""
_DTYPES = {"<f8": np.float64, "<f4": np.float32}
_ITEMSIZE = {"<f8": 8, "<f4": 4}
_ARRAY_KEYS = frozenset({"dtype", "shape", "data"})
MAX_MAGNITUDE = 1e9
"""Largest magnitude of an array element [SI units]: far beyond any position, speed, input or
gain the fleet sends, and far enough below overflow that squares and sums of such values stay
finite."""
_MAX = np.maximum.reduce
_MIN = np.minimum.reduce


class WireError(ValueError):
    """A payload was rejected; ``reason`` is short and names the field."""

    def __init__(self, reason: str):
        self.reason = reason
        super().__init__(reason)


class Keys:
    """Key expressions of one fleet."""

    def __init__(self, fleet: str):
        if not ROBOT_ID.fullmatch(fleet):
            raise ValueError(f"fleet name {fleet!r} must match {ROBOT_ID.pattern}")
        self.root = f"fleet/{fleet}"

    def pose(self, robot: str = "*") -> str:
        """``fleet/F/pose/<robot>``: measured poses (:class:`Pose`); ``*`` (the default) for every robot."""
        return f"{self.root}/pose/{robot}"

    def truth(self, robot: str = "*") -> str:
        """``fleet/F/truth/<robot>``: true poses (:class:`Truth`); ``*`` (the default) for every robot."""
        return f"{self.root}/truth/{robot}"

    def plan(self, robot: str = "*") -> str:
        """``fleet/F/plan/<robot>``: committed references (:class:`Plan`); ``*`` for every robot."""
        return f"{self.root}/plan/{robot}"

    def near(self, robot: str = "*", cell: str = "*") -> str:
        """``fleet/F/near/<cell>/<robot>``: plans by place (``--exchange place``); ``*`` (the
        defaults) for every robot or cell."""
        return f"{self.root}/near/{cell}/{robot}"

    def at(self, robot: str = "*", cell: str | None = None, step: int | None = None) -> str:
        """A place token's key, or with ``cell`` None every place token of ``robot``."""
        return f"{self.root}/at/{robot}/**" if cell is None else f"{self.root}/at/{robot}/{cell}/{step}"

    def place_of(self, key: str) -> tuple[str, Cell, int]:
        """(robot, cell, step) of a place token's key; raises WireError otherwise."""
        parts = str(key).split("/")
        if len(parts) != 6 or parts[:3] != [*self.root.split("/"), "at"]:
            raise WireError(f"key {str(key)[:80]!r}: not a place token")
        rid, cell, step = parts[3:]
        if not ROBOT_ID.fullmatch(rid) or not re.fullmatch(r"[0-9]{1,10}", step):
            raise WireError(f"key {str(key)[:80]!r}: bad robot id or step")
        try:
            return rid, parse_cell(cell), int(step)
        except ValueError as e:
            raise WireError(f"key {str(key)[:80]!r}: {e}") from None

    def cmd(self, robot: str = "*") -> str:
        """``fleet/F/cmd/<robot>``: commands (:class:`Command`); ``*`` (the default) for every robot."""
        return f"{self.root}/cmd/{robot}"

    def odom(self, robot: str = "*") -> str:
        """``fleet/F/odom/<robot>``: inner-loop velocities (:class:`Odom`); ``*`` for every robot."""
        return f"{self.root}/odom/{robot}"

    def goal(self, robot: str = "*") -> str:
        """``fleet/F/goal/<robot>``: new goals (:class:`Goal`), put or asked as a query; ``*``
        (the default) for every robot."""
        return f"{self.root}/goal/{robot}"

    def alive(self, robot: str = "*") -> str:
        """``fleet/F/alive/<id>``: liveliness tokens (an agent's, or ``supervisor``, ``script``,
        ``tracker``); ``*`` (the default) for every one."""
        return f"{self.root}/alive/{robot}"

    def wheels(self, robot: str = "*") -> str:
        """``fleet/F/wheels/<robot>``: wheel odometry (:class:`Wheels`); ``*`` for every robot."""
        return f"{self.root}/wheels/{robot}"

    def emu(self, robot: str = "*") -> str:
        """``fleet/F/emu/<robot>``: an e-puck emulator's true pose (:class:`Truth`); ``*`` (the
        default) for every robot."""
        return f"{self.root}/emu/{robot}"

    def applied(self, robot: str = "*") -> str:
        """``fleet/F/applied/<robot>``: what the robot did over a step (:class:`Applied`); ``*``
        (the default) for every robot."""
        return f"{self.root}/applied/{robot}"

    def link(self, robot: str = "*") -> str:
        """``fleet/F/link/<robot>``: the state of the radio link to the robot (:class:`LinkState`);
        ``*`` (the default) for every robot."""
        return f"{self.root}/link/{robot}"

    @property
    def clock(self) -> str:
        """``fleet/F/clock``: the clock's ticks (:class:`Tick`)."""
        return f"{self.root}/clock"

    @property
    def outcome(self) -> str:
        """``fleet/F/outcome``: what the robot sides did over a step (:class:`Outcome`)."""
        return f"{self.root}/outcome"

    @property
    def digest(self) -> str:
        """``fleet/F/digest``: one step's plans, relayed by the tracker (:class:`Digest`)."""
        return f"{self.root}/digest"

    @property
    def script(self) -> str:
        """``fleet/F/script``: a script's permits and end of the run (:class:`Script`)."""
        return f"{self.root}/script"

    def robot_of(self, key: str) -> str:
        """The robot id at the end of a per-robot key; raises WireError otherwise."""
        rid = str(key).rsplit("/", 1)[-1]
        if not ROBOT_ID.fullmatch(rid):
            raise WireError(f"key {key!r}: bad robot id")
        return rid


# ---------------------------------------------------------------- arrays
def encode_array(a: NDArray[Any]) -> dict[str, Any]:
    """``a`` as the wire's array map ``{"dtype": "<f8", "shape", "data"}``: cast to float64,
    C-contiguous, its raw bytes (:func:`decode_array` reads it back)."""
    a = np.ascontiguousarray(a, dtype=np.float64)
    return {"dtype": "<f8", "shape": list(a.shape), "data": a.tobytes()}


def decode_array(obj: Any, name: str, shape: tuple[int | None, ...]) -> NDArray[np.float64]:
    """Strictly decode an array; ``None`` in ``shape`` is a free dimension (≤ MAX_HORIZON).

    This runs for every plan a process receives (n − 1 plans a step per agent),
    so it avoids numpy's Python-level wrappers."""
    if type(obj) is not dict or obj.keys() != _ARRAY_KEYS:
        raise WireError(f"{name}: expected an array map with dtype, shape, data")
    code = obj["dtype"]
    dt = _DTYPES.get(code) if type(code) is str else None
    if dt is None:
        raise WireError(f"{name}: unsupported dtype {code!r}")
    shp = obj["shape"]
    if type(shp) is not list or len(shp) != len(shape):
        raise WireError(f"{name}: expected {len(shape)} dimensions")
    count = 1
    for got, want in zip(shp, shape, strict=True):
        if type(got) is not int:
            raise WireError(f"{name}: expected {len(shape)} dimensions")
        if want is None:
            if not 1 <= got <= MAX_HORIZON:
                raise WireError(f"{name}: dimension {got} outside 1..{MAX_HORIZON}")
        elif got != want:
            raise WireError(f"{name}: expected shape {shape}, got {tuple(shp)}")
        count *= got
    data = obj["data"]
    if type(data) is not bytes or len(data) != count * _ITEMSIZE[code]:
        raise WireError(f"{name}: data length does not match shape {tuple(shp)}")
    a = np.frombuffer(data, dtype=dt)
    # NaN fails both comparisons (minimum and maximum propagate it) and ±inf one of them: two
    # reductions, no temporaries, and no floating-point warning, which a sum of hostile values
    # gives as it overflows. Checked as sent: casting a signalling NaN warns too.
    if count and not (_MIN(a) >= -MAX_MAGNITUDE and _MAX(a) <= MAX_MAGNITUDE):
        raise WireError(f"{name}: a value not finite or beyond ±{MAX_MAGNITUDE:g}")
    if dt is not np.float64:
        a = a.astype(np.float64)
    return a.reshape(shp)


# -------------------------------------------------------------- messages
def _num(v: Any, name: str) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise WireError(f"{name}: expected a number")
    f = float(v)
    if not math.isfinite(f):
        raise WireError(f"{name}: non-finite value")
    return f


def _int(v: Any, name: str, lo: int = 0, hi: int = 2**62) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        raise WireError(f"{name}: expected an integer")
    if not lo <= v <= hi:
        raise WireError(f"{name}: {v} outside {lo}..{hi}")
    return v


def _str(v: Any, name: str, pattern: re.Pattern[str] | None = None, maxlen: int = 64) -> str:
    if not isinstance(v, str) or len(v) > maxlen or (pattern is not None and not pattern.fullmatch(v)):
        raise WireError(f"{name}: bad string")
    return v


M = TypeVar("M", bound="Message")


_FIELD_NAMES: dict[type, tuple[tuple[str, ...], frozenset[str]]] = {}


def _field_names(cls: type) -> tuple[tuple[str, ...], frozenset[str]]:
    """The dataclass field names of a message class, in order and as a set, looked up once
    (an agent encodes two messages a step; ``dataclasses.fields`` builds its tuple anew
    each call)."""
    names = _FIELD_NAMES.get(cls)
    if names is None:
        ordered = tuple(f.name for f in fields(cls))
        names = _FIELD_NAMES[cls] = (ordered, frozenset(ordered))
    return names


@dataclass(frozen=True)
class Message:
    """Base class: subclasses list their fields and how each is checked."""

    TYPE: ClassVar[str] = ""
    MAX_BYTES: ClassVar[int] = MAX_PAYLOAD
    """Largest accepted encoding of this type [bytes]."""
    robot: str

    def _fields(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for name in _field_names(type(self))[0]:
            v = getattr(self, name)
            out[name] = encode_array(v) if isinstance(v, np.ndarray) else v
        return out

    def encode(self) -> bytes:
        """The msgpack bytes of this message: its fields (arrays as :func:`encode_array` maps)
        with the schema version and the type's name."""
        body = {"schema": SCHEMA_VERSION, "type": self.TYPE, **self._fields()}
        return bytes(msgpack.packb(body, use_bin_type=True))

    @classmethod
    def _check(cls, d: dict[str, Any]) -> dict[str, Any]:
        raise NotImplementedError


@dataclass(frozen=True)
class Pose(Message):
    """Measured pose of a robot's axle centre."""

    TYPE: ClassVar[str] = "pose"
    seq: int
    """Sequence number of the camera frame / simulation step."""
    t: float
    """Capture time [s] on the fleet clock."""
    x: float
    y: float
    """Position [m], world frame."""
    theta: float
    """Heading [rad], counter-clockwise from the world x axis."""

    @classmethod
    def _check(cls, d: dict[str, Any]) -> dict[str, Any]:
        return {
            "seq": _int(d["seq"], "seq"),
            "t": _num(d["t"], "t"),
            "x": _num(d["x"], "x"),
            "y": _num(d["y"], "y"),
            "theta": _num(d["theta"], "theta"),
        }


@dataclass(frozen=True)
class Truth(Pose):
    """Ground-truth pose of a robot's axle centre (simulation only, on the truth
    key): what the supervisor's safety monitor checks.  Same fields as Pose."""

    TYPE: ClassVar[str] = "truth"


DISC_KINDS = ("stale", "placed", "loose", "dead", "braked", "blind")
"""Why an agent keeps clear of another robot as a disc (:attr:`Plan.discs`; docs/method.md §6.4):
its plan is late or lost; it is known by its place token only; its radio link is down and it
drives on; its agent is gone; its robot side braked it; its agent holds without poses."""
OFF_PLAN = frozenset({"dead", "braked", "blind"})
"""The :data:`DISC_KINDS` of a robot off its plans for good: its robot stops where it is, and the
disc about it is static and bounded."""
Disc = tuple[str, bool, float, float, float]
"""One disc an agent kept clear of: (kind in :data:`DISC_KINDS`, at rest, centre x [m], centre y
[m], radius [m]), world frame; at rest: about where the camera saw the robot standing still."""
LINK_DOWN = "HOLD_LINK_DOWN"
"""``Plan.status`` of an agent whose robot's radio link is down: the robot drives on uncontrolled
and nothing the agent sends reaches it, so it solves nothing, commits "stay put" and waits for
the link (docs/method.md §6.4)."""

BLIND = "HOLD_NO_POSE"
"""``Plan.status`` of an agent without poses past its model bound: the robot brakes where it
is, off its committed reference, so the neighbours keep clear of it as of a braked robot
(docs/method.md §6), and it commits afresh from where it is when the poses come back."""


@dataclass(frozen=True)
class Plan(Message):
    """An agent's committed reference and what neighbours need to coordinate."""

    TYPE: ClassVar[str] = "plan"
    step: int
    """Step k at which the plan was committed."""
    t0: float
    """Time of ``committed[0]`` [s]."""
    Ts: float
    """Sampling period [s]."""
    committed: NDArray[np.float64] = field(compare=False)
    """Committed reference ỹ_{k+1} … ỹ_{k+N}, (N, 2) [m]."""
    nominal: NDArray[np.float64] = field(compare=False)
    """Nominal positions x̂_k … x̂_{k+N} of the applied plan, (N+1, 2) [m]."""
    footprint: float
    """Footprint radius r_i [m]."""
    priority: int
    rank: int
    phase: int
    """Precedence phase (0 under way, 1 returning, 2 parked, 3 waiting)."""
    target: NDArray[np.float64] = field(compare=False)
    """Navigation waypoint (2,) [m]."""
    goal: NDArray[np.float64] = field(compare=False)
    """Goal (2,) [m]."""
    status: str
    """Solver status of this step; :data:`BLIND` when the agent had no measurement and its
    robot brakes instead of tracking ``committed``."""
    solve_time: float
    """QP update + solve time [s]."""
    tube_ok: bool
    """x − x̂ ∈ Z held at this step."""
    phase_age: int = 0
    """Steps the robot has been in ``phase`` as of this step [steps]: among returning
    robots the one displaced first goes first (docs/method.md §7)."""
    late: int = 0
    """News of other robots' places this agent heard later than the reach's lag bound allows,
    so far [messages] (its inbox's count, docs/method.md §6.7); 0 where nothing is measured
    (every plan to every agent, ``fleet simulate``)."""
    discs: dict[str, Disc] = field(compare=False, default_factory=dict)
    """The other robots this step kept clear of as discs, robot id → :data:`Disc` (at most MAX_ROBOTS;
    empty while every robot in reach is a neighbour)."""
    blocked: str = ""
    """The robot whose static disc (off its plans for good, :data:`OFF_PLAN`) covers this robot's
    goal this step, or "": the goal cannot be reached while it stands there."""
    no_room: str = ""
    """The robot that goes first whose corridor this robot, making way for it, found no free point
    out of this step, or "": the room to step aside that progress assumes is missing here
    (docs/method.md §7, assumption (A))."""

    @classmethod
    def _check(cls, d: dict[str, Any]) -> dict[str, Any]:
        if not isinstance(d["tube_ok"], bool):
            raise WireError("tube_ok: expected a boolean")
        Ts = _num(d["Ts"], "Ts")
        fp = _num(d["footprint"], "footprint")
        if not 0 < Ts <= 10:
            raise WireError("Ts: outside (0, 10] s")
        if not 0 < fp <= 10:
            raise WireError("footprint: outside (0, 10] m")
        return {
            "step": _int(d["step"], "step"),
            "t0": _num(d["t0"], "t0"),
            "Ts": Ts,
            "committed": decode_array(d["committed"], "committed", (None, 2)),
            "nominal": decode_array(d["nominal"], "nominal", (None, 2)),
            "footprint": fp,
            "priority": _int(d["priority"], "priority", -(2**31), 2**31),
            "rank": _int(d["rank"], "rank", 0, 2**31),
            "phase": _int(d["phase"], "phase", 0, WAITING),
            "phase_age": _int(d["phase_age"], "phase_age", 0, MAX_AGE),
            "late": _int(d["late"], "late", 0, 2**31),
            "discs": _discs(d["discs"], d["robot"]),
            "blocked": _other(d["blocked"], d["robot"], "blocked"),
            "no_room": _other(d["no_room"], d["robot"], "no_room"),
            "target": decode_array(d["target"], "target", (2,)),
            "goal": decode_array(d["goal"], "goal", (2,)),
            "status": _str(d["status"], "status"),
            "solve_time": _num(d["solve_time"], "solve_time"),
            "tube_ok": d["tube_ok"],
        }


@dataclass(frozen=True)
class Command(Message):
    """Agent → robot side: the acceleration to hold for one step, and what to do
    if the next commands miss their deadline.

    The robot side (simulated tracker or ``epuck_link``) runs the inner loop at
    ≥ 50 Hz on it; holding (v, ω) for a whole step instead costs about half of
    W (docs/design.md, "Where the inner loop runs").

    ``x_next`` and ``v_next`` are the shifted candidate of the plan just made: the nominal
    state at step ``step + 1`` and the nominal inputs from there, and ``K`` the gain the
    agent plans with.  A robot side with a deadline (the simulated tracker in
    realtime) that has no command of step ``step + m`` in time applies the
    ancillary law on it instead, ``u = v̂ + K(x − x̂)`` with ``x̂`` propagated
    m steps by the nominal model, for as long as ``v_next`` lasts
    (docs/design.md, "Missed deadlines")."""

    TYPE: ClassVar[str] = "cmd"
    step: int
    ax: float
    ay: float
    """Acceleration of the controlled point [m/s²], world frame, u = v̂ + K(x − x̂)."""
    fallback: bool = False
    """Whether ``x_next`` and ``v_next`` may be followed (False: the agent has no plan yet)."""
    x_next: NDArray[np.float64] = field(compare=False, default_factory=lambda: np.zeros(4))
    """Nominal state x̂ at step ``step + 1``, (4,) [px, vx, py, vy] in m, m/s, world frame."""
    v_next: NDArray[np.float64] = field(compare=False, default_factory=lambda: np.zeros((1, 2)))
    """Nominal inputs v̂ from step ``step + 1`` on, (m, 2) [m/s²], world frame, 1 ≤ m ≤ MAX_HORIZON."""
    K: NDArray[np.float64] = field(compare=False, default_factory=lambda: np.zeros((2, 4)))
    """The ancillary gain K (2, 4) [1/s², 1/s] of the law u = v̂ + K(x − x̂) that the agent
    plans with, for the robot side to apply on the candidate."""
    brake: bool = False
    """The agent holds (no pose past its model bound): the robot side brakes the robot over this
    step, from its own state, as it brakes a dead agent's robot (:func:`ground.model.brake_input`,
    or zero wheel speeds), instead of applying ``ax``, ``ay``.  The command counts as applied."""

    @classmethod
    def _check(cls, d: dict[str, Any]) -> dict[str, Any]:
        if not isinstance(d["fallback"], bool):
            raise WireError("fallback: expected a boolean")
        if not isinstance(d["brake"], bool):
            raise WireError("brake: expected a boolean")
        return {
            "step": _int(d["step"], "step"),
            "ax": _num(d["ax"], "ax"),
            "ay": _num(d["ay"], "ay"),
            "fallback": d["fallback"],
            "x_next": decode_array(d["x_next"], "x_next", (4,)),
            "v_next": decode_array(d["v_next"], "v_next", (None, 2)),
            "K": decode_array(d["K"], "K", (2, 4)),
            "brake": d["brake"],
        }


@dataclass(frozen=True)
class Odom(Message):
    """Robot side → agent: velocity of the controlled point from the inner loop's state."""

    TYPE: ClassVar[str] = "odom"
    seq: int
    t: float
    vx: float
    vy: float
    """Velocity [m/s], world frame."""

    @classmethod
    def _check(cls, d: dict[str, Any]) -> dict[str, Any]:
        return {
            "seq": _int(d["seq"], "seq"),
            "t": _num(d["t"], "t"),
            "vx": _num(d["vx"], "vx"),
            "vy": _num(d["vy"], "vy"),
        }


@dataclass(frozen=True)
class Goal(Message):
    """Operator or script → agent: a new goal at run time, for robot ``robot``.

    Published (``fleet goal``), the agent takes it at its next step if it passes its checks; sent
    as a query on the same key (a script), the agent answers whether it accepted it
    (:mod:`agent.node`)."""

    TYPE: ClassVar[str] = "goal"
    goal: NDArray[np.float64] = field(compare=False)
    """Goal (2,) [m], world frame, of the controlled point."""
    batch: dict[str, NDArray[np.float64]] = field(compare=False, default_factory=dict)
    """The goals given to other robots together with this one: robot id → goal (2,) [m], world
    frame; at most :data:`MAX_BATCH`, never ``robot`` itself.  The agent checks its goal against
    these in place of those robots' current goals, so robots may trade goals in one batch."""

    def _fields(self) -> dict[str, Any]:
        return {
            "robot": self.robot,
            "goal": encode_array(self.goal),
            "batch": {r: encode_array(g) for r, g in self.batch.items()},
        }

    @classmethod
    def _check(cls, d: dict[str, Any]) -> dict[str, Any]:
        batch = d["batch"]
        if type(batch) is not dict:
            raise WireError("batch: expected a map of robot ids to goals")
        if len(batch) > MAX_BATCH:
            raise WireError(f"batch: more than {MAX_BATCH} goals")
        goals = {_str(r, "batch", ROBOT_ID): decode_array(g, "batch", (2,)) for r, g in batch.items()}
        if d["robot"] in goals:
            raise WireError("batch: names the robot the goal is for")
        return {"goal": decode_array(d["goal"], "goal", (2,)), "batch": goals}


@dataclass(frozen=True)
class Script(Message):
    """Script → tracker (``fleet/F/script``): how far the clock may run, and the end of the run.

    In a scripted run (``python -m tracker --scripted``) on lockstep, the tracker publishes the
    ground truth of sample k, then holds step k until a Script with ``step`` ≥ k has come: the
    script sees sample k, gives its goals (each acknowledged by its agent), then permits step k.
    On realtime ``step`` is not used.  ``robot`` is the sender, :data:`SCRIPT`."""

    TYPE: ClassVar[str] = "script"
    step: int
    """The last step the tracker may start (≥ −1; −1: none yet).  Permits only grow: a smaller
    one than the tracker already has changes nothing."""
    stop: bool
    """End the run now: the tracker finishes as at the end of its duration (the stop tick)."""

    @classmethod
    def _check(cls, d: dict[str, Any]) -> dict[str, Any]:
        if not isinstance(d["stop"], bool):
            raise WireError("stop: expected a boolean")
        return {"step": _int(d["step"], "step", -1), "stop": d["stop"]}


STEPS_KEPT = 64
"""How far back [steps] the processes remember which steps' commands were not applied."""


def remember_steps(steps: set[int], new: Iterable[int], now: int, kept: int = STEPS_KEPT) -> None:
    """Add ``new`` to ``steps``, the recent steps a fact holds for (e.g. "its command was not
    applied"), and forget those before ``now − kept`` once there are twice ``kept``: the
    set stays bounded without a scan each step.  An old entry is still true, only not needed.

    A ``range`` (the steps a tick says were never executed, resent at every tick of a long
    episode: up to ``kept`` steps for each of 32 robots) is added without a Python loop,
    half the time of a generator over it."""
    if isinstance(new, range) and new.step == 1:
        steps.update(range(max(new.start, now - kept), new.stop))
    else:
        steps.update(s for s in new if s >= now - kept)
    if len(steps) > 2 * kept:
        steps.difference_update([s for s in steps if s < now - kept])


class _Executed:
    """What a robot-side report says per robot (:class:`Tick`, :class:`Outcome`): the maps of
    robots that followed a candidate (``fallback``) or braked (``braked``) instead of the
    command of the step reported, each to the step of its last applied command."""

    fallback: dict[str, int]
    braked: dict[str, int]

    def executed(self, robot: str) -> int | None:
        """The newest step whose plan ``robot`` executed, if its robot side did not apply the
        command of the step reported (None: it applied it, or the report does not say)."""
        got = self.fallback.get(robot)
        return self.braked.get(robot) if got is None else got


@dataclass(frozen=True)
class Tick(_Executed, Message):
    """The clock: step k starts at time t; ``stop`` ends the run.  ``robot`` is the sender."""

    TYPE: ClassVar[str] = "tick"
    step: int
    t: float
    stop: bool
    misses: int
    """Commands that missed their deadline so far (realtime clock; 0 in lockstep)."""
    fallback: dict[str, int] = field(default_factory=dict)
    """Robots whose command of step ``step − 1`` the robot side did not apply, and
    followed instead the shifted candidate of its last applied command: robot id →
    the step of that command.  At most MAX_ROBOTS robots; in lockstep only for commands lost or
    not sent within the timeout.  From the camera tracker, and for emulated robots, it is
    what the ``epuck_link`` processes reported (:class:`Applied`)."""
    braked: dict[str, int] = field(default_factory=dict)
    """Robots that the robot side braked over step ``step − 1`` instead (dead or silent
    agent, or nothing left to follow): robot id → the step of its last applied
    command, −1 if none.  A plan of a later step than the value was never executed."""

    @classmethod
    def _check(cls, d: dict[str, Any]) -> dict[str, Any]:
        if not isinstance(d["stop"], bool):
            raise WireError("stop: expected a boolean")
        step = _int(d["step"], "step")
        return {
            "step": step,
            "t": _num(d["t"], "t"),
            "stop": d["stop"],
            "misses": _int(d["misses"], "misses"),
            "fallback": _steps_by_robot(d["fallback"], "fallback", 0, step),
            "braked": _steps_by_robot(d["braked"], "braked", -1, step),
        }


@dataclass(frozen=True)
class Outcome(_Executed, Message):
    """Tracker → agents, with delay compensation (docs/design.md, "Delay compensation"): what
    the robot sides did over step ``step``, sent as soon as it is decided (at the step's
    deadline, or once every live agent's command is in; with ``epuck_link`` robot sides, once
    their :class:`Applied` reports of the step are in), so that the agents make their plans
    of step ``step + 1`` knowing which plans of step ``step`` are in force.  ``robot`` is the
    sender.  The next tick says the same again (:attr:`Tick.fallback`, :attr:`Tick.braked`)."""

    TYPE: ClassVar[str] = "outcome"
    step: int
    fallback: dict[str, int] = field(default_factory=dict)
    """Robots whose command of ``step`` the robot side did not apply, and that followed the
    shifted candidate of their last applied command instead: robot id → the step of that
    command (< ``step``).  At most MAX_ROBOTS robots."""
    braked: dict[str, int] = field(default_factory=dict)
    """Robots braked over ``step`` instead: robot id → the step of the last applied command,
    −1 if none (< ``step``)."""

    @classmethod
    def _check(cls, d: dict[str, Any]) -> dict[str, Any]:
        step = _int(d["step"], "step")
        return {
            "step": step,
            "fallback": _steps_by_robot(d["fallback"], "fallback", 0, step - 1),
            "braked": _steps_by_robot(d["braked"], "braked", -1, step - 1),
        }


def _other(v: Any, me: Any, name: str) -> str:
    """A plan's field ``name`` that names another robot (``blocked``, ``no_room``): "" or
    another robot's id."""
    if v == "":
        return ""
    rid = _str(v, name, ROBOT_ID)
    if rid == me:
        raise WireError(f"{name}: names the plan's own robot")
    return rid


def _discs(v: Any, me: Any) -> dict[str, Disc]:
    """A map robot id (never ``me``) → :data:`Disc` (at most MAX_ROBOTS entries: :func:`decode`'s
    map limit)."""
    if type(v) is not dict:
        raise WireError("discs: expected a map of robot ids to discs")
    out: dict[str, Disc] = {}
    for r, disc in v.items():
        rid = _str(r, "discs", ROBOT_ID)
        if rid == me:
            raise WireError("discs: names the plan's own robot")
        if type(disc) is not list or len(disc) != 5:
            raise WireError("discs: expected [kind, rest, x, y, radius]")
        kind, rest, x, y, radius = disc
        if kind not in DISC_KINDS:
            raise WireError("discs: unknown kind")
        if not isinstance(rest, bool) or (rest and kind not in ("dead", "braked")):
            raise WireError("discs: rest: expected a boolean, true only for a dead or braked robot")
        x, y, radius = _num(x, "discs"), _num(y, "discs"), _num(radius, "discs")
        if max(abs(x), abs(y)) > MAX_MAGNITUDE or not 0.0 < radius <= MAX_MAGNITUDE:
            raise WireError("discs: a centre or radius out of range")
        out[rid] = (kind, rest, x, y, radius)
    return out


def _steps_by_robot(v: Any, name: str, lo: int, hi: int) -> dict[str, int]:
    """A map robot id → step in lo..hi (at most MAX_ROBOTS entries: :func:`decode`'s map limit)."""
    if type(v) is not dict:
        raise WireError(f"{name}: expected a map of robot ids to steps")
    return {_str(r, name, ROBOT_ID): _int(s, name, lo, hi) for r, s in v.items()}


@dataclass(frozen=True)
class Digest(Message):
    """Tracker → agents (``--exchange relay``): the plans of one step, in one message.

    The tracker already receives every plan; relaying them lets each agent take
    one message a step instead of n − 1 (docs/design.md, "Relayed
    plans").  Row i is robot ``ids[i]``'s newest plan, of step ``steps[i]`` ≤
    ``step``, as the tracker received it on that robot's own key, with what a
    neighbour uses of it: the whole committed reference, footprint, precedence
    and goal.  A plan late for one digest is in the next: a neighbour then uses
    it as it would use a late plan on its own key.  The nominal
    plan, solver status and timing stay on ``fleet/F/plan/R`` for the supervisor.
    ``robot`` is the sender ("tracker")."""

    TYPE: ClassVar[str] = "digest"
    MAX_BYTES: ClassVar[int] = MAX_RELAYED * (MAX_HORIZON * 2 * 8 + 256)
    """A row per robot: its committed reference (at most MAX_HORIZON points of two float64)
    and, within 256 bytes, its id (≤ 32 characters), step, precedence, footprint, target and goal
    (test_wire.py packs the largest)."""
    step: int
    """The step k − 1 whose plans the digest is for (sent before tick k)."""
    Ts: float
    """Sampling period [s]."""
    ids: list[str] = field(compare=False)
    """Robot ids, (n,), distinct, 0 ≤ n ≤ MAX_RELAYED."""
    steps: list[int] = field(compare=False)
    """Step at which each plan was committed, (n,), each ≤ ``step``."""
    priority: list[int] = field(compare=False)
    rank: list[int] = field(compare=False)
    phase: list[int] = field(compare=False)
    phase_age: list[int] = field(compare=False)
    """Per robot, (n,) each: as in :class:`Plan`."""
    footprint: NDArray[np.float64] = field(compare=False)
    """Footprint radii r_i, (n,) [m]."""
    committed: NDArray[np.float64] = field(compare=False)
    """Committed references ỹ_{k+1} … ỹ_{k+N}, (n, N, 2) [m], world frame."""
    target: NDArray[np.float64] = field(compare=False)
    goal: NDArray[np.float64] = field(compare=False)
    """Navigation waypoints and goals, (n, 2) each [m], world frame."""

    @classmethod
    def of(cls, sender: str, step: int, Ts: float, horizon: int, plans: list[Plan]) -> Digest:
        """The digest of ``plans``: each of step ≤ ``step``, committing ``horizon``
        points, at most MAX_RELAYED of them (none is a valid digest)."""
        n = len(plans)
        return cls(
            robot=sender, step=step, Ts=Ts, ids=[p.robot for p in plans], steps=[p.step for p in plans],
            priority=[p.priority for p in plans], rank=[p.rank for p in plans],
            phase=[p.phase for p in plans], phase_age=[p.phase_age for p in plans],
            footprint=np.array([p.footprint for p in plans], float),
            committed=np.array([p.committed for p in plans], float).reshape(n, horizon, 2),
            target=np.array([p.target for p in plans], float).reshape(n, 2),
            goal=np.array([p.goal for p in plans], float).reshape(n, 2),
        )  # fmt: skip

    def plans(self) -> list[Plan]:
        """The relayed plans.  They carry no nominal plan (shape (0, 2)), status
        ``"relayed"``, solve time 0, ``tube_ok`` True, ``late`` 0, no discs and no blocker: a
        neighbour does not use those."""
        empty = np.zeros((0, 2))
        Ts, fp = self.Ts, self.footprint.tolist()
        out: list[Plan] = []
        for i, (rid, k) in enumerate(zip(self.ids, self.steps, strict=True)):
            plan = _checked(
                Plan, robot=rid, step=k, t0=(k + 1) * Ts, Ts=Ts, committed=self.committed[i], nominal=empty,
                footprint=fp[i], priority=self.priority[i], rank=self.rank[i], phase=self.phase[i],
                phase_age=self.phase_age[i], target=self.target[i], goal=self.goal[i], status="relayed",
                solve_time=0.0, tube_ok=True, late=0, discs={}, blocked="", no_room="",
            )  # fmt: skip
            out.append(plan)
        return out

    @classmethod
    def _check(cls, d: dict[str, Any]) -> dict[str, Any]:
        Ts = _num(d["Ts"], "Ts")
        if not 0 < Ts <= 10:
            raise WireError("Ts: outside (0, 10] s")
        ids = d["ids"]
        if type(ids) is not list:
            raise WireError("ids: expected a list")
        n = len(ids)
        ids = [_str(r, "ids", ROBOT_ID) for r in ids]
        if len(set(ids)) != n:
            raise WireError("ids: a robot appears twice")
        step = _int(d["step"], "step")
        cols: dict[str, list[int]] = {}
        for name, lo, hi in (
            ("steps", 0, step), ("priority", -(2**31), 2**31), ("rank", 0, 2**31), ("phase", 0, WAITING),
            ("phase_age", 0, MAX_AGE),
        ):  # fmt: skip
            col = d[name]
            if type(col) is not list or len(col) != n:
                raise WireError(f"{name}: expected a list of {n} integers")
            cols[name] = [_int(v, name, lo, hi) for v in col]
        fp = decode_array(d["footprint"], "footprint", (n,))
        if not (fp > 0).all() or not (fp <= 10).all():
            raise WireError("footprint: outside (0, 10] m")
        return {
            "step": step,
            "Ts": Ts,
            "ids": ids,
            **cols,
            "footprint": fp,
            "committed": decode_array(d["committed"], "committed", (n, None, 2)),
            "target": decode_array(d["target"], "target", (n, 2)),
            "goal": decode_array(d["goal"], "goal", (n, 2)),
        }


@dataclass(frozen=True)
class Wheels(Message):
    """``epuck_link`` → all: wheel odometry from the robot's encoders.

    The link reads the int16 encoders, which wrap, and unwraps them into
    cumulative counts; the speeds come from the count deltas over the reads
    of the last ≈ 0.1 s."""

    TYPE: ClassVar[str] = "wheels"
    seq: int
    """Number of the encoder read since the link started."""
    t: float
    """Time of the read [s] since the link process started (monotonic clock)."""
    left_steps: int
    right_steps: int
    """Unwrapped cumulative encoder counts [steps] (1000 per wheel revolution)."""
    v: float
    """Forward speed of the axle centre [m/s] from the count deltas."""
    omega: float
    """Turn rate [rad/s], counter-clockwise, from the count deltas."""

    @classmethod
    def _check(cls, d: dict[str, Any]) -> dict[str, Any]:
        return {
            "seq": _int(d["seq"], "seq"),
            "t": _num(d["t"], "t"),
            "left_steps": _int(d["left_steps"], "left_steps", -(2**62), 2**62),
            "right_steps": _int(d["right_steps"], "right_steps", -(2**62), 2**62),
            "v": _num(d["v"], "v"),
            "omega": _num(d["omega"], "omega"),
        }


@dataclass(frozen=True)
class Applied(Message):
    """``epuck_link`` → tracker: what the robot side applied over step ``step``, decided when
    the step's command came in time, else at that step's deadline (``--deadline``·Ts after the
    link received tick ``step``).

    The camera tracker, and the tracker of emulated robots, put it in the next tick
    (:attr:`Tick.fallback`, :attr:`Tick.braked`; with delay compensation, in the step's
    :class:`Outcome` first), so that the agent takes the same
    candidate and its neighbours skip the plan that was never executed, as with
    simulated robots (docs/design.md, "Missed deadlines")."""

    TYPE: ClassVar[str] = "applied"
    step: int
    last: int
    """The step of the last command applied, −1 if none, ≤ ``step``: ``step`` itself when the
    command of this step came in time; otherwise the robot followed that command's candidate
    over this step, or braked."""
    braked: bool
    """The robot was braked over this step instead (dead or silent agent, nothing to follow)."""

    @classmethod
    def _check(cls, d: dict[str, Any]) -> dict[str, Any]:
        if not isinstance(d["braked"], bool):
            raise WireError("braked: expected a boolean")
        step = _int(d["step"], "step")
        last = _int(d["last"], "last", -1, step)
        if last == step and d["braked"]:
            raise WireError("braked: a step whose command was applied")
        if last < 0 and not d["braked"]:
            raise WireError("last: no command applied, so nothing to follow: braked must be true")
        return {"step": step, "last": last, "braked": d["braked"]}

    @property
    def on_time(self) -> bool:
        """The command of this step was applied."""
        return self.last == self.step


@dataclass(frozen=True)
class LinkState(Message):
    """``epuck_link`` → all, on ``fleet/F/link/R``: the radio link to the robot is down (or up
    again).  The firmware has no deadman: while the link is down the robot drives on at the
    wheel speeds it last received, uncontrolled.  Sent at once when the link is lost, and at
    every tick, down or up, with the newest camera pose (one lost message never sticks).

    The neighbours keep clear of a robot whose link is down as of a moving obstacle: a disc
    about its newest measured controlled point, grown by ``speed`` for every second since that
    pose (docs/method.md §6.4).  They go on doing so after the link is back, until they have
    a plan of that robot's of step ``back`` or later: the plans before were made for a robot
    that was not following them."""

    TYPE: ClassVar[str] = "link"
    up: bool
    """The link is up (again): the robot took a zero-speed command and stands."""
    step: int
    """The newest tick the link had received, −1 before the first."""
    lost: int
    """The newest tick when the link was last lost (−1: never lost)."""
    back: int
    """The first step whose plan of this robot's is made from where it stands after the
    outage: its agent starts again then (−1: never lost, or still down)."""
    left: int
    right: int
    """Wheel speeds [steps/s] the robot may drive on at: of the last command confirmed or the
    one whose reply was lost, whichever moves the controlled point faster."""
    speed: float
    """Speed [m/s] of the robot's controlled point at those wheel speeds (a bound on how fast it
    moves while uncontrolled)."""
    seq: int
    """Sequence number of the newest camera pose below (−1: none yet)."""
    x: float
    y: float
    """Newest measured position of the controlled point [m], world frame (0 when ``seq`` is −1)."""

    @classmethod
    def _check(cls, d: dict[str, Any]) -> dict[str, Any]:
        if not isinstance(d["up"], bool):
            raise WireError("up: expected a boolean")
        speed = _num(d["speed"], "speed")
        if not 0.0 <= speed <= 10.0:
            raise WireError("speed: outside [0, 10] m/s")
        return {
            "up": d["up"],
            "step": _int(d["step"], "step", -1),
            "lost": _int(d["lost"], "lost", -1),
            "back": _int(d["back"], "back", -1),
            "left": _int(d["left"], "left", -32768, 32767),
            "right": _int(d["right"], "right", -32768, 32767),
            "speed": speed,
            "seq": _int(d["seq"], "seq", -1),
            "x": _num(d["x"], "x"),
            "y": _num(d["y"], "y"),
        }


MESSAGES: dict[str, type[Message]] = {
    m.TYPE: m
    for m in (Pose, Truth, Odom, Plan, Command, Goal, Script, Tick, Digest, Wheels, Applied, LinkState)
}


def decode(payload: bytes, expected: type[M], robot: str | None = None) -> M:
    """Decode ``payload`` as message type ``expected``.

    ``robot``, when given, is the id the key names: a message claiming another
    id is rejected.  Raises :class:`WireError` and nothing else."""
    if not isinstance(payload, bytes | bytearray | memoryview):
        raise WireError("payload: not bytes")
    if len(payload) > expected.MAX_BYTES:
        raise WireError(f"payload: {len(payload)} bytes exceeds {expected.MAX_BYTES}")
    try:
        d = msgpack.unpackb(
            payload, raw=False, strict_map_key=True, max_bin_len=expected.MAX_BYTES, max_str_len=4096,
            max_array_len=MAX_ROBOTS, max_map_len=MAX_ROBOTS,
        )  # fmt: skip
    except (ValueError, TypeError, OverflowError) as e:  # msgpack's errors for garbage
        raise WireError(f"payload: not msgpack ({type(e).__name__})") from None
    if not isinstance(d, dict):
        raise WireError("payload: not a map")
    if type(d.get("schema")) is not int or d["schema"] != SCHEMA_VERSION:
        raise WireError(f"schema: version {_short(repr(d.get('schema')))}, expected {SCHEMA_VERSION}")
    if d.get("type") != expected.TYPE:
        raise WireError(f"type: {d.get('type')!r}, expected {expected.TYPE!r}")
    names = _names(expected)
    if d.keys() != names:
        keys = set(d) - {"schema", "type"}
        got = names - {"schema", "type"}
        missing, extra = sorted(got - keys), sorted(map(str, keys - got))
        raise WireError(f"fields: missing {missing}, unknown {extra}")
    rid = _str(d["robot"], "robot", ROBOT_ID)
    if robot is not None and rid != robot:
        raise WireError(f"robot: message claims {rid!r} on the key of {robot!r}")
    try:
        checked = expected._check(d)
    except WireError:
        raise
    except (TypeError, ValueError, KeyError, OverflowError) as e:
        raise WireError(f"payload: {type(e).__name__}") from None
    return expected(robot=rid, **checked)


_NAMES: dict[type[Message], frozenset[str]] = {}


def _names(cls: type[Message]) -> frozenset[str]:
    """The keys of a valid ``cls`` map: its fields, "schema" and "type" (cached)."""
    got = _NAMES.get(cls)
    if got is None:
        got = _NAMES[cls] = _field_names(cls)[1] | {"schema", "type"}
    return got


def _checked(cls: type[M], **values: Any) -> M:
    """A ``cls`` of values already checked, made without the dataclass ``__init__``.

    Every field must be given (a ``ValueError`` otherwise).  A frozen dataclass's
    ``__init__`` sets each field through ``object.__setattr__``, and an agent takes
    n − 1 relayed plans a step."""
    expected = _field_names(cls)[1]
    if values.keys() != expected:
        raise ValueError(f"{cls.__name__}: fields {sorted(values)}, expected {sorted(expected)}")
    msg = object.__new__(cls)
    msg.__dict__.update(values)
    return msg


def _short(text: str, limit: int = 160) -> str:
    """``text`` made safe for one log line: escaped (a key or field may carry
    newlines or control characters) and cut to ``limit`` characters."""
    safe = text.encode("unicode_escape").decode("ascii")
    return safe if len(safe) <= limit else safe[: limit - 1] + "…"


class RejectCounter:
    """Counts rejected payloads per (source, reason); reports each source once.

    Sources are chosen by the sender (any key under a subscription), so at
    most ``max_sources`` distinct ones are reported and kept apart; the rest
    are counted together under ``"(other sources)"`` with one last line."""

    OTHER = "(other sources)"

    def __init__(self, report: Any = None, max_sources: int = 32):
        self.counts: dict[tuple[str, str], int] = {}
        self._reported: set[str] = set()
        self._report = report
        self.max_sources = max_sources

    def reject(self, source: str, err: WireError) -> None:
        """Count one payload from ``source`` (its key) rejected with ``err``, by source and
        the field its reason names; report the first rejection of each source.  Past ``max_sources``
        sources, the others are counted together under :attr:`OTHER`."""
        if source not in self._reported and len(self._reported) >= self.max_sources:
            if self.OTHER not in self._reported and self._report is not None:
                self._report(
                    f"rejected payloads from more than {self.max_sources} keys; further sources are counted"
                )
            self._reported.add(self.OTHER)
            source = self.OTHER
        key = (source, _short(err.reason.split(":", 1)[0], 64))
        self.counts[key] = self.counts.get(key, 0) + 1
        if source not in self._reported:
            self._reported.add(source)
            if self._report is not None:
                src, why = _short(source), _short(err.reason)
                self._report(f"rejected payload from {src}: {why} (further rejections are counted)")

    @property
    def total(self) -> int:
        """Payloads rejected so far, every source and reason."""
        return sum(self.counts.values())
