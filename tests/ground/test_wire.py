"""The wire contract: round trips, strict rejection, and a fuzz test of the decoders."""

from __future__ import annotations

import dataclasses
import threading
import zlib

import msgpack
import numpy as np
import pytest

from ground.wire import (
    MAX_BATCH,
    MAX_HORIZON,
    MAX_MAGNITUDE,
    MAX_PAYLOAD,
    MAX_RELAYED,
    MAX_ROBOTS,
    SCHEMA_VERSION,
    SCRIPT,
    Applied,
    Command,
    Digest,
    Goal,
    Keys,
    LinkState,
    Odom,
    Outcome,
    Plan,
    Pose,
    RejectCounter,
    Script,
    Tick,
    Truth,
    WireError,
    _checked,
    decode,
    encode_array,
)
from transport.bus import Inbox
from transport.faults import FaultPlan


def _disc(robot, *disc):
    """A plan whose discs map ``robot`` to ``disc`` (as it travels: a list)."""
    return _mutate(SAMPLES["plan"], discs={robot: list(disc)})


def _plan(robot="r1", n=20):
    rng = np.random.default_rng(0)
    return Plan(
        robot=robot, step=7, t0=0.8, Ts=0.1, committed=rng.uniform(-1, 1, (n, 2)),
        nominal=rng.uniform(-1, 1, (n + 1, 2)), footprint=0.134,
        priority=1, rank=2, phase=0, target=np.array([0.1, 0.2]), goal=np.array([0.5, -0.5]),
        status="PROXQP_SOLVED", solve_time=2.5e-4, tube_ok=True, late=3,
        discs={"r8": ("dead", True, 0.4, -0.1, 0.1344), "r9": ("stale", False, -0.2, 0.3, 0.2)},
        blocked="r8", no_room="r9",
    )  # fmt: skip


def _with(a, at, value):
    """A copy of ``a`` with ``a[at] = value``."""
    b = a.copy()
    b[at] = value
    return b


SAMPLES = {
    "pose": Pose(robot="r1", seq=3, t=0.3, x=0.1, y=-0.2, theta=1.5),
    "truth": Truth(robot="r1", seq=3, t=0.3, x=0.1, y=-0.2, theta=1.5),
    "plan": _plan(),
    "cmd": Command(
        robot="r1",
        step=4,
        ax=0.05,
        ay=-0.3,
        fallback=True,
        x_next=np.array([0.1, 0.02, -0.2, 0.0]),
        v_next=np.linspace(-0.1, 0.1, 40).reshape(20, 2),
    ),
    "odom": Odom(robot="r1", seq=4, t=0.4, vx=0.05, vy=-0.01),
    "goal": Goal(
        robot="r1", goal=np.array([0.3, 0.4]), batch={"r2": np.array([-0.3, 0.4]), "r3": np.zeros(2)}
    ),
    "script": Script(robot=SCRIPT, step=41, stop=False),
    "tick": Tick(
        robot="tracker", step=12, t=1.2, stop=False, misses=3, fallback={"r2": 9}, braked={"r3": -1}
    ),
    "digest": Digest.of("tracker", 7, 0.1, 20, [_plan("r1"), _plan("r2"), _plan("r3")]),
    "applied": Applied(robot="r1", step=9, last=7, braked=False),
    "outcome": Outcome(robot="tracker", step=12, fallback={"r2": 9}, braked={"r3": -1}),
    "link": LinkState(
        robot="r1",
        up=False,
        step=61,
        lost=58,
        back=-1,
        left=480,
        right=-20,
        speed=0.06,
        seq=60,
        x=0.2,
        y=-0.1,
    ),
}


