"""Hostile-payload generators for the fuzz tests (``tests/system/test_fuzz_live.py``).

``Generator(name, rng).make(robot)`` returns one :class:`Payload` aimed at the decoder of the
message type ``name`` (``pose``, ``truth``, ``odom``, ``plan``, ``cmd``, ``goal``, ``script``,
``tick``, ``wheels``, ``digest``, ``applied``, ``link``) on the key of robot ``robot``. Every
*kind* but two builds a payload that the wire contract (``ground/wire.py``) rejects by
construction (``strict``): garbage that is not msgpack, msgpack that is not a map, a wrong
schema version or message type, missing or extra fields, NaN/±inf in a number or inside an
array, a wrong array dtype, shape or byte length, a huge declared shape, a bad list (the
digest's columns: wrong length, element type or range, a repeated or malformed id), a bad map of
goals (a goal's batch: a bad or own id, a bad point, too many), a bool where an int is expected,
an int out of range, a too-long or malformed string, a payload over ``MAX_PAYLOAD``, a message
of another type, and a message (realistic, otherwise valid) claiming another robot's id. The two
random kinds (``garbage``: random bytes, ``mutate``: byte flips of a valid message) may produce
a valid message by chance; the caller drops those (a valid message is not a malformed one:
hostile *valid* messages are a matter for access control, not for the decoders)."""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, fields
from typing import Any

import msgpack
import numpy as np

from ground.wire import (
    MAX_BATCH,
    MAX_HORIZON,
    MAX_PAYLOAD,
    MAX_RELAYED,
    MAX_ROBOTS,
    SCHEMA_VERSION,
    WAITING,
    Applied,
    Command,
    Digest,
    Goal,
    LinkState,
    Message,
    Odom,
    Outcome,
    Plan,
    Pose,
    Script,
    Tick,
    Truth,
    Wheels,
)

TYPES: dict[str, type[Message]] = {m.TYPE: m for m in (Pose, Truth, Odom, Plan, Command, Goal, Script, Tick)}
TYPES |= {m.TYPE: m for m in (Outcome, Wheels, Digest, Applied, LinkState)}
NAMES = tuple(TYPES)

_SEQ = (0, 2**62)
FLOATS: dict[str, tuple[str, ...]] = {
    "pose": ("t", "x", "y", "theta"),
    "truth": ("t", "x", "y", "theta"),
    "odom": ("t", "vx", "vy"),
    "plan": ("t0", "Ts", "footprint", "solve_time"),
    "cmd": ("ax", "ay"),
    "goal": (),
    "script": (),
    "tick": ("t",),
    "outcome": (),
    "wheels": ("t", "v", "omega"),
    "digest": ("Ts",),
    "applied": (),
    "link": ("speed", "x", "y"),
}
"""Number fields (int or float accepted, finite)."""
INTS: dict[str, dict[str, tuple[int, int]]] = {
    "pose": {"seq": _SEQ},
    "truth": {"seq": _SEQ},
    "odom": {"seq": _SEQ},
    "plan": {
        "step": _SEQ,
        "priority": (-(2**31), 2**31),
        "rank": (0, 2**31),
        "phase": (0, WAITING),
        "phase_age": (0, 2**31),
        "late": (0, 2**31),
    },
    "cmd": {"step": _SEQ},
    "goal": {},
    "script": {"step": (-1, 2**62)},
    "tick": {"step": _SEQ, "misses": _SEQ},
    "outcome": {"step": _SEQ},
    "wheels": {"seq": _SEQ, "left_steps": (-(2**62), 2**62), "right_steps": (-(2**62), 2**62)},
    "digest": {"step": _SEQ},
    "applied": {"step": _SEQ, "last": (-1, 2**62)},
    "link": {
        "step": (-1, 2**62),
        "lost": (-1, 2**62),
        "back": (-1, 2**62),
        "seq": (-1, 2**62),
        "left": (-32768, 32767),
        "right": (-32768, 32767),
    },
}
"""Integer fields and their accepted closed ranges."""
BOOLS: dict[str, tuple[str, ...]] = {
    "plan": ("tube_ok",), "tick": ("stop",), "cmd": ("fallback", "brake"), "applied": ("braked",),
    "link": ("up",),
    "script": ("stop",),
}  # fmt: skip
ARRAYS: dict[str, dict[str, tuple[int | None, ...]]] = {
    "plan": {"committed": (None, 2), "nominal": (None, 2), "target": (2,), "goal": (2,)},
    "goal": {"goal": (2,)},
    "cmd": {"x_next": (4,), "v_next": (None, 2), "K": (2, 4)},
    "digest": {"footprint": ("n",), "committed": ("n", None, 2), "target": ("n", 2), "goal": ("n", 2)},
}
"""Array fields and their shapes (None: 1..MAX_HORIZON; "n": the digest's number of robots)."""
LISTS: dict[str, dict[str, tuple[int, int] | None]] = {
    "digest": {
        "ids": None,
        "steps": (0, -1),
        "priority": (-(2**31), 2**31),
        "rank": (0, 2**31),
        "phase": (0, WAITING),
        "phase_age": (0, 2**31),
    },
}
"""List fields, one entry per relayed robot: robot ids (None), or integers in a closed range
(``steps``: 0 … the digest's step, written −1)."""
STRINGS: dict[str, dict[str, int]] = {"plan": {"status": 64, "blocked": 32, "no_room": 32}}
"""Free-text fields and their longest accepted length (``blocked``, ``no_room``: a robot id or "")."""
DISC_MAPS: dict[str, tuple[str, ...]] = {"plan": ("discs",)}
"""Maps robot id (never the message's own robot) → [kind, at rest, x, y, radius] (a plan's discs)."""
MAPS: dict[str, dict[str, int]] = {
    "tick": {"fallback": 0, "braked": -1},
    "outcome": {"fallback": 0, "braked": -1},
}
"""Maps robot id → step, and the smallest step each accepts (the largest is the message's step,
less one for an outcome)."""
POINT_MAPS: dict[str, tuple[str, ...]] = {"goal": ("batch",)}
"""Maps robot id → point (2,) [m], never the message's own robot, at most MAX_BATCH entries."""
OPEN_RANGES: dict[str, dict[str, tuple[float, float]]] = {
    "plan": {"Ts": (0.0, 10.0), "footprint": (0.0, 10.0)},
    "digest": {"Ts": (0.0, 10.0)},
}
"""Number fields that must lie in (lo, hi]."""
CLOSED_RANGES: dict[str, dict[str, tuple[float, float]]] = {"link": {"speed": (0.0, 10.0)}}
"""Number fields that must lie in [lo, hi]."""

