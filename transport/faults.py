"""Fault injection on the receiving side of a process's subscriptions.

A fault plan drops or delays chosen messages, seeded and reproducible:
whether the message of step k on key K is lost for receiver R depends only on
(seed, R, K, k), never on timing, so a lockstep run with faults is as
deterministic as one without.  A JSON plan (a file path, or the text itself)::

    {"seed": 3, "rules": [
        {"key": "plan/*", "drop": 0.1},                        # 10 % random loss
        {"key": "plan/r2", "bursts": [[40, 45]], "to": ["agent r1"]},  # steps 40..44 lost
        {"key": "pose/r1", "delay": 2}                          # delivered 2 steps late
    ]}

A plan may also cut robots' radio links: ``"links": {"r2": [[150, 170]]}`` cuts
r2's link between ``epuck_link`` and its robot over steps 150..169 (by the
link's clock); the robot drives on at its last wheel speeds, as a real one does
(its firmware has no deadman).

A plan may also kill robots' agents: ``"kills": {"r2": 120}`` ends r2's agent at step 120,
before it plans that step: in a process fleet the agent sends itself SIGKILL (a hard death, its
liveliness token goes with its session), and in ``fleet simulate`` it makes no plan from then
on.  Either way its robot side brakes its robot, and the other agents keep clear of it as of a
dead robot (docs/method.md §6.4).

``key`` is an ``fnmatch`` pattern on the key below ``fleet/F/`` (``plan/r2``,
``pose/*``, ``clock``); ``to`` (optional) lists the receiving roles (``agent
r1``, ``tracker``, ``supervisor``; default: every receiver).  ``drop`` is a
probability in [0, 1]; ``bursts`` are half-open step ranges ``[first,
end)`` lost entirely; ``delay`` holds a message back ``delay`` steps (it
reaches the receiver when its own step passes ``k + delay``, or never if the
run ends first).  The first matching rule decides.  Only messages that carry
a step or sequence number are subject to faults.

:class:`transport.bus.Inbox` applies the plan: a dropped or delayed message
leaves a tombstone, so a receiver that waits for step k learns at once that
it will not come in time and carries on with what it has, as it would after
a real loss.
"""

from __future__ import annotations

import fnmatch
import json
import math
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

DELIVER, DROP = "deliver", "drop"


class FaultPlanError(ValueError):
    """A fault plan that cannot be used; the message names the field."""


@dataclass(frozen=True)
class FaultRule:
    """One rule of a fault plan (see the module docstring)."""

    key: str
    drop: float = 0.0
    bursts: tuple[tuple[int, int], ...] = ()
    delay: int = 0
    to: tuple[str, ...] | None = None


