"""One goal rule: every face that takes a goal at run time judges it by
:func:`ground.scenario.goal_problem` and by nothing of its own, and the scenario loader judges
the scenario's goals by the same rule, so a goal is refused with the same text wherever it is
refused.  The rule's content, and the loader's text equal to the rule's, are tested in
tests/ground/test_scenario.py."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
FACES = ("agent/goals.py", "fleet/running/operator.py", "fleet/experiment/api.py", "ros2_link/node.py")
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


def test_the_loader_judges_goals_by_the_rule_and_the_rule_by_its_one_body() -> None:
    """``check_geometry`` (the loader's geometry) and ``goal_problem`` both reach the rule's one
    body, ``_goal_reason``, and nothing else in the module builds a goal's passage or spacing
    text: the texts ``cannot be reached from`` and ``'s goal, closer than`` are written once."""
    src = (ROOT / "ground" / "scenario.py").read_text()
    tree = ast.parse(src)
    fns = {n.name: n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef)}
    for name in ("check_geometry", "goal_problem"):
        called = {
            c.func.id for c in ast.walk(fns[name]) if isinstance(c, ast.Call) and isinstance(c.func, ast.Name)
        }
        assert "_goal_reason" in called, name
    assert src.count("cannot be reached from") == 1 and src.count("'s goal, closer than") == 1