POOL = 64
"""Realistic valid messages per robot that the malformations start from."""
OTHER_IDS = ("r1", "r2", "r3", "r9", "tracker", "supervisor")
"""Ids a message may falsely claim."""

_NAN_BITS = (
    struct.pack("<d", math.nan),
    struct.pack("<Q", 0x7FF0000000000001),  # signalling NaN
    struct.pack("<Q", 0xFFF8000000000000),  # negative quiet NaN
    struct.pack("<Q", 0x7FFFFFFFFFFFFFFF),  # all-ones payload NaN
    struct.pack("<d", math.inf),
    struct.pack("<d", -math.inf),
)
_MISSING = object()


def field_names(name: str) -> set[str]:
    """Fields of message type ``name`` (the dataclass), without ``schema`` and ``type``."""
    return {f.name for f in fields(TYPES[name])}


def table_names(name: str) -> set[str]:
    """Fields the tables above describe for ``name`` (must equal :func:`field_names`)."""
    return (
        {"robot"}
        | set(FLOATS[name])
        | set(INTS[name])
        | set(BOOLS.get(name, ()))
        | set(ARRAYS.get(name, {}))
        | set(STRINGS.get(name, {}))
        | set(MAPS.get(name, {}))
        | set(POINT_MAPS.get(name, ()))
        | set(DISC_MAPS.get(name, ()))
        | set(LISTS.get(name, {}))
    )


@dataclass(frozen=True)
class Payload:
    data: bytes
    kind: str
    strict: bool
    """Invalid by construction: a decoder that accepts it is wrong."""


def _pack(obj: Any, single: bool = False) -> bytes:
    return bytes(msgpack.packb(obj, use_bin_type=True, use_single_float=single))


def _arr(a: np.ndarray, dtype: str = "<f8") -> dict[str, Any]:
    a = np.ascontiguousarray(a, dtype=np.dtype(dtype))
    return {"dtype": dtype, "shape": list(a.shape), "data": a.tobytes()}


