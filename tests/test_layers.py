"""The house's layers, read from the source: who may import whom, and what starts without what.

The packages stand in layers, the contract at the bottom:

    ground                              the contract: wire, schema, geometry, model, goal rule
    transport                           the Zenoh bus, the network, the process prologue, faults
    agent, epuck_link                   the math of one robot; the robot side
    tracker, supervisor, ros2_link      the world and its camera; the judge and the recording;
                                        the fleet as ROS 2 sees it
    camera_tools, secure_router         the camera's offline tools; the TLS router and its rights
    fleet.running                       running fleets: launch, fork server, simulate, goal, report
    fleet.experiment                    experiments as scripts: the API and its backends
    benchmarks                          the harnesses of ``fleet bench``
    fleet                               the command line

A module imports only from its own unit and from the units :data:`ALLOWED` lists for it, all of
a lower layer: ``tracker`` may use ``epuck_link``'s plant and robot side; only ``fleet`` and the
benchmarks may use the agent's math beside the agent itself, so that nothing else loads the QP
solver.  Every import counts, those inside functions too.
"""

from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
LAYERS = {
    "ground": 0, "transport": 1, "agent": 2, "epuck_link": 2, "tracker": 3, "supervisor": 3,
    "ros2_link": 3, "camera_tools": 4, "secure_router": 4, "fleet.running": 5, "fleet.experiment": 6,
    "benchmarks": 7, "fleet": 8,
}  # fmt: skip
"""The units of the house (a package, or a subpackage of ``fleet``) and their layers."""
BELOW_RUNNING = {
    "ground",
    "transport",
    "agent",
    "epuck_link",
    "tracker",
    "camera_tools",
    "supervisor",
    "ros2_link",
}
ALLOWED = {
    "ground": set(),
    "transport": {"ground"},
    "agent": {"ground", "transport"},
    "epuck_link": {"ground", "transport"},
    "tracker": {"ground", "transport", "epuck_link"},
    "supervisor": {"ground", "transport"},
    "ros2_link": {"ground", "transport"},
    "camera_tools": {"ground", "transport", "tracker"},
    "secure_router": {"ground", "transport", "ros2_link"},
    "fleet.running": BELOW_RUNNING,
    "fleet.experiment": BELOW_RUNNING | {"fleet.running"},
    "benchmarks": BELOW_RUNNING | {"fleet.running", "fleet.experiment"},
    "fleet": BELOW_RUNNING | {"secure_router", "fleet.running", "fleet.experiment", "benchmarks"},
}
"""The units each unit may import besides itself."""
PACKAGES = sorted({u.split(".")[0] for u in LAYERS})
"""The top-level packages of the house."""
OURS = set(PACKAGES) | {"tests"}
MATH = ("agent.sets", "agent.tube", "agent.qp", "agent.coordination", "agent.navigator", "agent.hazards",
        "agent.controller", "agent.protocol", "agent.sync")  # fmt: skip
"""The math of one robot: no transport, no logging, no plotting."""
IO = ("zenoh", "rerun", "matplotlib", "transport", "cv2")
"""What the math must not import."""


def unit(module: str) -> str:
    """The unit of :data:`LAYERS` a dotted module name belongs to: the longest that contains it."""
    return max((u for u in LAYERS if module == u or module.startswith(u + ".")), key=len)


def _modules() -> dict[str, Path]:
    """Every module of the packages: dotted name → file."""
    out = {}
    for pkg in PACKAGES:
        for f in sorted((ROOT / pkg).rglob("*.py")):
            rel = f.relative_to(ROOT).with_suffix("")
            parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
            out[".".join(parts)] = f
    return out


MODULES = _modules()


def _imports(path: Path) -> set[str]:
    """The modules ``path`` imports (absolute names; every import statement, at any depth)."""
    got: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            got.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            got.add(node.module)
            got.update(f"{node.module}.{a.name}" for a in node.names if f"{node.module}.{a.name}" in MODULES)
    return got


GRAPH = {m: {i for i in _imports(f) if i.split(".")[0] in OURS} for m, f in MODULES.items()}


def test_the_packages_are_found():
    """The walk sees the whole house (a test of the test: an empty graph passes every rule)."""
    assert {unit(m) for m in MODULES} == set(LAYERS)
    assert len(MODULES) > 40 and sum(len(v) for v in GRAPH.values()) > 100


@pytest.mark.parametrize("module", sorted(MODULES))
def test_every_module_imports_only_what_its_layer_allows(module):
    pkg = unit(module)
    bad = sorted(i for i in GRAPH[module] if unit(i) not in {pkg, *ALLOWED[pkg]})
    assert not bad, f"{module} imports {bad}; {pkg} may import {sorted(ALLOWED[pkg]) or 'nothing of ours'}"


def test_each_allowed_import_goes_down():
    """The allowed imports themselves go to lower layers only (so they can make no loop)."""
    for pkg, allowed in ALLOWED.items():
        assert all(LAYERS[a] < LAYERS[pkg] for a in allowed), pkg


def test_ground_imports_nothing_of_ours_but_ground():
    bad = {
        m: sorted(i for i in deps if not i.startswith("ground"))
        for m, deps in GRAPH.items()
        if m.startswith("ground")
    }
    assert not any(bad.values()), bad