@pytest.mark.parametrize("name", sorted(SAMPLES))
def test_round_trip(name):
    msg = SAMPLES[name]
    back = decode(msg.encode(), type(msg), robot=msg.robot)
    assert back == msg
    for f in ("committed", "target", "goal", "x_next", "v_next"):
        if hasattr(msg, f):
            assert np.array_equal(getattr(back, f), getattr(msg, f))
    if isinstance(msg, Plan):
        assert back.discs == msg.discs and back.blocked == msg.blocked == "r8"
        assert back.no_room == msg.no_room == "r9"
    if isinstance(msg, Goal):
        assert back.batch.keys() == msg.batch.keys() and len(msg.batch) == 2
        assert all(np.array_equal(back.batch[r], g) for r, g in msg.batch.items())


def test_every_phase_travels_and_none_beyond_waiting():
    """The four precedence phases (under way, returning, parked, waiting) decode as sent; the
    next value is rejected, naming the field."""
    from dataclasses import replace

    from ground.wire import PARKED, RETURNING, UNDER_WAY, WAITING

    for phase in (UNDER_WAY, RETURNING, PARKED, WAITING):
        assert decode(replace(_plan(), phase=phase).encode(), Plan).phase == phase
    with pytest.raises(WireError) as e:
        decode(replace(_plan(), phase=WAITING + 1).encode(), Plan)
    assert e.value.reason.startswith("phase")


def test_a_goal_alone_has_an_empty_batch_and_a_script_may_permit_no_step_yet():
    alone = decode(Goal(robot="r1", goal=np.array([0.3, 0.4])).encode(), Goal, robot="r1")
    assert alone.batch == {} and np.array_equal(alone.goal, [0.3, 0.4])
    none_yet = decode(Script(robot=SCRIPT, step=-1, stop=True).encode(), Script, robot=SCRIPT)
    assert (none_yet.step, none_yet.stop) == (-1, True)
    full = {f"q{i}": np.full(2, 0.01 * i) for i in range(MAX_BATCH)}
    assert len(decode(Goal(robot="r1", goal=np.zeros(2), batch=full).encode(), Goal).batch) == MAX_BATCH


def test_arrays_travel_as_raw_bytes():
    raw = msgpack.unpackb(_plan().encode(), raw=False)
    assert raw["schema"] == SCHEMA_VERSION and raw["type"] == "plan"
    assert raw["committed"]["dtype"] == "<f8" and raw["committed"]["shape"] == [20, 2]
    assert isinstance(raw["committed"]["data"], bytes) and len(raw["committed"]["data"]) == 320


def _mutate(msg, **changes):
    d = msgpack.unpackb(msg.encode(), raw=False)
    for k, v in changes.items():
        if v is KeyError:
            del d[k]
        else:
            d[k] = v
    return msgpack.packb(d, use_bin_type=True)