class FaultPlan:
    """Decides the fate of each received message, reproducibly."""

    def __init__(
        self,
        rules: list[FaultRule],
        seed: int = 0,
        links: dict[str, tuple[tuple[int, int], ...]] | None = None,
        kills: dict[str, int] | None = None,
    ):
        self.rules = rules
        self.seed = seed
        self.links = links or {}
        """Per robot, the half-open step ranges over which its radio link is cut."""
        self.kills = kills or {}
        """Per robot, the step its agent is killed at [steps]."""

    @classmethod
    def parse(cls, text_or_path: str) -> FaultPlan:
        """A plan from JSON text or a JSON file; raises FaultPlanError naming the field."""
        text = text_or_path
        if not text_or_path.lstrip().startswith("{"):
            try:
                text = Path(text_or_path).read_text()
            except OSError as e:
                raise FaultPlanError(f"faults: cannot read {text_or_path!r} ({e.strerror})") from None
        try:
            raw = json.loads(text)
        except json.JSONDecodeError as e:
            raise FaultPlanError(f"faults: not JSON ({e.msg} at line {e.lineno})") from None
        if not isinstance(raw, dict) or set(raw) - {"seed", "rules", "links", "kills"}:
            raise FaultPlanError("faults: expected an object with 'seed', 'rules', 'links' and 'kills'")
        seed = raw.get("seed", 0)
        if isinstance(seed, bool) or not isinstance(seed, int):
            raise FaultPlanError("faults.seed: expected an integer")
        rules_raw = raw.get("rules", [])
        if not isinstance(rules_raw, list):
            raise FaultPlanError("faults.rules: expected a list")
        links_raw = raw.get("links", {})
        if not isinstance(links_raw, dict):
            raise FaultPlanError("faults.links: expected an object of robot ids")
        links = {str(r): _bursts(b, f"faults.links.{r}") for r, b in links_raw.items()}
        kills_raw = raw.get("kills", {})
        if not isinstance(kills_raw, dict):
            raise FaultPlanError("faults.kills: expected an object of robot ids to steps")
        kills = {}
        for r, step in kills_raw.items():
            if type(step) is not int or step < 0:
                raise FaultPlanError(f"faults.kills.{r}: expected a step >= 0")
            kills[str(r)] = step
        rules = [_rule(r, f"faults.rules[{i}]") for i, r in enumerate(rules_raw)]
        return cls(rules, seed, links, kills)

    def link_cut(self, robot: str, step: int) -> bool:
        """The radio link of ``robot`` is cut at ``step``."""
        return any(a <= step < b for a, b in self.links.get(robot, ()))

    def decide(self, receiver: str, key: str, step: int) -> tuple[str, int]:
        """(DELIVER, 0), (DROP, 0) or (DELIVER, d): delivered ``d`` steps late.

        ``key`` is the part below ``fleet/F/``; ``step`` the message's step or seq."""
        for rule in self.rules:
            if not fnmatch.fnmatchcase(key, rule.key):
                continue
            if rule.to is not None and receiver not in rule.to:
                continue
            if any(a <= step < b for a, b in rule.bursts):
                return DROP, 0
            if rule.drop > 0 and _uniform(self.seed, receiver, key, step) < rule.drop:
                return DROP, 0
            return DELIVER, rule.delay
        return DELIVER, 0


def _uniform(seed: int, receiver: str, key: str, step: int) -> float:
    """A number in [0, 1) fixed by its arguments (CRC-32, not Python's salted hash)."""
    return zlib.crc32(f"{seed}|{receiver}|{key}|{step}".encode()) / 2**32


def _rule(raw: Any, path: str) -> FaultRule:
    if not isinstance(raw, dict):
        raise FaultPlanError(f"{path}: expected an object")
    unknown = set(raw) - {"key", "drop", "bursts", "delay", "to"}
    if unknown:
        raise FaultPlanError(f"{path}: unknown field {sorted(unknown)[0]!r}")
    key = raw.get("key")
    if not isinstance(key, str) or not key:
        raise FaultPlanError(f"{path}.key: expected a key pattern such as 'plan/*'")
    drop = raw.get("drop", 0.0)
    if isinstance(drop, bool) or not isinstance(drop, int | float) or not (0.0 <= drop <= 1.0):
        raise FaultPlanError(f"{path}.drop: expected a probability in [0, 1]")
    if isinstance(drop, float) and math.isnan(drop):
        raise FaultPlanError(f"{path}.drop: expected a probability in [0, 1]")
    bursts = _bursts(raw.get("bursts", []), f"{path}.bursts")
    delay = raw.get("delay", 0)
    if type(delay) is not int or delay < 0:
        raise FaultPlanError(f"{path}.delay: expected a whole number of steps >= 0")
    to = raw.get("to")
    if to is not None and (not isinstance(to, list) or not all(isinstance(r, str) for r in to)):
        raise FaultPlanError(f"{path}.to: expected a list of receiving roles")
    return FaultRule(key, float(drop), bursts, delay, None if to is None else tuple(to))


def _bursts(bursts: Any, path: str) -> tuple[tuple[int, int], ...]:
    if not isinstance(bursts, list) or not all(
        isinstance(b, list) and len(b) == 2 and all(type(v) is int for v in b) and 0 <= b[0] <= b[1]
        for b in bursts
    ):
        raise FaultPlanError(f"{path}: expected [[first, end), ...] step pairs")
    return tuple((b[0], b[1]) for b in bursts)