def realistic(name: str, robot: str, rng: np.random.Generator) -> Message:
    """A valid message of type ``name`` from ``robot`` with plausible content (never sent as is)."""
    k = int(rng.integers(0, 400))
    t = 0.1 * k
    u = lambda lo, hi: float(rng.uniform(lo, hi))  # noqa: E731
    if name in ("pose", "truth"):
        return (Pose if name == "pose" else Truth)(
            robot=robot, seq=k, t=t, x=u(-0.9, 0.9), y=u(-0.9, 0.9), theta=u(-math.pi, math.pi)
        )
    if name == "odom":
        return Odom(robot=robot, seq=k, t=t, vx=u(-0.13, 0.13), vy=u(-0.13, 0.13))
    if name == "cmd":
        return Command(
            robot=robot, step=k, ax=u(-0.3, 0.3), ay=u(-0.3, 0.3), fallback=True,
            x_next=rng.uniform(-0.7, 0.7, 4), v_next=rng.uniform(-0.3, 0.3, (20, 2)),
            K=rng.uniform(-50.0, 0.0, (2, 4)),
        )  # fmt: skip
    if name == "goal":
        others = [r for r in OTHER_IDS[:4] if r != robot][: int(rng.integers(0, 4))]
        batch = {r: rng.uniform(-0.7, 0.7, 2) for r in others}
        return Goal(robot=robot, goal=rng.uniform(-0.7, 0.7, 2), batch=batch)
    if name == "script":
        return Script(robot=robot, step=k - 1, stop=bool(rng.random() < 0.2))
    if name == "tick":
        late = {r: max(0, k - int(rng.integers(1, 4))) for r in OTHER_IDS[: int(rng.integers(0, 3))]}
        return Tick(
            robot=robot, step=k, t=t, stop=False, misses=int(rng.integers(0, 3)), fallback=late,
            braked={"r9": -1} if rng.random() < 0.3 else {},
        )  # fmt: skip
    if name == "outcome":
        late = {r: max(0, k - int(rng.integers(1, 4))) for r in OTHER_IDS[: int(rng.integers(0, 3))]}
        braked = {"r9": -1} if rng.random() < 0.3 else {}
        return Outcome(robot=robot, step=max(k, 1), fallback=late, braked=braked)
    if name == "applied":
        last = k - int(rng.integers(0, 4))
        return Applied(
            robot=robot, step=k, last=max(last, -1), braked=last < 0 or (last < k and rng.random() < 0.3)
        )
    if name == "link":
        lost = max(k - int(rng.integers(0, 20)), 0)
        up = bool(rng.random() < 0.5)
        return LinkState(
            robot=robot, up=up, step=k, lost=lost, back=k + 2 if up else -1,
            left=int(rng.integers(-1000, 1001)), right=int(rng.integers(-1000, 1001)), speed=u(0.0, 0.16),
            seq=k - 1, x=u(-0.9, 0.9), y=u(-0.9, 0.9),
        )  # fmt: skip
    if name == "digest":
        plans = [realistic("plan", r, rng) for r in ("r1", "r2", "r3")[: int(rng.integers(1, 4))]]
        step = max(pl.step for pl in plans) + int(rng.integers(0, 3))
        return Digest.of(robot, step, 0.1, 20, plans)
    if name == "wheels":
        return Wheels(
            robot=robot, seq=k, t=t, left_steps=int(rng.integers(-(10**5), 10**5)),
            right_steps=int(rng.integers(-(10**5), 10**5)), v=u(-0.13, 0.13), omega=u(-4, 4),
        )  # fmt: skip
    n = 20
    start = rng.uniform(-0.7, 0.7, 2)
    path = start + np.cumsum(rng.uniform(-0.01, 0.01, (n + 1, 2)), axis=0)
    return Plan(
        robot=robot, step=k, t0=t + 0.1, Ts=0.1, committed=path[1:], nominal=path, footprint=0.134,
        priority=int(rng.integers(0, 3)), rank=int(rng.integers(0, 3)), phase=int(rng.integers(0, 3)),
        phase_age=int(rng.integers(0, 500)), target=path[-1].copy(), goal=rng.uniform(-0.7, 0.7, 2),
        status="PROXQP_SOLVED", solve_time=u(1e-4, 2e-3), tube_ok=True, late=int(rng.integers(0, 50)),
        discs={
            r: (kind, kind in ("dead", "braked") and bool(rng.random() < 0.5), u(-0.9, 0.9), u(-0.9, 0.9),
                u(0.13, 0.6))
            for r in ("r7", "r8")[: int(rng.integers(0, 3))]
            for kind in [str(rng.choice(["stale", "dead", "braked", "loose"]))]
        },
        blocked=str(rng.choice(["", "r7"])),
        no_room=str(rng.choice(["", "r8"])),
    )  # fmt: skip


