"""An agent's standing against its own robot (agent/sync.py), seen without a bus: the state it
plans from while poses come and go, and what it does when the robot side says its commands were
not applied (docs/design.md, "Missed deadlines")."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np

from agent.sync import REJOIN_GAP, Sync
from ground.model import double_integrator

TS = 0.1


class Controller:
    """Records what :class:`Sync` asks of the controller; ``rewinds`` says whether a rewind holds."""

    def __init__(self, rewinds: bool = True) -> None:
        self.rewinds = rewinds
        self.resets: list[np.ndarray] = []
        self.rewound: list[tuple[int, int]] = []

    def reset(self, point: np.ndarray, x: np.ndarray) -> None:
        self.resets.append(np.array(point))

    def rewind(self, unapplied: int, coasted: int) -> bool:
        self.rewound.append((unapplied, coasted))
        return self.rewinds


def _sync(ctrl: Controller, blind_steps: int = 3) -> tuple[Sync, list[str]]:
    A, B, _ = double_integrator(TS)
    said: list[str] = []
    sync = Sync(ctrl, SimpleNamespace(A=A, B=B), blind_steps, said.append)  # type: ignore[arg-type]
    return sync, said


def _x(px: float, py: float, vx: float = 0.0, vy: float = 0.0) -> np.ndarray:
    return np.array([px, vx, py, vy])


def test_without_poses_it_plans_on_the_nominal_model_then_holds_and_starts_again_where_the_robot_is() -> None:
    ctrl = Controller()
    sync, said = _sync(ctrl, blind_steps=2)
    assert sync.state(0, None) is None  # nothing measured yet: nothing to plan from
    x0 = sync.state(0, _x(0.1, 0.2, 0.3, 0.0))
    assert x0 is not None and sync.joined and not ctrl.resets  # step 0: the start, no rejoin
    sync.x_est, sync.a_prev = x0, np.array([1.0, -1.0])
    A, B, _ = double_integrator(TS)
    predicted = sync.state(1, None)
    assert np.allclose(predicted, A @ x0 + B @ np.array([1.0, -1.0]))  # the nominal model's step
    assert not sync.holding
    sync.state(2, None)
    assert not sync.holding
    sync.state(3, None)
    assert sync.holding and said == ["step 3: no pose for 3 steps; braking and holding"]
    back = _x(0.5, 0.6)
    assert np.array_equal(sync.state(4, back), back)
    assert sync.joined and sync.blind == 0 and len(ctrl.resets) == 1
    assert np.allclose(ctrl.resets[0], [0.5, 0.6])  # started again where the robot is
    assert said[1:] == ["step 4: measurements back after 3 steps; starting again where it is",
                        "joined at step 4 at (0.500, 0.600)"]  # fmt: skip


def test_a_robot_that_braked_is_joined_again_from_its_measurement_and_each_episode_is_said_once() -> None:
    ctrl = Controller()
    sync, said = _sync(ctrl)
    sync.state(0, _x(0.0, 0.0))
    sync.ran = [1, 2]
    for k in (3, 4, 5):  # three reports of the same braking episode
        sync.take_report(k, executed=1, braked=True)
        assert not sync.joined and sync.behind == "braked" and sync.x_est is None
        sync.state(k, _x(0.1 * k, 0.0))  # it starts again at each of its steps, said once
    assert said.count("step 3: robot braked after step 1; starting again where it is") == 1
    assert [s for s in said if s.startswith("joined")] == ["joined at step 3 at (0.300, 0.000)"]
    assert len(ctrl.resets) == 3 and ctrl.rewound == []  # braked: nothing to rewind
    sync.take_report(6, executed=None, braked=False)  # its commands are applied again
    assert sync.behind == "" and not sync.rejoined and sync.synced == 5 and sync.reported == 5


def test_commands_not_applied_rewind_the_controller_by_the_steps_the_robot_did_not_take() -> None:
    ctrl = Controller(rewinds=True)
    sync, said = _sync(ctrl)
    sync.state(0, _x(0.0, 0.0))
    sync.synced, sync.ran = 4, [5, 6, 7]  # it stepped at 5, 6 and 7; the robot applied up to 5
    sync.take_report(8, executed=5, braked=False)
    assert ctrl.rewound == [(2, 0)] and sync.joined and sync.behind == "candidate"
    assert said == ["step 8: commands after step 5 not applied; on its candidate"]
    assert sync.ran == [] and sync.synced == 7
    # A rewind that cannot hold (the candidate is spent) is a brake: start again.
    ctrl.rewinds = False
    sync.ran = [8]
    sync.take_report(9, executed=5, braked=False)
    assert not sync.joined and sync.behind == "braked"


def test_an_agent_that_fell_far_behind_an_unreporting_clock_starts_again() -> None:
    sync, said = _sync(Controller())
    sync.state(0, _x(0.0, 0.0))
    assert sync.catch_up(10, 10 + REJOIN_GAP, None, stop=False) == 10 + REJOIN_GAP
    assert sync.joined  # behind by REJOIN_GAP: it goes on from its plan
    assert sync.catch_up(20, 21 + REJOIN_GAP, None, stop=False) == 21 + REJOIN_GAP
    assert not sync.joined and sync.x_est is None  # farther: it starts again where the robot is
    assert said == [f"fell behind the clock: step 10 → {10 + REJOIN_GAP}"]
    sync.state(30, _x(0.0, 0.0))
    # When the clock says what the robot did, the report decides instead.
    ran: Any = sync.catch_up(30, 40 + REJOIN_GAP, 35, stop=False)
    assert ran == 40 + REJOIN_GAP and sync.joined
    assert sync.catch_up(50, 49, None, stop=False) == 50  # never backwards


def test_a_link_outage_holds_the_steps_until_the_robot_is_back_and_is_said_once_each_way() -> None:
    """Down, then up but held until step ``back`` (the robot stood still meanwhile): cut at
    every step of it, and two lines in all."""
    sync, said = _sync(Controller())
    assert not sync.cut(0, None)  # a simulated robot: no link to lose
    down: Any = SimpleNamespace(up=False, back=-1)
    assert all(sync.cut(k, down) for k in (3, 4, 5))
    held: Any = SimpleNamespace(up=True, back=8)
    assert sync.cut(6, held) and sync.cut(7, held) and not sync.cut(8, held)
    assert said == [
        "step 3: the robot's link is down; it drives on uncontrolled, so nothing is solved until "
        "the link is back",
        "step 8: the robot's link is back after 5 steps",
    ]