BAD = [
    ("garbage", lambda: b"\xc1\xff\x00garbage", Pose, "payload"),
    ("not a map", lambda: msgpack.packb([1, 2, 3]), Pose, "payload"),
    ("old version", lambda: _mutate(SAMPLES["pose"], schema=0), Pose, "schema"),
    ("wrong type", lambda: SAMPLES["cmd"].encode(), Pose, "type"),
    ("missing field", lambda: _mutate(SAMPLES["pose"], x=KeyError), Pose, "fields"),
    ("unknown field", lambda: _mutate(SAMPLES["pose"], z=1.0), Pose, "fields"),
    ("NaN", lambda: _mutate(SAMPLES["pose"], x=float("nan")), Pose, "x"),
    ("infinity", lambda: _mutate(SAMPLES["cmd"], ax=float("inf")), Command, "ax"),
    ("non-bool stop", lambda: _mutate(SAMPLES["tick"], stop=1), Tick, "stop"),
    ("tick: a step after the tick", lambda: _mutate(SAMPLES["tick"], fallback={"r2": 13}), Tick, "fallback"),
    ("tick: braked below -1", lambda: _mutate(SAMPLES["tick"], braked={"r3": -2}), Tick, "braked"),
    ("tick: not a map", lambda: _mutate(SAMPLES["tick"], fallback=[["r2", 9]]), Tick, "fallback"),
    ("tick: bad robot id", lambda: _mutate(SAMPLES["tick"], braked={"r 3": 1}), Tick, "braked"),
    ("outcome: its own step on a candidate",
     lambda: _mutate(SAMPLES["outcome"], fallback={"r2": 12}), Outcome, "fallback"),
    ("outcome: braked after its step", lambda: _mutate(SAMPLES["outcome"], braked={"r3": 12}), Outcome,
     "braked"),
    ("cmd: non-bool fallback", lambda: _mutate(SAMPLES["cmd"], fallback=1), Command, "fallback"),
    ("cmd: NaN candidate", lambda: _mutate(
        SAMPLES["cmd"], x_next=encode_array(np.array([0.0, np.nan, 0.0, 0.0]))
    ), Command, "x_next"),
    ("cmd: inputs of 3 columns", lambda: _mutate(SAMPLES["cmd"], v_next=encode_array(np.zeros((20, 3)))),
     Command, "v_next"),
    ("bool as number", lambda: _mutate(SAMPLES["pose"], y=True), Pose, "y"),
    ("string as number", lambda: _mutate(SAMPLES["pose"], theta="1.0"), Pose, "theta"),
    ("negative seq", lambda: _mutate(SAMPLES["pose"], seq=-1), Pose, "seq"),
    ("plan: negative late count", lambda: _mutate(SAMPLES["plan"], late=-1), Plan, "late"),
    ("plan: discs not a map", lambda: _mutate(SAMPLES["plan"], discs=[["r2", "dead"]]), Plan, "discs"),
    ("plan: a disc of its own robot", lambda: _disc("r1", "dead", True, 0, 0, 1),
     Plan, "discs"),
    ("plan: a disc of an unknown kind", lambda: _disc("r2", "gone", True, 0, 0, 1),
     Plan, "discs"),
    ("plan: a disc's rest not a bool", lambda: _disc("r2", "dead", 1, 0, 0, 1),
     Plan, "discs"),
    ("plan: a disc of no radius", lambda: _disc("r2", "dead", True, 0, 0, 0.0),
     Plan, "discs"),
    ("plan: a disc's NaN centre", lambda: _disc("r2", "dead", True, float("nan"), 0, 1),
     Plan, "discs"),
    ("plan: a disc far off", lambda: _disc("r2", "dead", True, 2e9, 0, 1),
     Plan, "discs"),
    ("plan: a disc of four numbers", lambda: _disc("r2", "dead", True, 0, 0),
     Plan, "discs"),
    ("plan: a disc of a bad id", lambda: _disc("r/2", "dead", True, 0, 0, 1),
     Plan, "discs"),
    ("plan: blocked by a bad id", lambda: _mutate(SAMPLES["plan"], blocked="r 2"), Plan, "blocked"),
    ("plan: blocked by itself", lambda: _mutate(SAMPLES["plan"], blocked="r1"), Plan, "blocked"),
    ("plan: no room for itself", lambda: _mutate(SAMPLES["plan"], no_room="r1"), Plan, "no_room"),
    ("plan: no room for a bad id", lambda: _mutate(SAMPLES["plan"], no_room="r 2"), Plan, "no_room"),
    ("plan: a stale disc at rest", lambda: _disc("r2", "stale", True, 0, 0, 1), Plan, "discs"),
    ("cmd: brake not a boolean", lambda: _mutate(SAMPLES["cmd"], brake=1), Command, "brake"),
    ("plan: blocked by a number", lambda: _mutate(SAMPLES["plan"], blocked=2), Plan, "blocked"),
    ("plan: late count of a float", lambda: _mutate(SAMPLES["plan"], late=2.0), Plan, "late"),
    ("bad robot id", lambda: _mutate(SAMPLES["pose"], robot="r1/../x"), Pose, "robot"),
    ("NaN in array", lambda: _mutate(SAMPLES["goal"], goal=encode_array(np.array([np.nan, 0.0]))), Goal,
     "goal"),
    ("wrong shape", lambda: _mutate(SAMPLES["goal"], goal=encode_array(np.zeros(3))), Goal, "goal"),
    ("-inf mid-array", lambda: _mutate(
        _plan(), nominal=encode_array(_with(_plan().nominal, (9, 1), -np.inf))
    ), Plan, "nominal"),
    ("NaN in float32", lambda: _mutate(_plan(), committed={"dtype": "<f4", "shape": [2, 2],
     "data": np.array([0, 0, np.nan, 0], "<f4").tobytes()}), Plan, "committed"),
    ("signalling NaN in float32", lambda: _mutate(_plan(), committed={"dtype": "<f4", "shape": [2, 2],
     "data": np.array([0, 0, 0x7F800001, 0], "<u4").tobytes()}), Plan, "committed"),
    ("sum overflows", lambda: _mutate(_plan(), committed=encode_array(np.full((20, 2), 1e308))), Plan,
     "committed"),
    ("+inf and -inf", lambda: _mutate(_plan(), committed=encode_array(
        _with(_with(_plan().committed, (3, 0), np.inf), (3, 1), -np.inf))), Plan, "committed"),
    ("beyond the magnitude bound", lambda: _mutate(_plan(), committed=encode_array(
        _with(_plan().committed, (0, 0), -2 * MAX_MAGNITUDE))), Plan, "committed"),
    ("huge array", lambda: _mutate(_plan(), committed=encode_array(np.zeros((1000, 2)))), Plan, "committed"),
    ("short data", lambda: _mutate(_plan(), committed={"dtype": "<f8", "shape": [20, 2], "data": b"\0" * 8}),
     Plan, "committed"),
    ("bad dtype", lambda: _mutate(_plan(), committed={"dtype": "|O", "shape": [1, 2], "data": b"\0" * 16}),
     Plan, "committed"),
    ("zero footprint", lambda: _mutate(_plan(), footprint=0.0), Plan, "footprint"),
    ("bad phase", lambda: _mutate(_plan(), phase=7), Plan, "phase"),
    ("oversize", lambda: b"\x00" * (MAX_PAYLOAD + 1), Plan, "payload"),
    ("digest: id twice", lambda: _mutate(SAMPLES["digest"], ids=["r1", "r2", "r1"]), Digest, "ids"),
    ("digest: bad id", lambda: _mutate(SAMPLES["digest"], ids=["r1", "r 2", "r3"]), Digest, "ids"),
    ("digest: short column", lambda: _mutate(SAMPLES["digest"], rank=[0, 1]), Digest, "rank"),
    ("digest: bad phase", lambda: _mutate(SAMPLES["digest"], phase=[0, 4, 0]), Digest, "phase"),
    ("digest: a plan newer than it", lambda: _mutate(SAMPLES["digest"], steps=[7, 8, 7]), Digest, "steps"),
    ("digest: rows and ids differ", lambda: _mutate(
        SAMPLES["digest"], committed=encode_array(np.zeros((2, 20, 2)))), Digest, "committed"),
    ("digest: NaN in a reference", lambda: _mutate(SAMPLES["digest"], committed=encode_array(
        _with(SAMPLES["digest"].committed, (1, 19, 0), np.nan))), Digest, "committed"),
    ("digest: zero footprint", lambda: _mutate(
        SAMPLES["digest"], footprint=encode_array(np.array([0.1, 0.0, 0.1]))), Digest, "footprint"),
    ("digest: goals of 2 robots", lambda: _mutate(
        SAMPLES["digest"], goal=encode_array(np.zeros((2, 2)))), Digest, "goal"),
    ("digest: too many robots", lambda: _mutate(
        SAMPLES["digest"], ids=[f"r{i}" for i in range(MAX_RELAYED + 1)]), Digest, "payload"),
    ("digest: oversize", lambda: b"\x00" * (Digest.MAX_BYTES + 1), Digest, "payload"),
    ("applied: a step after it", lambda: _mutate(SAMPLES["applied"], last=10), Applied, "last"),
    ("applied: below -1", lambda: _mutate(SAMPLES["applied"], last=-2), Applied, "last"),
    ("applied: braked on a command applied", lambda: _mutate(SAMPLES["applied"], last=9, braked=True),
     Applied, "braked"),
    ("applied: followed with nothing applied", lambda: _mutate(SAMPLES["applied"], last=-1), Applied, "last"),
    ("applied: non-bool braked", lambda: _mutate(SAMPLES["applied"], braked=0), Applied, "braked"),
    ("goal: schema 3, no batch", lambda: _mutate(SAMPLES["goal"], batch=KeyError), Goal, "fields"),
    ("goal: batch not a map", lambda: _mutate(SAMPLES["goal"], batch=[["r2", encode_array(np.zeros(2))]]),
     Goal, "batch"),
    ("goal: batch names the robot itself", lambda: _mutate(
        SAMPLES["goal"], batch={"r1": encode_array(np.zeros(2))}), Goal, "batch"),
    ("goal: batch with a bad id", lambda: _mutate(
        SAMPLES["goal"], batch={"r 2": encode_array(np.zeros(2))}), Goal, "batch"),
    ("goal: NaN in the batch", lambda: _mutate(
        SAMPLES["goal"], batch={"r2": encode_array(np.array([0.0, np.nan]))}), Goal, "batch"),
    ("goal: batch point of 3", lambda: _mutate(
        SAMPLES["goal"], batch={"r2": encode_array(np.zeros(3))}), Goal, "batch"),
    ("goal: batch of a number", lambda: _mutate(SAMPLES["goal"], batch={"r2": 0.5}), Goal, "batch"),
    ("goal: batch over the limit", lambda: _mutate(
        SAMPLES["goal"], batch={f"q{i}": encode_array(np.zeros(2)) for i in range(MAX_BATCH + 1)}),
     Goal, "payload"),
    ("script: step below -1", lambda: _mutate(SAMPLES["script"], step=-2), Script, "step"),
    ("script: non-bool stop", lambda: _mutate(SAMPLES["script"], stop=1), Script, "stop"),
    ("script: float step", lambda: _mutate(SAMPLES["script"], step=3.0), Script, "step"),
    ("link: non-bool up", lambda: _mutate(SAMPLES["link"], up=0), LinkState, "up"),
    ("link: negative speed", lambda: _mutate(SAMPLES["link"], speed=-0.1), LinkState, "speed"),
    ("link: wheel speed past int16", lambda: _mutate(SAMPLES["link"], left=40000), LinkState, "left"),
]  # fmt: skip


