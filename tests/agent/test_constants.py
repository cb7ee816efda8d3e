"""The table of the navigator's constants in docs/method.md §7 ("derived or tuned") says what
the code holds: each row's dotted name resolves, and its value is the one written."""

from __future__ import annotations

import dataclasses
import importlib
import re
from pathlib import Path

import pytest

METHOD = Path(__file__).resolve().parents[2] / "docs" / "method.md"
ROW = re.compile(r"^\| `(agent\.[\w.]+)` \| ([-0-9.e]+) \|", re.M)


def _rows() -> list[tuple[str, str]]:
    text = METHOD.read_text()
    start = text.index("**The navigator's constants: derived or tuned.**")
    return ROW.findall(text[start : text.index("**Where the layout forces an order", start)])


def _resolve(dotted: str) -> object:
    parts = dotted.split(".")
    for cut in range(len(parts) - 1, 0, -1):
        try:
            obj: object = importlib.import_module(".".join(parts[:cut]))
        except ModuleNotFoundError:
            continue
        for name in parts[cut:]:
            if dataclasses.is_dataclass(obj) and isinstance(obj, type):
                obj = {f.name: f for f in dataclasses.fields(obj)}[name].default
            else:
                obj = getattr(obj, name)
        return obj
    raise LookupError(dotted)


def test_the_table_names_every_constant_it_lists_at_its_value() -> None:
    rows = _rows()
    assert len(rows) >= 15, rows  # the table was found, and read
    for dotted, written in rows:
        assert _resolve(dotted) == pytest.approx(float(written)), dotted