class Generator:
    """Seeded payloads for message type ``name``; see the module docstring."""

    def __init__(self, name: str, rng: np.random.Generator):
        self.name = name
        self.rng = rng
        self.typ = TYPES[name]
        self.floats = FLOATS[name]
        self.ints = INTS[name]
        self.bools = BOOLS.get(name, ())
        self.arrays = ARRAYS.get(name, {})
        self.strings = STRINGS.get(name, {})
        self.maps = MAPS.get(name, {})
        self.points = POINT_MAPS.get(name, ())
        self.discs = DISC_MAPS.get(name, ())
        self.lists = LISTS.get(name, {})
        kinds: dict[str, float] = {
            "garbage": 2.0,
            "mutate": 2.0,
            "truncate": 1.0,
            "oversize": 0.15,
            "not_map": 1.0,
            "schema": 1.0,
            "type": 1.0,
            "fields": 1.0,
            "nonfinite": 1.5,
            "wrong_type": 1.5,
            "int_range": 1.0,
            "bool_int": 1.0,
            "strings": 1.0,
            "cross_type": 0.5,
            "claims": 1.5 if name == "plan" else 0.7,
        }
        if self.arrays:
            kinds |= {"array_nonfinite": 1.5, "array_shape": 1.5, "array_huge": 1.0, "array_dtype": 1.0}
        if name in OPEN_RANGES or name in CLOSED_RANGES:
            kinds["float_range"] = 1.0
        if self.maps:
            kinds["map_bad"] = 1.5
        if self.points:
            kinds["point_map_bad"] = 1.5
        if self.discs:
            kinds["disc_map_bad"] = 1.5
        if self.lists:
            kinds["list_bad"] = 3.0
        if not self.floats:
            del kinds["nonfinite"]  # Goal: its only numbers are inside the array
        if not self.ints:
            del kinds["int_range"]
        self._pool: dict[str, list[dict[str, Any]]] = {}
        self.kinds = list(kinds)
        w = np.cumsum(list(kinds.values()))
        self.cumulative = w / w[-1]

    # ------------------------------------------------------------ helpers
    def choice(self, seq: Any) -> Any:
        return seq[int(self.rng.integers(len(seq)))]

    def base(self, robot: str) -> dict[str, Any]:
        """A realistic valid message of ``robot`` as a map (one of a pool of POOL per robot)."""
        pool = self._pool.get(robot)
        if pool is None:
            pool = self._pool[robot] = [
                msgpack.unpackb(realistic(self.name, robot, self.rng).encode(), raw=False)
                for _ in range(POOL)
            ]
        return dict(pool[int(self.rng.integers(POOL))])

    def make(self, robot: str | None, kind: str | None = None) -> Payload:
        """One payload for a key of ``robot`` (None: the clock key, no id check)."""
        if kind is None:
            kind = self.kinds[
                min(int(np.searchsorted(self.cumulative, self.rng.random())), len(self.kinds) - 1)
            ]
        if kind == "claims" and robot is None:
            kind = "fields"  # the clock key names no robot: nothing to claim
        sender = robot if robot is not None else "tracker"
        data, strict = getattr(self, "_" + kind)(self.base(sender), sender)
        return Payload(data if isinstance(data, bytes) else _pack(data), kind, strict)

    # -------------------------------------------------------------- kinds
    def _garbage(self, d: dict[str, Any], robot: str) -> tuple[bytes, bool]:
        r = self.rng.random()
        n = 0 if r < 0.05 else int(self.rng.integers(1, 65)) if r < 0.6 else int(self.rng.integers(65, 4097))
        return self.rng.bytes(n), False

    def _mutate(self, d: dict[str, Any], robot: str) -> tuple[bytes, bool]:
        b = bytearray(_pack(d))
        how = int(self.rng.integers(4))
        if how == 0:  # byte flips
            for _ in range(int(self.rng.integers(1, 6))):
                b[int(self.rng.integers(len(b)))] = int(self.rng.integers(256))
        elif how == 1:  # a slice cut out
            i = int(self.rng.integers(len(b)))
            del b[i : i + int(self.rng.integers(1, 9))]
        elif how == 2:  # random bytes inserted
            i = int(self.rng.integers(len(b)))
            b[i:i] = self.rng.bytes(int(self.rng.integers(1, 9)))
        else:  # rotated
            i = int(self.rng.integers(1, len(b)))
            b = b[i:] + b[:i]
        return bytes(b), False

    def _truncate(self, d: dict[str, Any], robot: str) -> tuple[bytes, bool]:
        good = _pack(d)
        if self.rng.random() < 0.7:
            return good[: int(self.rng.integers(len(good)))], True  # incomplete msgpack
        return good + self.rng.bytes(int(self.rng.integers(1, 9))), True  # trailing data

    def _oversize(self, d: dict[str, Any], robot: str) -> tuple[bytes | dict[str, Any], bool]:
        how = int(self.rng.integers(3))
        if how == 0:
            return self.rng.bytes(self.typ.MAX_BYTES + 1 + int(self.rng.integers(0, 8192))), True
        if how == 1 and self.arrays:  # a well-formed array far longer than the horizon, > 64 KiB
            f = self.choice(list(self.arrays))
            rows = MAX_PAYLOAD // 16 + 1 + int(self.rng.integers(0, 512))
            cols = 2 if len(self.arrays[f]) == 2 else None
            shape = (rows, 2) if cols else (2 * rows,)
            return {**d, f: _arr(self.rng.uniform(-1, 1, shape))}, True
        return {**d, "pad": self.rng.bytes(MAX_PAYLOAD)}, True  # valid message + a 64 KiB extra field

    def _not_map(self, d: dict[str, Any], robot: str) -> tuple[bytes | Any, bool]:
        how = int(self.rng.integers(12))
        depth = int(self.rng.integers(2, 4000))
        options: list[Any] = [
            None, bool(self.rng.integers(2)), int(self.rng.integers(-(2**63), 2**63)), float("nan"),
            self.name, self.rng.bytes(int(self.rng.integers(0, 64))), list(d.values()), [d],
            msgpack.ExtType(int(self.rng.integers(0, 128)), self.rng.bytes(int(self.rng.integers(0, 16)))),
            msgpack.Timestamp(int(self.rng.integers(0, 2**32)), int(self.rng.integers(0, 10**9))),
            b"\x91" * depth + b"\xc0",  # nested one-element arrays (raw msgpack)
            b"\x81\xa1k" * depth + b"\xc0",  # nested one-entry maps (raw msgpack)
        ]  # fmt: skip
        obj = options[how]
        if how >= 10:
            return obj, True
        return _pack(obj), True

    def _schema(self, d: dict[str, Any], robot: str) -> tuple[dict[str, Any], bool]:
        bad = [
            _MISSING, 0, SCHEMA_VERSION + 1, -1, 255, 65536, 2**64 - 1, -(2**63), True, False, None,
            str(SCHEMA_VERSION), "v1", bytes([SCHEMA_VERSION]), float(SCHEMA_VERSION), 1.5, math.nan,
            math.inf, [SCHEMA_VERSION], {"version": SCHEMA_VERSION},
        ]  # fmt: skip
        v = self.choice(bad)
        d = dict(d)
        if v is _MISSING:
            del d["schema"]
        else:
            d["schema"] = v
        return d, True

    def _type(self, d: dict[str, Any], robot: str) -> tuple[dict[str, Any], bool]:
        others = [n for n in NAMES if n != self.name]
        bad = [
            *others,
            "",
            self.name.upper(),
            self.name + " ",
            None,
            1,
            True,
            self.name.encode(),
            [self.name],
        ]
        v = self.choice([_MISSING, *bad])
        d = dict(d)
        if v is _MISSING:
            del d["type"]
        else:
            d["type"] = v
        return d, True

    def _fields(self, d: dict[str, Any], robot: str) -> tuple[dict[Any, Any], bool]:
        names = sorted(field_names(self.name))
        how = int(self.rng.integers(6))
        d = dict(d)
        if how == 0:  # one or more fields missing
            for f in self.rng.choice(names, size=int(self.rng.integers(1, len(names) + 1)), replace=False):
                del d[str(f)]
        elif how == 1:  # unknown extra fields
            for _ in range(int(self.rng.integers(1, 4))):
                d[self.choice(["extra", "Robot", "seq2", "__class__", "robot ", "x" * 40])] = self.choice(
                    [0, 1.5, "x", None, b"\x00"]
                )
        elif how == 2:  # a field name as bytes instead of text
            f = self.choice(names)
            d[f.encode()] = d.pop(f)
        elif how == 3:  # nothing but the header
            d = {"schema": SCHEMA_VERSION, "type": self.name}
        elif how == 4:  # more entries than a message may have
            d |= {f"f{i}": i for i in range(70)}
        else:  # an integer map key (msgpack packs it; the decoder must not take it)
            return {7: 7, **d}, True
        return d, True

    def _nonfinite(self, d: dict[str, Any], robot: str) -> tuple[bytes, bool]:
        d = dict(d)
        chosen = self.rng.choice(
            self.floats, size=int(self.rng.integers(1, len(self.floats) + 1)), replace=False
        )
        for f in chosen:
            d[str(f)] = self.choice([math.nan, math.inf, -math.inf, -math.nan])
        return _pack(d, single=bool(self.rng.random() < 0.3)), True

    def _float_range(self, d: dict[str, Any], robot: str) -> tuple[dict[str, Any], bool]:
        ranges = {f: (lo, hi, True) for f, (lo, hi) in OPEN_RANGES.get(self.name, {}).items()}
        ranges |= {f: (lo, hi, False) for f, (lo, hi) in CLOSED_RANGES.get(self.name, {}).items()}
        f, (lo, hi, open_lo) = self.choice(list(ranges.items()))
        bad = [lo - 1e-9, -1.0, hi + 1e-6, hi + 1, 1e300, -1e300, 2**64 - 1, -(2**63)]
        if open_lo:
            bad += [lo, -0.0]
        d = dict(d)
        d[f] = self.choice([v for v in bad if not (lo < v <= hi if open_lo else lo <= v <= hi)])
        return d, True

    def _int_range(self, d: dict[str, Any], robot: str) -> tuple[dict[str, Any], bool]:
        f, (lo, hi) = self.choice(list(self.ints.items()))
        big = int(self.rng.integers(1, 2**62))
        options = [lo - 1, hi + 1, hi + big, 2.0, 1e3, 0.5, float(lo), 2**64 - 1]
        if lo - big >= -(2**63):
            options.append(lo - big)
        if lo > -(2**63):
            options.append(-(2**63))
        v = self.choice([o for o in options if isinstance(o, float) or not lo <= o <= hi])
        d = dict(d)
        d[f] = v
        return d, True

    def _bool_int(self, d: dict[str, Any], robot: str) -> tuple[dict[str, Any], bool]:
        d = dict(d)
        targets = [(f, "int") for f in self.ints] + [(f, "bool") for f in self.bools]
        if not targets:  # Goal: nothing integer or boolean; a bool where the array is expected
            d[self.choice(list(self.arrays))] = bool(self.rng.integers(2))
            return d, True
        f, what = self.choice(targets)
        d[f] = bool(self.rng.integers(2)) if what == "int" else self.choice([0, 1, None, "true", 1.0])
        return d, True

    def _wrong_type(self, d: dict[str, Any], robot: str) -> tuple[dict[str, Any], bool]:
        f = self.choice(sorted(field_names(self.name)))
        d = dict(d)
        generic = [
            "0.1", "", b"\x00" * 8, None, [], [0.1, 0.2], {}, {"dtype": "<f8"},
            msgpack.ExtType(1, b"x"), msgpack.Timestamp(1, 0),
        ]  # fmt: skip
        if f in self.arrays:
            a = d[f]
            v = self.choice([np.frombuffer(a["data"]).tolist(), None, "0.1,0.2", 0.5, a["data"], [a]])
        elif f in self.floats:
            v = self.choice(generic)
        elif f in self.ints:
            v = self.choice([*generic, str(d[f])])
        elif f in self.bools:
            v = self.choice([*generic, "true", "True"])
        elif f in self.maps:
            v = self.choice([None, "r1", 0, 1.5, True, b"\x00", [["r1", 0]], ["r1"]])
        elif f in self.points:
            pt = _arr(np.zeros(2))
            v = self.choice([None, "r2", 0, 1.5, True, b"\x00", [["r2", pt]], [pt]])
        elif f in self.lists:
            v = self.choice([None, "r1", 0, 1.5, True, b"\x00", {"0": d[f][0]}, _arr(np.zeros(len(d[f])))])
        elif f in self.discs:
            v = self.choice([None, "r1", 0, 1.5, True, b"\x00", [["r1", "dead"]], ["dead", True, 0, 0, 1]])
        else:  # robot, status, blocked: text fields
            v = self.choice([None, 1, 1.5, True, d[f].encode(), [d[f]], {"id": d[f]}])
        d[f] = v
        return d, True

    def _strings(self, d: dict[str, Any], robot: str) -> tuple[dict[str, Any], bool]:
        d = dict(d)
        if self.strings and self.rng.random() < 0.4:
            f, maxlen = self.choice(list(self.strings.items()))
            d[f] = "S" * self.choice([maxlen + 1, maxlen + 100, 4096, 5000])
            return d, True
        n = self.choice([33, 40, 100, 4096, 4097, 10_000])
        d["robot"] = self.choice(
            ["", robot * (n // len(robot) + 1), robot + "/x", robot + " ", " " + robot, robot + "\n",
             robot + "\x00", "ř" + robot, robot + ".", "*", "\u202e" + robot, robot + "\r\n"]
        )  # fmt: skip
        return d, True

    def _cross_type(self, d: dict[str, Any], robot: str) -> tuple[bytes, bool]:
        other = self.choice([n for n in NAMES if n != self.name])
        return realistic(other, robot, self.rng).encode(), True

    def _claims(self, d: dict[str, Any], robot: str) -> tuple[dict[str, Any], bool]:
        """A valid message with realistic content that claims another robot's id."""
        d = dict(d)
        d["robot"] = self.choice([r for r in OTHER_IDS if r != robot])
        return d, True

    def _map_bad(self, d: dict[str, Any], robot: str) -> tuple[dict[Any, Any], bool]:
        """A robot → step map with a bad entry, or not a map at all."""
        f, lo = self.choice(list(self.maps.items()))
        step = d["step"]
        bad_entries: list[tuple[Any, Any]] = [
            ("r1", lo - 1), ("r1", step + 1), ("r1", 2**63 - 1), ("r1", True), ("r1", 1.0), ("r1", None),
            ("r1", "3"), ("", 0), ("r/1", 0), ("x" * 33, 0), ("r1\n", 0), (b"r1", 0), (1, 0),
        ]  # fmt: skip
        how = int(self.rng.integers(3))
        d = dict(d)
        if how == 0:
            d[f] = self.choice([None, [], ["r1", 0], "r1", 0, [["r1", 0]], b"\x80"])
        else:
            d[f] = {**d[f], **dict([self.choice(bad_entries)])}
        return d, True

    def _point_map_bad(self, d: dict[str, Any], robot: str) -> tuple[dict[Any, Any], bool]:
        """A robot → point map (a goal's batch) with a bad entry, too many entries, or not a map."""
        f = self.choice(list(self.points))
        other = self.choice([r for r in OTHER_IDS if r != robot])
        good = _arr(self.rng.uniform(-0.7, 0.7, 2))
        bad_entries: list[tuple[Any, Any]] = [
            (robot, good), ("", good), ("r/2", good), ("x" * 33, good), ("r2\n", good), (b"r2", good),
            (other, None), (other, [0.1, 0.2]), (other, 0.5), (other, _arr(np.zeros(3))),
            (other, _arr(np.zeros((1, 2)))), (other, _arr(np.array([np.nan, 0.0]))),
            (other, _arr(np.array([0.0, np.inf]))), (other, _arr(np.zeros(2), "<i8")),
            (other, {**good, "shape": [3]}), (other, {**good, "data": good["data"][:-1]}),
        ]  # fmt: skip
        how = int(self.rng.integers(4))
        d = dict(d)
        if how == 0:
            d[f] = self.choice([None, [], [[other, good]], other, 0, 1.5, b"\x80", good])
        elif how == 1:  # more robots than a batch may name
            n = MAX_BATCH + 1 + int(self.rng.integers(0, 8))
            d[f] = {f"q{i}": good for i in range(n)}
        else:
            d[f] = {**d[f], **dict([self.choice(bad_entries)])}
        return d, True

    def _disc_map_bad(self, d: dict[str, Any], robot: str) -> tuple[dict[Any, Any], bool]:
        """A robot → disc map (a plan's discs) with a bad entry, too many entries, or not a map."""
        f = self.choice(list(self.discs))
        other = self.choice([r for r in OTHER_IDS if r != robot])
        good = ["dead", True, 0.1, -0.2, 0.3]
        bad_entries: list[tuple[Any, Any]] = [
            (robot, good), ("", good), ("r/2", good), ("x" * 33, good), (b"r2", good), (1, good),
            (other, None), (other, good[:4]), (other, [*good, 1.0]), (other, tuple(good[:3])),
            (other, ["gone", True, 0.1, 0.2, 0.3]), (other, [None, True, 0.1, 0.2, 0.3]),
            (other, ["dead", 1, 0.1, 0.2, 0.3]), (other, ["dead", None, 0.1, 0.2, 0.3]),
            (other, ["dead", False, math.nan, 0.2, 0.3]), (other, ["dead", False, 0.1, math.inf, 0.3]),
            (other, ["dead", False, 0.1, 0.2, 0.0]), (other, ["dead", False, 0.1, 0.2, -0.3]),
            (other, ["dead", False, 2e9, 0.2, 0.3]), (other, ["dead", False, 0.1, 0.2, 2e9]),
            (other, ["dead", False, "0.1", 0.2, 0.3]), (other, ["dead", False, 0.1, True, 0.3]),
            (other, {"kind": "dead"}),
        ]  # fmt: skip
        how = int(self.rng.integers(4))
        d = dict(d)
        if how == 0:
            d[f] = self.choice([None, [], [[other, good]], other, 0, 1.5, b"\x80", good])
        elif how == 1:  # more robots than a map may name
            d[f] = {f"q{i}": good for i in range(MAX_ROBOTS + 1 + int(self.rng.integers(0, 8)))}
        else:
            d[f] = {**d[f], **dict([self.choice(bad_entries)])}
        return d, True

    def _list_bad(self, d: dict[str, Any], robot: str) -> tuple[dict[str, Any], bool]:
        """A column of the digest (one entry per robot) that is not a list, one entry too many or
        too few, an entry of the wrong type, out of range or (ids) repeated or malformed; or
        more robots than a digest may carry, every column consistent."""
        f, bounds = self.choice(list(self.lists.items()))
        col = list(d[f])
        n = len(col)
        how = int(self.rng.integers(5))
        d = dict(d)
        i = int(self.rng.integers(n))
        if how == 0:
            d[f] = self.choice([None, 0, 1.5, "r1", b"\x00", {"0": col[0]}])
        elif how == 1:
            d[f] = col[:-1] if self.rng.random() < 0.5 else [*col, "r7" if bounds is None else col[-1]]
        elif how == 2:
            wrong: list[Any] = (
                [None, 1, 1.5, True, b"r1", ["r1"], {"id": "r1"}] if bounds is None
                else [None, 1.5, 2.0, True, False, "1", b"\x01", [1], {"a": 1}]
            )  # fmt: skip
            col[i] = self.choice(wrong)
            d[f] = col
        elif how == 3:
            if bounds is None:
                col[i] = self.choice(["", "r1/x", "r 1", "x" * 33, "r1\n", "*", *col[:i], *col[i + 1 :]])
            else:
                lo, hi = bounds[0], d["step"] if bounds[1] == -1 else bounds[1]
                col[i] = self.choice([lo - 1, hi + 1, hi + 2**40, -(2**63)])
            d[f] = col
        else:
            m = MAX_RELAYED + 1 + int(self.rng.integers(0, 8))
            reps = [j % n for j in range(m)]
            d["ids"] = [f"r{j + 1}" for j in range(m)]
            for name in ("steps", "priority", "rank", "phase", "phase_age"):
                d[name] = [d[name][j] for j in reps]
            for name in ("footprint", "committed", "target", "goal"):
                a = np.frombuffer(d[name]["data"]).reshape(d[name]["shape"])
                d[name] = _arr(a[reps])
        return d, True

    def _array_nonfinite(self, d: dict[str, Any], robot: str) -> tuple[dict[str, Any], bool]:
        f = self.choice(list(self.arrays))
        a = np.frombuffer(d[f]["data"]).copy()
        d = dict(d)
        if self.rng.random() < 0.3:  # single precision, NaN or inf as float32
            a = a.astype(np.float32)
            for i in self.rng.choice(
                a.size, size=int(self.rng.integers(1, min(4, a.size) + 1)), replace=False
            ):
                a[int(i)] = self.choice([np.nan, np.inf, -np.inf])
            d[f] = {"dtype": "<f4", "shape": d[f]["shape"], "data": a.tobytes()}
            return d, True
        raw = bytearray(a.tobytes())
        for i in self.rng.choice(a.size, size=int(self.rng.integers(1, min(4, a.size) + 1)), replace=False):
            raw[8 * int(i) : 8 * int(i) + 8] = self.choice(_NAN_BITS)
        d[f] = {**d[f], "data": bytes(raw)}
        return d, True

    def _array_shape(self, d: dict[str, Any], robot: str) -> tuple[dict[str, Any], bool]:
        f = self.choice(list(self.arrays))
        spec = self.arrays[f]
        a = dict(d[f])
        shape = list(a["shape"])
        how = int(self.rng.integers(10))
        if how == 0:  # wrong number of dimensions
            a["shape"] = self.choice(
                [[], [*shape, 1], [1, *shape]] + ([[math.prod(shape)]] if len(spec) >= 2 else [])
            )
        elif how == 1:  # wrong last dimension, same data
            wrong = [n for n in (1, 2, 3, 4, 5) if n != shape[-1]]
            a["shape"] = [*shape[:-1], self.choice(wrong)]
        elif how == 2:  # zero or negative dimension
            a["shape"] = [self.choice([0, -1, -shape[0]]), *shape[1:]]
        elif how == 3:  # dimensions that are not integers
            a["shape"] = [self.choice([float(shape[0]), True, str(shape[0]), None]), *shape[1:]]
        elif how == 4:  # shape not a list
            a["shape"] = self.choice([shape[0], "x".join(map(str, shape)), None, {"0": shape[0]}])
        elif how == 5:  # data shorter or longer than the shape says
            cut = int(self.rng.integers(1, 9))
            a["data"] = a["data"][:-cut] if self.rng.random() < 0.5 else a["data"] + self.rng.bytes(cut)
        elif how == 6:  # a plausible shape that does not match the data
            if len(spec) >= 2:
                n = self.choice([r for r in (1, 2, 5, 19, 21, 50, MAX_HORIZON) if r != shape[0]])
                a["shape"] = [n, *shape[1:]]
            else:
                a["data"] = a["data"] + a["data"]
        elif how == 7:  # data not bytes
            a["data"] = self.choice([None, np.frombuffer(a["data"]).tolist(), a["data"].hex(), 0])
        elif how == 8:  # keys missing or extra
            k = self.choice(["dtype", "shape", "data"])
            if self.rng.random() < 0.5:
                del a[k]
            else:
                a["order"] = "C"
        else:  # empty array
            a = {"dtype": "<f8", "shape": [0, *shape[1:]], "data": b""}
        d = dict(d)
        d[f] = a
        return d, True

    def _array_huge(self, d: dict[str, Any], robot: str) -> tuple[dict[str, Any], bool]:
        f = self.choice(list(self.arrays))
        spec = self.arrays[f]
        a = dict(d[f])
        if self.rng.random() < 0.6:  # a huge declared shape over the few real bytes
            n = self.choice([MAX_HORIZON + 1, 10**6, 2**31, 2**32 + 1, 2**62, 2**63 - 1, 2**64 - 1, -(2**63)])
            a["shape"] = [n, *a["shape"][1:]]
        else:  # a real array longer than the horizon allows, under MAX_PAYLOAD per robot
            rows = int(self.rng.integers(MAX_HORIZON + 1, 3500))
            big = {1: (2 * rows,), 2: (rows, 2), 3: (a["shape"][0], rows, 2)}[len(spec)]
            a = _arr(self.rng.uniform(-1, 1, big))
        d = dict(d)
        d[f] = a
        return d, True

    def _array_dtype(self, d: dict[str, Any], robot: str) -> tuple[dict[str, Any], bool]:
        f = self.choice(list(self.arrays))
        bad = [
            "<f2", ">f8", "=f8", "f8", "|f8", "<i8", "<u8", "<c16", "|b1", "O", "float64", "", "<f8 ", "<F8",
            None, 8, b"<f8", ["<f8"], {"<f8": 1},
        ]  # fmt: skip
        d = dict(d)
        d[f] = {**d[f], "dtype": self.choice(bad)}
        return d, True