# A hostile payload is rejected and counted, with nothing else on the process's stderr: no
# floating-point warning either.
@pytest.mark.filterwarnings("error")
@pytest.mark.parametrize(("case", "make", "typ", "field"), BAD, ids=[b[0] for b in BAD])
def test_malformed_payloads_are_rejected_with_the_field(case, make, typ, field):
    with pytest.raises(WireError) as ei:
        decode(make(), typ)
    assert ei.value.reason.startswith(field), ei.value.reason


def test_a_plan_claiming_another_robots_id_is_rejected():
    payload = _plan(robot="r2").encode()
    with pytest.raises(WireError, match="claims 'r2'"):
        decode(payload, Plan, robot="r1")
    assert decode(payload, Plan, robot="r2").robot == "r2"


def test_a_digest_relays_what_neighbours_use_of_each_plan():
    """Relayed plans keep the committed reference, footprint, precedence, target and goal
    bit for bit; one message of n plans instead of n."""
    plans = [_plan("r1"), _plan("r2", n=20), _plan("r3")]
    plans[1] = Plan(**{
        **plans[1].__dict__, "committed": plans[1].committed + 0.5, "priority": 4, "rank": 1, "phase": 1,
        "phase_age": 37, "late": 4,
    })  # fmt: skip
    plans[2] = Plan(**{**plans[2].__dict__, "step": 5, "t0": 0.6})  # late: relayed again in a later digest
    d = decode(Digest.of("tracker", 7, 0.1, 20, plans).encode(), Digest)
    assert d.ids == ["r1", "r2", "r3"] and d.steps == [7, 7, 5] and d.committed.shape == (3, 20, 2)
    for sent, got in zip(plans, d.plans(), strict=True):
        assert got.robot == sent.robot and got.step == sent.step
        for f in ("committed", "target", "goal"):
            assert np.array_equal(getattr(got, f), getattr(sent, f)), f
        assert (got.footprint, got.priority, got.rank, got.phase, got.phase_age) == (
            sent.footprint, sent.priority, sent.rank, sent.phase, sent.phase_age)  # fmt: skip
        assert got.t0 == pytest.approx(sent.t0) and got.status == "relayed"
        assert got.late == 0  # the relaying agent's count is its own, not relayed
        # Made without the dataclass __init__ (ground.wire._checked), yet a whole Plan: with
        # a nominal plan (a relayed one has none) it passes the receiving checks as it is.
        whole = dataclasses.replace(got, nominal=sent.nominal)
        assert type(got) is Plan and decode(whole.encode(), Plan, robot=got.robot) == whole
        assert type(got.footprint) is float
    with pytest.raises(ValueError, match="fields"):
        _checked(Plan, robot="r1", step=1)
    empty = decode(Digest.of("tracker", 3, 0.1, 20, []).encode(), Digest)
    assert empty.ids == [] and empty.plans() == []