def test_the_contract_loads_no_transport():
    """``ground`` is only the contract: no module of it imports Zenoh, directly or otherwise, so
    the schema, the wire's decoders and the goal rule can be used and tested without a network."""
    bad = sorted(
        f"{m} → {i}"
        for m, f in MODULES.items()
        if m.startswith("ground")
        for i in _imports(f)
        if i == "zenoh" or i.startswith("zenoh.")
    )
    assert not bad, bad


def test_no_import_loops():
    """No module reaches itself through the imports of others (at module granularity)."""
    edges = {
        m: {i if i in MODULES else i.rsplit(".", 1)[0] for i in deps} & set(MODULES)
        for m, deps in GRAPH.items()
    }
    for m in edges:
        edges[m].discard(m)
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m: str) -> None:
        state[m] = 1
        stack.append(m)
        for n in sorted(edges[m]):
            if state.get(n) == 1:
                raise AssertionError("import loop: " + " → ".join([*stack[stack.index(n) :], n]))
            if n not in state:
                visit(n)
        stack.pop()
        state[m] = 2

    for m in sorted(edges):
        if m not in state:
            visit(m)


@pytest.mark.parametrize("module", MATH)
def test_the_math_imports_no_transport_logging_or_plotting(module):
    deps = _imports(MODULES[module])
    bad = sorted(i for i in deps if any(i == x or i.startswith(x + ".") for x in IO))
    assert not bad, f"{module} imports {bad}"


DECISIONS = ("supervisor.judge", "epuck_link.robot_side")
"""Logic that a process runs on what it hears, with no need of the bus itself."""
TRANSPORT = ("zenoh", "transport")


@pytest.mark.parametrize("module", DECISIONS)
def test_the_judge_and_the_robot_sides_decisions_load_no_transport(module):
    """Not directly, and not through anything they import: they can be run, tested and reused
    without a session."""
    seen, todo = set(), [module]
    while todo:
        m = todo.pop()
        if m in seen or m not in MODULES:
            continue
        seen.add(m)
        todo.extend(GRAPH[m])
    bad = sorted(
        f"{m} → {i}"
        for m in seen
        for i in _imports(MODULES[m])
        if any(i == x or i.startswith(x + ".") for x in TRANSPORT)
    )
    assert not bad, f"{module} loads {bad}"


BLOCKER = """
import runpy, sys
class _Refuse:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in ("proxsuite", "agent", "scipy"):
            raise ImportError(f"{name} is refused in this interpreter")
        return None
sys.meta_path.insert(0, _Refuse())
sys.argv = [sys.argv[1], *sys.argv[2:]]
runpy.run_module(sys.argv[0], run_name="__main__", alter_sys=True)
"""
"""Runs ``python -m <module> args`` in an interpreter where proxsuite, scipy and the agent
package cannot be imported."""


@pytest.mark.parametrize(
    "module, args",
    [
        ("tracker", ["--start-timeout", "30"]),
        ("supervisor", ["--out", "{tmp}"]),
        ("epuck_link", ["--robot", "r1", "--link", "emulator"]),
        ("ros2_link", []),
    ],
)
def test_the_robot_side_tracker_and_supervisor_start_without_the_solver(module, args, tmp_path):
    """``python -m tracker``, ``epuck_link``, ``supervisor`` and ``ros2_link`` come up (their readiness line)
    in a fresh interpreter where proxsuite, scipy and the agent package cannot be imported:
    none of them loads the QP solver or synthesises the tube."""
    from transport.net import free_port, loopback

    scn = ROOT / "scenarios" / "paper_two_robots.toml"
    argv = [
        module,
        "--scenario",
        str(scn),
        "--listen",
        loopback(free_port()),
        *(a.format(tmp=tmp_path) for a in args),
    ]
    env = {**os.environ, "RERUN_ANALYTICS": "0", "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(
        [sys.executable, "-c", BLOCKER, *argv], cwd=ROOT, env=env, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()  # the readiness line, or nothing if it died
        ready = json.loads(line) if line.startswith("{") else {}
    finally:
        proc.terminate()
        try:
            _, err = proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            _, err = proc.communicate(timeout=30)
    assert ready.get("event") == "ready", err[-2000:]
    assert "refused in this interpreter" not in err


def test_the_blocker_refuses_the_agent():
    """A test of the test: the agent, which needs the solver, does not start under the blocker."""
    from transport.net import free_port, loopback

    scn = ROOT / "scenarios" / "paper_two_robots.toml"
    argv = [
        "agent",
        "--scenario",
        str(scn),
        "--robot",
        "r1",
        "--listen",
        loopback(free_port()),
        "--timeout",
        "1",
    ]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    res = subprocess.run(
        [sys.executable, "-c", BLOCKER, *argv], cwd=ROOT, env=env, capture_output=True, text=True, timeout=60
    )
    assert res.returncode != 0 and "refused in this interpreter" in res.stderr


def test_the_command_line_loads_the_solver_only_for_the_commands_that_need_it():
    """``fleet goal``, ``report``, ``markers`` and ``calibrate`` run without the agent: building
    the ``fleet`` parser imports neither the agent package nor ProxSuite."""
    code = (
        "import sys, fleet.cli; fleet.cli.build_parser(); "
        "print(sorted({m.split('.')[0] for m in sys.modules} & {'agent', 'proxsuite', 'scipy'}))"
    )
    res = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert res.returncode == 0 and res.stdout.strip() == "[]", res.stdout + res.stderr
