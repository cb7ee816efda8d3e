"""One goal rule: every face that takes a goal at run time judges it by
:func:`ground.scenario.goal_problem` and by nothing of its own, so a goal is refused with the
same reason wherever it is refused.  The rule's content is tested in tests/ground."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
FACES = ("agent/node.py", "fleet/running/operator.py", "fleet/experiment/api.py", "ros2_link/node.py")
"""The agent (the authority), ``fleet goal``, the experiment API and the ROS face."""
PIECES = {"check_point", "free_space", "free_space_model", "joined", "_joined"}
"""What the rule is made of: a face calling one of these judges a goal its own way."""


def _called(path: Path) -> set[str]:
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Call):
            f = node.func
            names.add(f.id if isinstance(f, ast.Name) else f.attr if isinstance(f, ast.Attribute) else "")
    return names


@pytest.mark.parametrize("face", FACES)
def test_each_face_judges_goals_by_the_one_rule_only(face: str) -> None:
    called = _called(ROOT / face)
    assert "goal_problem" in called, face
    assert not called & PIECES, (face, sorted(called & PIECES))
