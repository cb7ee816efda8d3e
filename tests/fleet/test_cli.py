"""The command-line contract of ``fleet`` (fleet/cli.py), exercised through a real subprocess.

Exit codes: 0 success, 1 an inadmissible design or a failed run, 2 bad input with one
``fleet: error: <field>: <reason>`` line on stderr and no traceback.
"""

from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from ground.params import preset

ROOT = Path(__file__).resolve().parents[2]
SCENARIOS = ROOT / "scenarios"
TIMEOUT = 300  # generous: a two-robot run takes a few seconds


def fleet(*args: str | Path, timeout: float = TIMEOUT) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, PYTHONIOENCODING="utf-8", OMP_NUM_THREADS="1")
    return subprocess.run(
        [sys.executable, "-m", "fleet.cli", *map(str, args)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        encoding="utf-8",
        timeout=timeout,
        env=env,
    )


def _reject_constant(name: str) -> Any:
    raise ValueError(f"non-standard JSON constant {name}")


def strict_json(text: str) -> Any:
    """Parse JSON, refusing NaN / Infinity (not JSON, though Python writes them by default)."""
    return json.loads(text, parse_constant=_reject_constant)


def no_traceback(proc: subprocess.CompletedProcess[str]) -> None:
    assert "Traceback" not in proc.stderr, proc.stderr
    assert "Traceback" not in proc.stdout, proc.stdout


# --------------------------------------------------------------------------- fleet design


def test_design_default_is_admissible():
    proc = fleet("design")
    no_traceback(proc)
    assert proc.returncode == 0, proc.stderr
    assert "admissible: yes" in proc.stdout
    assert "admissible: NO" not in proc.stdout


def test_design_json_keys_and_consistency():
    proc = fleet("design", "--json")
    no_traceback(proc)
    assert proc.returncode == 0, proc.stderr
    d = strict_json(proc.stdout)
    for key in (
        "K",
        "Z_half_widths",
        "Psi_half_widths",
        "KZ_m_s2",
        "tightened",
        "epsilon_m",
        "footprint_radius_m",
        "admissible",
        "failures",
    ):
        assert key in d, key
    assert d["admissible"] is True
    assert d["failures"] == []
    p = preset("epuck")
    zh, ph, tight = d["Z_half_widths"], d["Psi_half_widths"], d["tightened"]
    # X̂ = X ⊖ Z, Û = U ⊖ KZ: bound minus support.
    assert tight["velocity_m_s"] == pytest.approx(p.v_max - zh["velocity_m_s"], abs=1e-9)
    assert tight["acceleration_m_s2"] == pytest.approx(p.a_max - d["KZ_m_s2"][0], abs=1e-9)
    assert 0 < tight["velocity_m_s"] < p.v_max
    assert 0 < tight["acceleration_m_s2"] < p.a_max
    assert d["epsilon_m"] == pytest.approx(p.epsilon, rel=1e-12)
    # A usable tube (docs/method.md §3): centimetre-sized, far from the paper's 0.35 m.
    assert 0 < zh["position_m"] < 0.03
    assert 0 < zh["velocity_m_s"] < p.v_max
    assert 0 < ph["position_m"] and 0 < ph["velocity_m_s"] < tight["velocity_m_s"]
    assert len(d["KZ_m_s2"]) == 2 and all(k > 0 for k in d["KZ_m_s2"])
    # K is a 2×4 stabilising gain of the double integrator at Ts: ρ(A + BK) < 1.
    K = d["K"]
    assert len(K) == 2 and all(len(row) == 4 for row in K)
    Ts = p.Ts
    for row, (i, j) in zip(K, ((0, 1), (2, 3)), strict=True):
        k1, k2 = row[i], row[j]
        # Per axis A_K = [[1 + Ts²/2 k1, Ts + Ts²/2 k2], [Ts k1, 1 + Ts k2]].
        a11, a12, a21, a22 = 1 + Ts * Ts / 2 * k1, Ts + Ts * Ts / 2 * k2, Ts * k1, 1 + Ts * k2
        tr, det = a11 + a22, a11 * a22 - a12 * a21
        disc = tr * tr - 4 * det
        rho = (abs(tr) + math.sqrt(disc)) / 2 if disc >= 0 else math.sqrt(det)
        assert rho < 1
    # The footprint covers the body, the look-ahead offset and at least ε.
    assert d["footprint_radius_m"] >= p.robot_radius + p.lookahead + p.epsilon
    assert d["footprint_radius_m"] < 0.5


def test_design_paper_preset_fails_and_says_why():
    proc = fleet("design", "--preset", "paper")
    no_traceback(proc)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert "admissible: NO" in proc.stdout
    # Names the failing bound and a negative amount on the same line.
    lines = [ln for ln in proc.stdout.splitlines() if "velocity" in ln and re.search(r"= -\d", ln)]
    assert lines, proc.stdout

    proc = fleet("design", "--preset", "paper", "--json")
    no_traceback(proc)
    assert proc.returncode == 1
    d = strict_json(proc.stdout)
    assert d["admissible"] is False
    assert d["failures"]
    assert any("velocity" in f for f in d["failures"])
    # docs/method.md §3: the paper's K with W = ±1 cm gives a ≈ 0.35 m mRPI position half-width.
    assert 0.30 <= d["Z_half_widths"]["position_m"] <= 0.40
    assert d["tightened"]["velocity_m_s"] < 0
    assert d["tightened"]["velocity_m_s"] == pytest.approx(
        preset("paper").v_max - d["Z_half_widths"]["velocity_m_s"], abs=1e-9
    )


def test_design_of_a_scenario_reports_its_arena(tmp_path):
    proc = fleet("design", SCENARIOS / "paper_three_robots.toml", "--json")
    no_traceback(proc)
    assert proc.returncode == 0, proc.stderr
    d = strict_json(proc.stdout)
    assert d["scenario"] == "paper_three_robots"
    assert d["arena"] == [-1.0, 1.0, -1.0, 1.0]
    assert d["admissible"] is True

    # A different arena is reported as given (not a default).
    f = tmp_path / "wide.toml"
    f.write_text(scenario_toml(arena=(-1.5, 1.25, -1.2, 1.1), name="wide"))
    proc = fleet("design", f, "--json")
    no_traceback(proc)
    assert proc.returncode == 0, proc.stderr
    d = strict_json(proc.stdout)
    assert d["scenario"] == "wide"
    assert d["arena"] == [-1.5, 1.25, -1.2, 1.1]


def test_design_scenario_preset_override(tmp_path):
    f = tmp_path / "s.toml"
    f.write_text(scenario_toml())
    proc = fleet("design", f, "--preset", "paper", "--json")
    no_traceback(proc)
    assert proc.returncode == 1
    d = strict_json(proc.stdout)
    assert d["preset"] == "paper"
    assert d["admissible"] is False


# A scenario's controller override that `fleet design` must refuse, and what the one line naming
# the failing bound says (docs/method.md §1.2 and §4).
INADMISSIBLE = {
    # y axis only: the lag speed 5.92 cm/s exceeds 0.95 × 6.19 cm/s.
    "ref_Q_y": ("ref_Q = [100.0, 10.0, 500.0, 2.0]", ("y reference lag velocity", "X̂ y velocity bound")),
    # ℓ = 2 cm asks 0.176 m/s of wheels that give 0.129 m/s.
    "lookahead_2cm": (
        "lookahead = 0.02",
        ("wheel speed bound", "= 0.1761 m/s", "wheels' limit 0.1288 m/s", "smallest lookahead"),
    ),
}


@pytest.mark.parametrize("case", sorted(INADMISSIBLE))
def test_design_refuses_a_bound_failing_on_one_axis_or_the_wheels(tmp_path, case):
    override, words = INADMISSIBLE[case]
    f = tmp_path / f"{case}.toml"
    f.write_text(scenario_toml(controller=f"[controller]\n{override}\n"))
    proc = fleet("design", f)
    no_traceback(proc)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert "admissible: NO" in proc.stdout
    failures = [ln for ln in proc.stdout.splitlines() if ln.startswith("    - ")]
    assert len(failures) == 1, proc.stdout  # the one failing bound, in one line, with its amount
    assert all(w in failures[0] for w in words) and re.search(r"exceeds .* by \d", failures[0]), failures

    proc = fleet("design", f, "--json")
    no_traceback(proc)
    assert proc.returncode == 1
    d = strict_json(proc.stdout)
    assert d["admissible"] is False and len(d["failures"]) == 1
    assert all(w in d["failures"][0] for w in words)
    assert d["wheel_limit_m_s"] == pytest.approx(preset("epuck").wheel.max_wheel_speed)
    assert (d["wheel_speed_m_s"] > d["wheel_limit_m_s"]) is (case == "lookahead_2cm")


# --------------------------------------------------------------------------- fleet simulate

RUN_KEYS = (
    "scenario",
    "completed",
    "steps",
    "sim_time_s",
    "wall_time_s",
    "min_distance_m",
    "collisions",
    "min_reference_separation_m",
    "required_reference_separation_m",
    "obstacle_violations",
    "arena_violations",
)
ROBOT_KEYS = (
    "reached_goal",
    "time_to_goal_s",
    "final_error_m",
    "qp_solves",
    "qp_failures",
    "fallbacks",
    "tube_exits",
    "step_time_ms",
)


def simulate(scenario: Path, out: Path, *extra: str) -> tuple[subprocess.CompletedProcess[str], dict]:
    proc = fleet("simulate", scenario, "--out", out, *extra)
    no_traceback(proc)
    summary_file = out / "summary.json"
    summary = strict_json(summary_file.read_text()) if summary_file.exists() else {}
    return proc, summary


@pytest.fixture(scope="module")
def two_robot_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("two")
    return simulate(SCENARIOS / "paper_two_robots.toml", out)


def test_simulate_two_robots_succeeds_with_full_summary(two_robot_run):
    proc, s = two_robot_run
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "fleet: error" not in proc.stderr
    for key in RUN_KEYS:
        assert key in s, key
    assert s["scenario"] == "paper_two_robots"
    assert s["completed"] is True
    assert s["collisions"] == 0
    assert s["obstacle_violations"] == 0
    assert s["arena_violations"] == 0
    assert s["steps"] > 0
    assert s["sim_time_s"] == pytest.approx(s["steps"] * preset("epuck").Ts, rel=1e-9)
    assert s["sim_time_s"] <= 60.0 + 1e-9  # the scenario's duration
    assert s["wall_time_s"] > 0
    # The coordination guarantee (docs/method.md §6): committed references at least R apart, so the
    # bodies never touch.
    assert s["min_reference_separation_m"] >= s["required_reference_separation_m"] - 1e-9
    assert s["required_reference_separation_m"] > 2 * preset("epuck").robot_radius
    assert s["min_distance_m"] > 2 * preset("epuck").robot_radius
    assert set(s["robots"]) == {"r1", "r2"}
    for rid, r in s["robots"].items():
        for key in ROBOT_KEYS:
            assert key in r, (rid, key)
        assert r["reached_goal"] is True, rid
        assert r["final_error_m"] <= 0.02
        assert 0 < r["time_to_goal_s"] <= s["sim_time_s"] + 1e-9
        assert r["qp_solves"] >= s["steps"] * 0.5
        assert r["qp_failures"] >= 0 and r["fallbacks"] >= 0
        assert r["tube_exits"] == 0
        st = r["step_time_ms"]
        assert set(st) >= {"p50", "p99", "max"}
        assert 0 <= st["p50"] <= st["p99"] <= st["max"]
    assert "summary.json" in proc.stdout


def test_simulate_seed_is_recorded_and_deterministic(tmp_path, two_robot_run):
    _, default = two_robot_run
    assert default["seed"] == 0  # the scenario's [simulation] seed
    runs = []
    for k in range(2):
        proc, s = simulate(SCENARIOS / "paper_two_robots.toml", tmp_path / f"seed{k}", "--seed", "7")
        assert proc.returncode == 0, proc.stdout + proc.stderr
        assert s["seed"] == 7
        assert s["collisions"] == 0
        assert all(r["reached_goal"] for r in s["robots"].values())
        runs.append(s)
    a, b = runs

    def figures(s: dict) -> tuple:
        return (
            s["steps"],
            s["min_distance_m"],
            s["min_reference_separation_m"],
            tuple((rid, r["final_error_m"], r["time_to_goal_s"]) for rid, r in sorted(s["robots"].items())),
        )

    assert figures(a) == figures(b)
    # The seed really drives the disturbances: another seed gives another trajectory.
    assert figures(a) != figures(default)


def test_simulate_without_delay_compensation_says_so_and_keeps_the_figures(tmp_path, two_robot_run):
    """By default every plan is made a step ahead and the summary says so; with
    ``--no-delay-compensation`` it does not, and where constraint (a) never binds the safety
    figures are the same (docs/method.md §5)."""
    _, default = two_robot_run
    proc, s = simulate(SCENARIOS / "paper_two_robots.toml", tmp_path / "nd", "--no-delay-compensation")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert default["delay_compensation"] is True and "delay_compensation" not in s
    assert s["steps"] == default["steps"] and s["collisions"] == 0
    assert s["min_reference_separation_m"] == pytest.approx(default["min_reference_separation_m"], abs=1e-9)
    assert all(r["reached_goal"] and r["tube_exits"] == 0 for r in s["robots"].values())


def test_simulate_too_short_fails_and_names_robots(tmp_path):
    f = tmp_path / "short.toml"
    f.write_text(scenario_toml(duration=2.0, name="short"))
    out = tmp_path / "out"
    proc, s = simulate(f, out)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert "r1" in proc.stderr and "r2" in proc.stderr
    assert "goal" in proc.stderr
    # The summary is still written, and agrees.
    assert s["steps"] == 20
    assert s["collisions"] == 0
    assert not any(r["reached_goal"] for r in s["robots"].values())
    assert all(r["final_error_m"] > 0.02 for r in s["robots"].values())


# --------------------------------------------------------------------------- bad input


def scenario_toml(
    *,
    name: str = "cli_test",
    duration: float = 60.0,
    arena: tuple[float, float, float, float] = (-1.0, 1.0, -1.0, 1.0),
    controller: str = "",
    robots: str | None = None,
    obstacles: str = "",
) -> str:
    """A valid two-robot head-on scenario, with optional replacements."""
    if robots is None:
        robots = """
[[robots]]
id = "r1"
start = [-0.6, 0.0, 0.0]
goal = [0.6, 0.0]

[[robots]]
id = "r2"
start = [0.6, 0.0, 3.141592653589793]
goal = [-0.6, 0.0]
"""
    return (
        f'name = "{name}"\nduration = {duration}\n\n[arena]\nbounds = {list(arena)}\n\n'
        f"{controller}\n[simulation]\nseed = 0\n{robots}\n{obstacles}\n"
    )


def _robots(*specs: tuple[str, list[float], list[float]]) -> str:
    return "".join(f'\n[[robots]]\nid = "{i}"\nstart = {s}\ngoal = {g}\n' for i, s, g in specs)


BAD = {
    "unknown_key": (scenario_toml(controller="[controller]\nhorizn = 20\n"), "controller.horizn"),
    "non_numeric_weight": (
        scenario_toml(controller='[controller]\nR = [20.0, "heavy"]\n'),
        "controller.R[1]",
    ),
    "negative_duration": (scenario_toml(duration=-5.0), "duration"),
    "unknown_preset": (scenario_toml(controller='[controller]\npreset = "fast"\n'), "controller.preset"),
    "start_in_obstacle": (
        scenario_toml(obstacles="[[obstacles]]\ncircle = { center = [-0.6, 0.0], radius = 0.1 }\n"),
        "robots[0].start",
    ),
    "starts_too_close": (
        scenario_toml(
            robots=_robots(("r1", [-0.1, 0.0, 0.0], [0.6, 0.0]), ("r2", [0.05, 0.1, 0.0], [-0.6, 0.0]))
        ),
        "robots[1].start",
    ),
    "goal_outside_arena": (
        scenario_toml(
            robots=_robots(("r1", [-0.6, 0.0, 0.0], [0.6, 0.0]), ("r2", [0.6, 0.0, 3.14], [-1.4, 0.0]))
        ),
        "robots[1].goal",
    ),
    "duplicate_id": (
        scenario_toml(
            robots=_robots(("r1", [-0.6, 0.0, 0.0], [0.6, 0.0]), ("r1", [0.6, 0.0, 3.14], [-0.6, 0.0]))
        ),
        "robots[1].id",
    ),
    "goal_walled_in": (
        scenario_toml(obstacles="[[obstacles]]\npolygon = [[0.2, -1], [0.3, -1], [0.3, 1], [0.2, 1]]\n"),
        "robots[0].goal",
    ),
    "toml_syntax": ('name = "broken\nduration = 60\n', "file"),
    "inadmissible_epsilon": (scenario_toml(controller="[controller]\nepsilon = 0.05\n"), "controller"),
    "missing_file": (None, "file"),
    # Allowed by the schema (weights >= 0), but the reference generator's Riccati equation has
    # no stabilising solution: still bad input, not a crash.
    "degenerate_ref_weights": (
        scenario_toml(controller="[controller]\nref_Q = [0.0, 0.0, 0.0, 0.0]\n"),
        "controller",
    ),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_input_exits_2_with_one_line(tmp_path, case):
    text, field = BAD[case]
    f = tmp_path / f"{case}.toml"
    if text is not None:
        f.write_text(text)
    proc = fleet("simulate", f, "--out", tmp_path / "out")
    no_traceback(proc)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    lines = proc.stderr.strip("\n").split("\n")
    assert len(lines) == 1, proc.stderr
    line = lines[0]
    assert line.startswith("fleet: error: "), line
    assert f"fleet: error: {field}" in line, line
    assert not (tmp_path / "out" / "summary.json").exists()
    if case == "inadmissible_epsilon":
        assert "epsilon" in line
    if case == "missing_file":
        assert str(f.name) in line


@pytest.mark.parametrize("case", ["unknown_key", "non_numeric_weight", "toml_syntax", "missing_file"])
def test_bad_input_design_exits_2_with_one_line(tmp_path, case):
    text, field = BAD[case]
    f = tmp_path / f"{case}.toml"
    if text is not None:
        f.write_text(text)
    proc = fleet("design", f, "--json")
    no_traceback(proc)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    lines = proc.stderr.strip("\n").split("\n")
    assert len(lines) == 1 and lines[0].startswith(f"fleet: error: {field}"), proc.stderr
    assert proc.stdout == ""


def test_bad_input_template_is_valid(tmp_path):
    """The unmodified template runs to success, so each BAD case fails for its own reason only."""
    f = tmp_path / "ok.toml"
    f.write_text(scenario_toml())
    proc, s = simulate(f, tmp_path / "out")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert proc.stderr == ""
    assert s["scenario"] == "cli_test"
    assert s["collisions"] == 0
    assert all(r["reached_goal"] for r in s["robots"].values())


@pytest.mark.parametrize("value", ["0.1", "nan", "inf", "abc", "61"])
def test_bad_lease_is_refused_naming_the_option(tmp_path, value):
    proc = fleet("run", SCENARIOS / "paper_two_robots.toml", "--out", tmp_path, "--lease", value)
    no_traceback(proc)
    assert proc.returncode == 2, proc.stderr
    last = proc.stderr.strip().splitlines()[-1]  # argparse's usage, then one error line
    assert last.startswith("fleet run: error: argument --lease: "), proc.stderr
    assert not (tmp_path / "summary.json").exists()


def test_lease_reaches_the_zenoh_configuration(tmp_path):
    """``--lease`` [s] becomes Zenoh's transport lease [ms], on loopback and over a
    ``--zenoh-config`` file (whose own lease stands when --lease is not given)."""
    import argparse

    from transport.bus import session_config
    from transport.net import NetConfig
    from transport.process import add_common_args

    assert json.loads(NetConfig(lease=1.0).zenoh().get_json("transport/link/tx/lease")) == 1000
    ap = argparse.ArgumentParser()
    add_common_args(ap)
    conf = tmp_path / "peer.json5"
    conf.write_text('{mode: "peer", transport: {link: {tx: {lease: 3000}}}}\n')

    def lease(*argv: str) -> int:
        return json.loads(
            session_config(ap.parse_args(["--scenario", "s", *argv])).get_json("transport/link/tx/lease")
        )

    assert lease() == 10000
    assert lease("--lease", "1") == 1000
    assert lease("--zenoh-config", str(conf)) == 3000
    assert lease("--zenoh-config", str(conf), "--lease", "2.5") == 2500


def test_mode_reaches_the_zenoh_configuration_and_contradictions_are_refused(tmp_path):
    """``--mode`` becomes the session mode; a client listens on nothing.  ``--mode`` with a
    ``--zenoh-config`` file, ``--listen`` on a client or a client without ``--connect`` is one
    line naming the option, exit 2; a client whose router is not there, one line and exit 1."""
    import argparse

    from transport.bus import session_config
    from transport.net import NetConfig, free_port
    from transport.process import add_common_args

    ap = argparse.ArgumentParser()
    add_common_args(ap)

    def conf(*argv: str):
        return session_config(ap.parse_args(["--scenario", "s", *argv]))

    assert json.loads(conf().get_json("mode")) == "peer"
    assert json.loads(conf().get_json("listen/endpoints")) == ["tcp/127.0.0.1:0"]
    router = conf("--mode", "router", "--listen", "tcp/127.0.0.1:7447")
    assert json.loads(router.get_json("mode")) == "router"
    assert json.loads(router.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7447"]
    client = conf("--mode", "client", "--connect", "tcp/127.0.0.1:7447")
    assert json.loads(client.get_json("mode")) == "client"
    assert json.loads(client.get_json("listen/endpoints")) == []
    assert json.loads(client.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7447"]
    with pytest.raises(ValueError, match="mode 'hub'"):
        NetConfig(mode="hub").zenoh()
    file = tmp_path / "peer.json5"
    file.write_text('{mode: "peer"}\n')
    unreachable = f"tcp/127.0.0.1:{free_port()}"  # nobody listens there: a client does not wait
    for argv, code, option in (
        (["--mode", "client", "--zenoh-config", str(file)], 2, "--mode"),
        (["--mode", "client", "--listen", "tcp/127.0.0.1:1"], 2, "--listen"),
        (["--mode", "client"], 2, "--connect"),
        (["--mode", "client", "--connect", unreachable], 1, "--connect"),
    ):
        proc = subprocess.run(
            [sys.executable, "-m", "agent", "--scenario", str(SCENARIOS / "paper_two_robots.toml"),
             "--robot", "r1", *argv],
            capture_output=True, text=True, timeout=120, cwd=ROOT,
        )  # fmt: skip
        no_traceback(proc)
        assert proc.returncode == code, (argv, proc.stderr)
        assert proc.stderr.strip().splitlines() == [proc.stderr.strip()], proc.stderr
        assert proc.stderr.startswith(f"error: {option}: "), proc.stderr


@pytest.mark.parametrize("value", ["ring", ""])
def test_bad_topology_is_refused_naming_the_option(tmp_path, value):
    proc = fleet("run", SCENARIOS / "paper_two_robots.toml", "--out", tmp_path, "--topology", value)
    no_traceback(proc)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip().splitlines()[-1].startswith("fleet run: error: argument --topology: "), (
        proc.stderr
    )
    assert not (tmp_path / "summary.json").exists()


@pytest.mark.parametrize("value", ["0", "-0.5", "0.9", "1"])
def test_bad_tracker_deadline_is_refused_naming_the_option(value):
    """A deadline past 0.75·Ts leaves the simulated tracker too little of the step for its own
    work (its ticks would fall further behind each step): one line, exit 2, before any
    network is opened."""
    proc = subprocess.run(
        [sys.executable, "-m", "tracker", "--scenario", str(SCENARIOS / "paper_two_robots.toml"),
         "--clock", "realtime", "--deadline", value],
        cwd=ROOT, env=dict(os.environ, OMP_NUM_THREADS="1"), capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    no_traceback(proc)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.count("\n") == 1, proc.stderr
    assert proc.stderr.startswith(f"tracker: error: --deadline: {float(value)} outside (0, 0.75]"), (
        proc.stderr
    )


def test_a_realtime_run_short_of_cpu_says_so_in_one_line():
    """``fleet run`` on the realtime clock explains many misses or a lagging clock (the
    figures of a 32-robot run on 2 cores), and says nothing for a run that kept up."""
    from fleet.cli import realtime_note

    robots = {f"r{i}": {} for i in range(1, 33)}
    kept_up = {"steps": 300, "robots": robots, "deadline_misses": 20, "sim_time_s": 30.0, "wall_time_s": 30.4}
    assert realtime_note(kept_up, 0.1) is None
    overloaded = {**kept_up, "deadline_misses": 7143, "wall_time_s": 38.3}
    note = realtime_note(overloaded, 0.1)
    assert note is not None and "\n" not in note
    assert "74.4 % of the deadlines were missed" in note
    assert "8.3 s behind the wall clock" in note and "32 agents at Ts = 0.1 s" in note
    assert "fleet bench" in note
    only_late = realtime_note({**kept_up, "wall_time_s": 40.0}, 0.1)
    assert only_late is not None and "missed" not in only_late and "10.0 s behind" in only_late
    only_misses = realtime_note({**kept_up, "deadline_misses": 97}, 0.2)
    assert only_misses is not None and "1.0 % of the deadlines" in only_misses and "behind" not in only_misses


@pytest.mark.parametrize("seed", ["-1", "4294967296", "x"])
def test_a_seed_out_of_range_is_one_line_and_exit_2(seed):
    proc = fleet("simulate", str(SCENARIOS / "paper_two_robots.toml"), "--seed", seed)
    no_traceback(proc)
    assert proc.returncode == 2 and "--seed" in proc.stderr.strip().splitlines()[-1], proc.stderr


# --------------------------------------------------------------------------- the camera's error


LAB_CONTROLLER = {"preset": "epuck", "pose_noise": [0.001, 0.015], "W": [0.004, 0.002], "epsilon": 0.0025}
"""The lab scenario's controller (deploy/lab_three_robots.toml): pose_noise[0] = 1 mm."""


def test_design_and_run_refuse_a_pose_noise_below_the_cameras_floor_error(tmp_path):
    """A floor homography through the synthetic k₁ = −0.3 lens (tests/tracker/test_lens.py)
    fitted without intrinsics predicts its fiducials tens of mm off: ``fleet design`` and
    ``fleet run`` refuse the 1 mm pose_noise in one line naming both figures and the file.
    Fitted on fiducials undistorted through the lens's intrinsics, the error is sub-mm and
    the design passes."""
    cv2 = pytest.importorskip("cv2")
    import numpy as np

    from camera_tools.calibrate import main as calibrate_main
    from camera_tools.synth import PinholeCamera, Renderer
    from fleet.running.scenes import scene_to_toml
    from tracker.intrinsics import Intrinsics

    fiducials = {40: (-1.1, -1.1), 41: (0.0, -1.1), 42: (1.1, -1.1), 43: (1.1, 1.1), 44: (0.0, 1.1),
                 45: (-1.1, 1.1)}  # fmt: skip
    lens = (-0.3, 0.1, 0.0, 0.0, 0.0)
    cam = PinholeCamera.viewing(np.array([(-1.2, -1.2), (1.2, -1.2), (1.2, 1.2), (-1.2, 1.2)]),
                                tilt=math.radians(30.0), height=2.5, width_px=1920, height_px=1440,
                                distortion=lens)  # fmt: skip
    floor = tmp_path / "floor.png"
    image = Renderer(cam, fiducials, marker_size=0.05, fiducial_size=0.08).render({}, seed=3)
    assert cv2.imwrite(str(floor), image)
    Intrinsics(K=cam.intrinsics(), dist=lens, image_size=(1920, 1440)).save(tmp_path / "lens.json")

    def scenario(stem: str, camera: dict[str, Any]) -> Path:
        data = {"name": stem, "duration": 30.0, "arena": {"bounds": [-1.0, 1.0, -1.0, 1.0]},
                "controller": LAB_CONTROLLER,
                "robots": [{"id": "r1", "start": [-0.5, 0.0, 0.0], "goal": [0.5, 0.0], "marker": 1}],
                "camera": {"marker_size": 0.05,
                           "fiducials": [{"id": k, "position": list(v)} for k, v in fiducials.items()],
                           **camera}}  # fmt: skip
        path = tmp_path / f"{stem}.toml"
        path.write_text(scene_to_toml(data))
        return path

    bare = scenario("bare", {"homography": "bare.json"})
    lensed = scenario("lensed", {"homography": "lensed.json", "intrinsics": "lens.json"})
    for scn in (bare, lensed):
        assert calibrate_main([str(scn), "--image", str(floor)]) == 0
    for cmd in (("design", bare), ("run", bare, "--out", tmp_path / "out")):
        proc = fleet(*cmd)
        no_traceback(proc)
        assert proc.returncode == 2, proc.stdout + proc.stderr
        lines = proc.stderr.strip("\n").split("\n")
        assert len(lines) == 1, proc.stderr
        m = re.fullmatch(
            r"fleet: error: controller\.pose_noise: \[0\] = 1\.00 mm is below the camera's floor error "
            r"([0-9.]+) mm \(fiducial \d+, predicted without it\) in (.+): calibrate the lens .*",
            lines[0],
        )
        assert m is not None, lines[0]
        assert float(m[1]) > 10.0 and m[2] == str(tmp_path / "bare.json"), lines[0]
        assert proc.stdout == ""
    assert not (tmp_path / "out" / "summary.json").exists()
    proc = fleet("design", lensed)
    no_traceback(proc)
    assert proc.returncode == 0 and "admissible: yes" in proc.stdout, proc.stdout + proc.stderr
    # Without a homography file there is nothing to check.
    proc = fleet("design", scenario("nofile", {"homography": "missing.json"}))
    assert proc.returncode == 0, proc.stderr


@pytest.mark.parametrize(
    "args, field",
    [
        (["--ros2", "--ros-domain", "233"], "fleet run: error: argument --ros-domain: "),
        (["--ros2", "--ros-domain", "x"], "fleet run: error: argument --ros-domain: "),
        (["--ros-domain", "3"], "--ros-domain: the ROS 2 face is off"),
        (["--ros-listen", "tcp/127.0.0.1:7447"], "--ros-listen: the ROS 2 face is off"),
        (["--ros2", "--ros-listen", "udp/127.0.0.1:7447"], "fleet run: error: argument --ros-listen: "),
        (
            ["--ros2", "--topology", "star", "--ros-listen", "tcp/127.0.0.1:7447"],
            "--ros-listen: in the star topology ROS 2 tools connect to the hub",
        ),
    ],
)
def test_bad_ros2_options_are_refused_in_one_line(tmp_path, args, field):
    proc = fleet("run", SCENARIOS / "paper_two_robots.toml", "--out", tmp_path, *args)
    no_traceback(proc)
    assert proc.returncode == 2, proc.stderr
    assert field in proc.stderr.strip().splitlines()[-1], proc.stderr
    assert not (tmp_path / "summary.json").exists()


def test_a_robot_id_that_cannot_name_a_ros_topic_is_refused_with_ros2(tmp_path):
    """``r-1`` is a fleet id but not a ROS 2 name (``/r-1/pose``): with the ROS face on, the run is
    refused before any process starts; without it, the id is fine."""
    text = (SCENARIOS / "paper_two_robots.toml").read_text().replace('"r1"', '"r-1"')
    f = tmp_path / "dash.toml"
    f.write_text(text)
    proc = fleet("run", f, "--out", tmp_path / "a", "--ros2")
    no_traceback(proc)
    assert proc.returncode == 2, proc.stderr
    assert "robot id 'r-1' cannot name a ROS 2 topic" in proc.stderr.strip().splitlines()[-1], proc.stderr
    f.write_text(text + "\n[ros2]\nenabled = true\n")
    proc = fleet("simulate", f, "--out", tmp_path / "b")
    no_traceback(proc)
    assert proc.returncode == 2, proc.stderr
    assert (
        proc.stderr.strip()
        .splitlines()[-1]
        .endswith(
            "ros2.enabled: robot id 'r-1' cannot name a ROS 2 topic (/r-1/pose): it must start with a letter "
            "and hold only letters, digits and single underscores"
        )
    ), proc.stderr


def test_simulate_one_robot_alone_runs_and_reports_like_any_other(tmp_path):
    """A fleet of one: no pair to measure, so the closing line says so instead of failing on it."""
    scene = (SCENARIOS / "paper_two_robots.toml").read_text()
    one = tmp_path / "alone.toml"
    one.write_text(scene[: scene.rindex("[[robots]]")])
    proc, s = simulate(one, tmp_path / "out")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert s["min_distance_m"] is None and s["collisions"] == 0 and s["robots"]["r1"]["reached_goal"]
    assert "min distance none (one robot), goals reached 1/1" in proc.stdout, proc.stdout