def test_the_largest_fleet_fits_every_messages_caps():
    """A fleet of MAX_ROBOTS robots with the longest ids (32 characters) and the longest horizon
    (a nominal plan of N + 1 ≤ MAX_HORIZON points): its digest, a tick and an outcome naming
    every robot, a plan keeping clear of every other robot and a goal batch for the whole fleet
    each fit their byte cap and decode whole; one entry more is refused by the decoder's limit,
    not by luck."""
    assert MAX_ROBOTS >= 256 and MAX_RELAYED == MAX_BATCH == MAX_ROBOTS
    ids = [f"{i:032d}" for i in range(MAX_ROBOTS)]
    every, none = dict.fromkeys(ids, 2**31 - 2), dict.fromkeys(ids, -1)
    big = [dataclasses.replace(_plan(robot=r, n=MAX_HORIZON - 1), priority=-(2**31), rank=2**31 - 1,
                               phase_age=2**31 - 1, step=2**31 - 1) for r in ids]  # fmt: skip
    worst: list[Plan | Digest | Tick | Outcome | Goal] = [
        Digest.of("tracker", 2**31 - 1, 0.1, MAX_HORIZON - 1, big),
        Tick(robot="tracker", step=2**31 - 1, t=1e9, stop=False, misses=9, fallback=every, braked=none),
        Outcome(robot="tracker", step=2**31 - 1, fallback=every, braked=none),
        dataclasses.replace(big[0], discs={r: ("braked", True, -1e3, 1e3, 0.25) for r in ids[1:]}),
        Goal(robot=ids[0], goal=np.zeros(2), batch={r: np.array([-1e3, 1e3]) for r in ids[1:]}),
    ]
    for msg in worst:
        payload = msg.encode()
        assert len(payload) <= type(msg).MAX_BYTES, (type(msg).__name__, len(payload))
        assert decode(payload, type(msg)) == msg
    over = Tick(robot="tracker", step=9, t=0.9, stop=False, misses=0,
                fallback={f"r{i}": 1 for i in range(MAX_ROBOTS + 1)})  # fmt: skip
    with pytest.raises(WireError, match="payload"):
        decode(over.encode(), Tick)


