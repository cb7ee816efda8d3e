"""Every public definition of the packages says what it is: a docstring on each public class,
function and method (a name without a leading underscore), so a reader of any module finds the
units, frames and shapes where the code is."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = (
    "ground",
    "transport",
    "agent",
    "epuck_link",
    "secure_router",
    "tracker",
    "camera_tools",
    "supervisor",
    "ros2_link",
    "fleet",
)


def _undocumented(tree: ast.AST, prefix: str = "") -> list[str]:
    out = []
    for node in getattr(tree, "body", []):
        if isinstance(
            node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)
        ) and not node.name.startswith("_"):
            if ast.get_docstring(node) is None:
                out.append(f"{prefix}{node.name} (line {node.lineno})")
            if isinstance(node, ast.ClassDef):
                out += _undocumented(node, f"{prefix}{node.name}.")
    return out


def test_every_public_definition_has_a_docstring() -> None:
    files = sorted(f for p in PACKAGES for f in (ROOT / p).rglob("*.py"))
    assert len(files) > 50  # the packages were found
    missing = [f"{f.relative_to(ROOT)}: {d}" for f in files for d in _undocumented(ast.parse(f.read_text()))]
    assert not missing, "\n".join(missing)