def test_relayed_plans_pass_the_receivers_fault_plan_like_plans_on_their_own_keys():
    """An agent's inbox stores each plan of a digest under its robot, and the fault plan
    drops it as it would drop the plan on ``plan/<id>``."""
    faults = FaultPlan.parse(
        '{"seed": 1, "rules": [{"key": "plan/r2", "bursts": [[7, 8]], "to": ["agent r1"]}]}'
    )
    inbox = Inbox(Keys("lab"), "agent r1", faults)
    payload = SAMPLES["digest"].encode()
    inbox._accept("fleet/lab/digest", payload, Digest, True, 0.0)
    assert inbox.get(Plan, "r1", 7) is not None and inbox.get(Plan, "r3", 7) is not None
    assert inbox.get(Plan, "r2", 7) is None and inbox.lost(Plan, "r2", 7) and inbox.injected == 1
    assert inbox.get(Digest, "tracker").step == 7
    inbox._accept("fleet/lab/digest", payload[:-3], Digest, True, 0.0)  # truncated: rejected, counted
    assert inbox.rejects.total == 1


def test_keys():
    k = Keys("lab")
    assert k.plan("r1") == "fleet/lab/plan/r1" and k.pose() == "fleet/lab/pose/*"
    assert k.clock == "fleet/lab/clock" and k.digest == "fleet/lab/digest"
    assert k.script == "fleet/lab/script" and k.robot_of(k.script) == SCRIPT
    assert k.alive(SCRIPT) == "fleet/lab/alive/script"
    assert k.robot_of("fleet/lab/cmd/r7") == "r7"
    with pytest.raises(WireError):
        k.robot_of("fleet/lab/cmd/r 7")
    with pytest.raises(ValueError):
        Keys("a/b")


def test_a_script_claiming_another_id_is_rejected_and_its_stop_is_not_lost():
    """On ``fleet/F/script`` the sender is the script.  The inbox keeps the highest permit as the
    latest Script, so a stop sent with a smaller step would not replace it: ``then`` sees every
    message stored, which is how the tracker keeps a stop whatever its step."""
    keys = Keys("lab")
    inbox = Inbox(keys, "tracker")
    seen: list[Script] = []
    forged = Script(robot="r1", step=3, stop=True).encode()
    inbox._accept(keys.script, forged, Script, False, 0.0, seen.append)
    assert inbox.rejects.total == 1 and not seen and inbox.get(Script, SCRIPT) is None
    for step, stop in ((7, False), (-1, True)):
        inbox._accept(keys.script, Script(robot=SCRIPT, step=step, stop=stop).encode(), Script, False, 0.0,
                      seen.append)  # fmt: skip
    assert [(m.step, m.stop) for m in seen] == [(7, False), (-1, True)]
    assert inbox.get(Script, SCRIPT).step == 7 and not inbox.get(Script, SCRIPT).stop


def test_reject_counter_reports_once_per_source():
    lines = []
    rc = RejectCounter(report=lines.append)
    for _ in range(5):
        rc.reject("fleet/lab/plan/r1", WireError("x: bad"))
    rc.reject("fleet/lab/plan/r2", WireError("payload: not msgpack"))
    assert rc.total == 6 and len(lines) == 2
    assert rc.counts[("fleet/lab/plan/r1", "x")] == 5


@pytest.mark.filterwarnings("error")
@pytest.mark.parametrize("name", sorted(SAMPLES))
def test_fuzz_decoders_never_raise_anything_but_wire_error(name):
    """10,000 generated payloads per message type: byte flips, truncations, splices,
    random bytes and type-confused fields.  Each decodes to a valid message or raises
    WireError, and never warns; a decoded message never carries a non-finite number."""
    msg = SAMPLES[name]
    typ = type(msg)
    good = msg.encode()
    rng = np.random.default_rng(zlib.crc32(name.encode()))
    junk_values = [None, True, -1, 2**64 - 1, 1e308, float("nan"), "x" * 100, b"\x00" * 9, [1, 2], {"a": 1}]
    base = msgpack.unpackb(good, raw=False)
    accepted = 0
    for i in range(10_000):
        kind = i % 5
        if kind == 0:
            b = bytearray(good)
            for _ in range(int(rng.integers(1, 6))):
                b[int(rng.integers(len(b)))] = int(rng.integers(256))
            payload = bytes(b)
        elif kind == 1:
            payload = good[: int(rng.integers(len(good)))]
        elif kind == 2:
            payload = rng.bytes(int(rng.integers(0, 200)))
        elif kind == 3:
            d = dict(base)
            key = list(d)[int(rng.integers(len(d)))]
            d[key] = junk_values[int(rng.integers(len(junk_values)))]
            payload = msgpack.packb(d, use_bin_type=True)
        else:
            cut = int(rng.integers(len(good)))
            payload = good[cut:] + good[:cut]
        try:
            out = decode(payload, typ)
        except WireError:
            continue
        accepted += 1
        for f in out.__dataclass_fields__:
            v = getattr(out, f)
            if isinstance(v, float):
                assert np.isfinite(v)
            if isinstance(v, np.ndarray):
                assert np.all(np.isfinite(v))
    assert accepted < 10_000  # the generator really produced bad payloads


def test_reject_reports_are_capped_escaped_and_short():
    """A sender chooses the key and the payload: the counter reports at most max_sources
    keys (then one line), escapes newlines and cuts long reasons, and still counts all."""
    from ground.wire import RejectCounter, WireError

    lines: list[str] = []
    rc = RejectCounter(report=lines.append, max_sources=4)
    for i in range(50):
        rc.reject(f"fleet/lab/plan/x{i}\nFORGED", WireError("fields: " + "z" * 5000))
    assert rc.total == 50
    assert len(lines) == 5 and "more than 4 keys" in lines[-1]
    assert all("\n" not in ln and len(ln) < 400 for ln in lines)
    assert "\\nFORGED" in lines[0]


def test_tick_says_which_plans_each_robot_side_executed():
    """``Tick.executed``: None when the command of the previous step was applied (or the
    clock does not know), else the step of the newest plan the robot executed."""
    tick = SAMPLES["tick"]
    assert tick.executed("r1") is None
    assert tick.executed("r2") == 9  # followed the candidate of its command of step 9
    assert tick.executed("r3") == -1  # braked, never commanded
    assert Tick(robot="tracker", step=3, t=0.3, stop=False, misses=0).executed("r2") is None
    outcome = SAMPLES["outcome"]  # the same, of its own step
    assert [outcome.executed(r) for r in ("r1", "r2", "r3")] == [None, 9, -1]


class _Interrupted(threading.Condition):
    """A condition whose wait is interrupted by Ctrl-C, either at CPython's worst moment (the
    lock let go, the KeyboardInterrupt raised before ``Condition.wait`` could take it back) or
    at its usual one (while waiting, the lock taken back on the way out)."""

    def __init__(self, worst: bool) -> None:
        super().__init__()
        self.worst = worst

    def wait(self, timeout: float | None = None) -> bool:
        if self.worst:
            self._release_save()  # type: ignore[attr-defined]
        raise KeyboardInterrupt


@pytest.mark.parametrize("worst", [True, False], ids=["lock-let-go", "lock-taken-back"])
def test_an_interrupt_inside_a_wait_leaves_the_inbox_lock_free_and_says_keyboardinterrupt(worst):
    """Ctrl-C during ``Inbox.wait`` raises KeyboardInterrupt (not a lock error), and afterwards
    the lock is free: a receiving thread can take it, and the next wait works."""
    inbox = Inbox(Keys("lab"), "operator")
    inbox.cond = _Interrupted(worst)
    with pytest.raises(KeyboardInterrupt):
        inbox.wait(lambda: False, 5.0)
    taken = []

    def take() -> None:
        if inbox.cond.acquire(timeout=5.0):
            taken.append(True)
            inbox.cond.release()

    other = threading.Thread(target=take)
    other.start()
    other.join(10.0)
    assert taken == [True], "the lock was left held"
    inbox.cond = threading.Condition()
    assert inbox.wait(lambda: True, 0.1) and not inbox.wait(lambda: False, 0.01)
