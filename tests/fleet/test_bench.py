"""``fleet bench`` (fleet/bench.py → benchmarks.bench_scale): the tiny ``--quick`` run
completes, and its JSON has every figure, finite and of the right sign.

No speed threshold is checked here: the figures depend on the machine's load.
What is checked besides the schema is correctness the benchmark reports on
the way: ProxSuite agrees with DAQP on the applied input, and the fleet runs
have no collision.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import json
import math
import os
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "RERUN_ANALYTICS": "0", "PYTHONIOENCODING": "utf-8"}

pytestmark = pytest.mark.slow  # process fleets


def _command() -> list[str]:
    """``-m fleet.cli bench`` once the subcommand is registered, else ``-m fleet.bench`` (same code)."""
    from fleet.cli import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return ["-m", "fleet.cli", "bench"] if "bench" in sub.choices else ["-m", "fleet.bench"]


def _reject_constant(name: str) -> Any:
    raise ValueError(f"non-standard JSON constant {name}")


def positive(x: Any, what: str) -> None:
    assert isinstance(x, int | float) and not isinstance(x, bool), f"{what}: expected a number, got {x!r}"
    assert math.isfinite(x) and x > 0, f"{what}: expected finite > 0, got {x!r}"


def count(x: Any, what: str) -> None:
    assert isinstance(x, int) and not isinstance(x, bool) and x >= 0, f"{what}: expected a count, got {x!r}"


def percentiles(s: dict[str, Any], what: str) -> None:
    for k in ("p50", "p99", "max"):
        positive(s[k], f"{what}.{k}")
    count(s["n"], f"{what}.n")
    assert s["n"] > 0, f"{what}: no samples"
    assert s["p50"] <= s["p99"] <= s["max"], f"{what}: p50 ≤ p99 ≤ max violated: {s}"


@pytest.fixture(scope="module")
def quick(
    tmp_path_factory: pytest.TempPathFactory,
) -> tuple[subprocess.CompletedProcess[str], dict[str, Any]]:
    out = tmp_path_factory.mktemp("bench")
    proc = subprocess.run(
        [sys.executable, *_command(), "--quick", "--out", str(out), "--json", str(out / "b.json")],
        cwd=ROOT, env=ENV, capture_output=True, text=True, encoding="utf-8", timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    data = json.loads((out / "b.json").read_text(), parse_constant=_reject_constant)
    return proc, data


def test_quick_prints_the_tables(quick: tuple[subprocess.CompletedProcess[str], dict[str, Any]]) -> None:
    proc, _ = quick
    assert "Traceback" not in proc.stdout + proc.stderr
    for heading in (
        "[1] per-agent step time",
        "[2] solvers",
        "[3] wire codec",
        "[4] fleet run",
        "[5] realtime",
        "[6] capacity",
    ):
        assert heading in proc.stdout, f"missing {heading!r} in\n{proc.stdout}"
    assert "load average at start" in proc.stdout


def test_quick_json_header(quick: tuple[subprocess.CompletedProcess[str], dict[str, Any]]) -> None:
    _, d = quick
    assert d["schema"] == "fleet-bench/1"
    assert d["quick"] is True
    for key in ("loadavg_at_start",):
        la = d["machine"][key]
        assert len(la) == 3 and all(isinstance(v, int | float) and v >= 0 for v in la)
    assert len(d["loadavg_at_end"]) == 3
    positive(d["machine"]["nproc"], "nproc")
    positive(d["total_wall_s"], "total_wall_s")


def test_quick_step_grid(quick: tuple[subprocess.CompletedProcess[str], dict[str, Any]]) -> None:
    _, d = quick
    cells = {(c["horizon"], c["neighbours"]): c for c in d["step_grid"]}
    assert set(cells) == {(n, k) for n in (10, 20, 40) for k in (1, 8, 32)}
    for (n, k), c in cells.items():
        percentiles(c["step_ms"], f"step N={n} nb={k}")
        percentiles(c["solve_ms"], f"solve N={n} nb={k}")
        assert c["qp_variables"] == 2 * n + 6
        # The nearest ring (up to 6) of lattice neighbours is within reach: its rows are in the QP.
        assert c["mean_coordination_rows"] == pytest.approx(min(k, 6))
        count(c["fallbacks"], "fallbacks")
        assert c["step_ms"]["p50"] >= c["solve_ms"]["p50"]


def test_quick_solvers(quick: tuple[subprocess.CompletedProcess[str], dict[str, Any]]) -> None:
    _, d = quick
    s = d["solvers"]
    positive(s["qps"], "qps")
    v = s["variants"]
    assert "proxsuite" in v
    pytest.importorskip("daqp")
    assert s["reference"] == "daqp_model" and "daqp_model" in v
    for name, row in v.items():
        percentiles(row["ms"], name)
        positive(row["ratio_p50"], f"{name}.ratio_p50")
        positive(row["ratio_p99"], f"{name}.ratio_p99")
        count(row["failures"], f"{name}.failures")
    assert v["daqp_model"]["ratio_p50"] == pytest.approx(1.0)
    # Every ProxSuite variant solves every QP and applies the same input as DAQP.
    for name, row in v.items():
        if name.startswith("proxsuite"):
            assert row["failures"] == 0, name
            assert row["max_dv_first_input"] < 1e-3, name
    positive(s["proxsuite_over_daqp_p50"], "proxsuite_over_daqp_p50")


def test_quick_wire(quick: tuple[subprocess.CompletedProcess[str], dict[str, Any]]) -> None:
    _, d = quick
    w = d["wire"]
    assert set(w["per_message_us"]) == {"plan", "pose", "odom", "tick", "cmd"}
    for name, m in w["per_message_us"].items():
        for k in ("bytes", "encode", "decode", "unpack"):
            positive(m[k], f"wire.{name}.{k}")
        assert m["unpack"] < m["decode"], name  # the strict decoder parses, then checks
    per = w["agent_codec_ms_per_step"]
    assert [float(per[n]) for n in ("3", "8", "16", "32")] == sorted(
        float(per[n]) for n in ("3", "8", "16", "32")
    )


def test_quick_fleet_runs(quick: tuple[subprocess.CompletedProcess[str], dict[str, Any]]) -> None:
    _, d = quick
    runs = d["fleet_runs"]
    assert {r["clock"] for r in runs} == {"lockstep", "realtime"}
    for r in runs:
        what = f"{r['clock']} {r['robots']}"
        assert "error" not in r, f"{what}: {r.get('error')}: {r['verdict']}"
        for k in ("steps", "sim_s", "wall_s", "rtf"):
            positive(r[k], f"{what}.{k}")
        count(r["deadline_misses"], f"{what}.deadline_misses")
        assert 0.0 <= r["miss_rate"] <= 1.0
        assert r["collisions"] == 0, what
        assert (r["exchange"], r["topology"]) == ("relay", "star"), what  # the defaults: large-fleet setup
        assert r["delay_compensation"] is True, what  # as fleet run's default
        for k in ("agent_p50", "agent_max", "agent_peak_max", "tracker", "supervisor"):
            positive(r["rss_mb"][k], f"{what}.rss_mb.{k}")
        assert r["rss_mb"]["agents_sampled"] == r["robots"]
        for k in ("cores_used", "agents_cores", "agent_ms_per_step", "window_s"):
            positive(r["cpu"][k], f"{what}.cpu.{k}")
        percentiles(r["latency"]["pose_to_command_ms"], f"{what} pose→command")
        percentiles(r["latency"]["tick_to_command_ms"], f"{what} tick→command")
        positive(r["ready_s"], f"{what}.ready_s")  # launch to first tick: inside the whole run
        assert r["ready_s"] < r["total_s"] - r["wall_s"] + 1e-6, what
    positive(d["lockstep_rtf"]["3"], "lockstep_rtf[3]")
    positive(d["rss_mb_per_agent"]["p50"], "rss_mb_per_agent.p50")
    assert d["latency"], "no latency figures"
    assert d["goals"] and all(isinstance(g["met"], bool) for g in d["goals"])
    # The capacity run is not a goal: the goals are at Ts = 0.1 s.
    assert [g["robots"] for g in d["goals"]] == [3]
    assert [r["Ts_s"] for r in runs if r["clock"] == "realtime"] == pytest.approx([0.1, 0.2])
    # Each run's latency under its own key: the capacity run does not overwrite the goal run's.
    assert set(d["latency"]) == {"lockstep_3", "realtime_3", "realtime_3_capacity"}
    goal_run = next(r for r in runs if r["clock"] == "realtime" and r.get("purpose") != "capacity")
    assert d["latency"]["realtime_3"] == goal_run["latency"]


def test_quick_capacity(quick: tuple[subprocess.CompletedProcess[str], dict[str, Any]]) -> None:
    """[6]: the realtime fleet again at Ts = 0.2 s; the CPU of all its processes a step, from
    that run's own figures, and the cores it makes at Ts = 0.1 s."""
    _, d = quick
    c = d["capacity"]
    run = next(r for r in d["fleet_runs"] if r.get("purpose") == "capacity")
    assert (c["robots"], c["Ts_s"], c["goal_Ts_s"]) == (3, pytest.approx(0.2), 0.1)
    assert c["steps"] == run["steps"] and c["deadline_misses"] == run["deadline_misses"]
    cpu = run["cpu"]
    assert c["cpu_ms_per_step"] == pytest.approx(1e3 * cpu["cores_used"] * cpu["window_s"] / (c["steps"] - 1))
    positive(c["cpu_ms_per_step"], "cpu_ms_per_step")
    assert c["cpu_ms_per_robot_step"] == pytest.approx(c["cpu_ms_per_step"] / 3)
    assert c["cores_needed_at_goal_Ts"] == pytest.approx(c["cpu_ms_per_step"] / 100.0)
    # The premise: the fleet's CPU follows its step rate.  The same 3 robots at Ts = 0.1 s, in
    # the run before, used the cores the figure says within a factor of 3: a shared machine,
    # and at 3 robots the work that follows the wall clock (recorder, Zenoh) is half of it;
    # a wrong unit is off by 10 or more (a period not applied: the Ts_s check above).
    at_goal = next(r for r in d["fleet_runs"] if r["clock"] == "realtime" and r is not run)
    assert 1 / 3 <= c["cores_needed_at_goal_Ts"] / at_goal["cpu"]["cores_used"] <= 3.0
    assert c["nproc"] == d["machine"]["nproc"]


def test_hex_lattice_neighbours_keep_their_distance() -> None:
    """The synthetic neighbours of the step grid: the 32 nearest lattice points are ≥ 1
    apart (times the spacing r_i + r_j + √2·ε), the first ring exactly 6 at distance 1."""
    from benchmarks import bench_scale

    pts = bench_scale.hex_offsets(32)
    assert pts.shape == (32, 2)
    r = np.hypot(pts[:, 0], pts[:, 1])
    assert np.all(np.diff(r) >= -1e-12)
    assert np.sum(np.isclose(r, 1.0)) == 6
    d = np.hypot(*(pts[:, None, :] - pts[None, :, :]).transpose(2, 0, 1))
    assert d[~np.eye(32, dtype=bool)].min() == pytest.approx(1.0)


@pytest.mark.parametrize(("n", "radius", "half"), [(32, 1.55, 1.8), (48, 2.31, 2.56)])
def test_large_swap_files_match_generator(n: int, radius: float, half: float) -> None:
    from fleet.running.scenes import COMPACT_CONTROLLER, antipodal_swap
    from ground.scenario import load_scenario, parse_scenario

    from_file = load_scenario(ROOT / "scenarios" / f"swap_{n}.toml")
    data = antipodal_swap(n, radius=radius, arena=(-half, half, -half, half), duration=300.0)
    data["controller"] = dict(COMPACT_CONTROLLER)
    generated = parse_scenario(data)
    assert dataclasses.replace(from_file, source="") == dataclasses.replace(generated, source="")


def test_fleet_runs_sum_the_agents_closing_counts() -> None:
    """A fleet run's row sums the counters of the agents' closing lines, the news of places
    heard later than the reach's proof assumes among them (plans by place only)."""
    from benchmarks import bench_scale

    common = "0 steered ahead, 9 plans taken ({}), {}0 injected faults, 0 rejected payloads"
    lines = [
        "[agent r1] stopped after 9 steps: 10 solves, 1 fallbacks, 0 tube exits, 2 blind holds, "
        + common.format("place", "4 places heard over 2 steps late, "),
        "[agent r2] stopped after 9 steps: 10 solves, 0 fallbacks, 3 tube exits, 0 blind holds, "
        + common.format("place", "7 places heard over 2 steps late, "),
        "[agent r3] stopped after 9 steps: 10 solves, 0 fallbacks, 0 tube exits, 0 blind holds, "
        + common.format("mesh", ""),
        "[tracker] run ended at step 9; 0 deadline misses, 0 rejected payloads",
    ]
    counters = bench_scale._agent_counters
    assert counters(lines) == {
        "solves": 30, "fallbacks": 1, "tube_exits": 3, "blind_holds": 2, "agents": 3, "places_late": 11,
    }  # fmt: skip
    # A fleet whose plans go to every agent measures no lag: not a measured 0.
    assert counters(lines[2:])["places_late"] is None and counters(lines[2:])["solves"] == 10


def test_solver_variants_run_in_shuffled_order(monkeypatch: pytest.MonkeyPatch) -> None:
    """[2] times each variant on the same QP one after another.  The one that runs right
    after a ProxSuite variant finds the QP and ProxSuite's code in the cache, so a fixed
    order (even rotated) always times the same variant cold: the order is shuffled per QP,
    and every variant follows every other one."""
    from benchmarks import bench_scale

    bench = bench_scale
    calls: list[tuple[int, str]] = []

    class Fake:
        def __init__(self, name: str, seq: dict[str, Any]):
            self.name = name

        def prepare(self, prob: dict[str, Any]) -> None:
            pass

        def solve(self, prob: dict[str, Any], warm: Any) -> tuple[Any, int]:
            calls.append((prob["i"], self.name))
            return np.zeros(6), 1

    names = ["a", "b", "c", "d"]
    variants = [(n, n, lambda s, n=n: Fake(n, s)) for n in names]
    monkeypatch.setattr(bench, "solver_variants", lambda full: variants)
    seq = {"qps": [{"prob": {"i": i}, "warm": None} for i in range(40)]}
    out = bench.compare_solvers([seq], False, lambda _: None)

    assert out["qps"] == 40
    orders = [tuple(n for i, n in calls if i == q) for q in range(40)]
    assert all(sorted(o) == names for o in orders)  # each variant once per QP
    assert {o[0] for o in orders} == set(names)
    pairs = {(o[j], o[j + 1]) for o in orders for j in range(len(o) - 1)}
    assert pairs == {(x, y) for x in names for y in names if x != y}
    calls.clear()  # seeded: a second run times them in the same orders
    bench.compare_solvers([seq], False, lambda _: None)
    assert [tuple(n for i, n in calls if i == q) for q in range(40)] == orders


def test_cpu_figures_cover_a_window_shorter_than_the_sampling_period() -> None:
    """A quick lockstep run can step for less time than the sampler's period: its CPU is taken
    from the sample before the window to the one after, never as nothing."""
    from benchmarks import bench_scale

    sampler = bench_scale.Sampler
    samples = [(0.0, 1.0), (0.25, 1.2), (0.5, 1.3)]
    assert sampler._between(samples, 0.05, 0.19) == pytest.approx(0.2)  # inside one period
    assert sampler._between(samples, 0.0, 0.5) == pytest.approx(0.3)
    assert sampler._between(samples, 0.3, 0.4) == pytest.approx(0.1)
    assert sampler._between([], 0.0, 1.0) == 0.0


def test_cpu_harness_splits_a_fleets_cpu_by_process_and_thread(tmp_path):
    """``fleet bench --cpu 3``: the marginal CPU per robot-step of ``fleet run`` (defaults,
    ``--ros2``, ``--no-delay-compensation``, place, relay + star) next to ``fleet simulate``'s,
    from two run lengths, with its split by process role and by thread.  A fleet of processes costs more
    than the one-process simulator (it does the same math and talks besides).  The split of three
    robots' short runs is mostly start-up noise, so only its parts and their accounting are
    checked here, not their sizes: the ROS 2 face's CPU is its own role's ("ros2"), in the
    ``--ros2`` row only."""
    out = tmp_path / "cpu.json"
    res = subprocess.run(
        [sys.executable, *_command(), "--cpu", "3", "--cpu-s", "2,20", "--out", str(tmp_path),
         "--json", str(out)],
        cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr[-2000:]
    d = json.loads(out.read_text())
    assert d["schema"] == "fleet-bench-cpu/1" and d["robots"] == 3
    sim, *fleets = d["rows"]
    ros2 = importlib.util.find_spec("rosbags") is not None  # the ros2 extra, in the test extras
    labels = ["fleet run (defaults)", "fleet run (defaults), Zenoh's own sizes",
              *(["fleet run --ros2"] if ros2 else []), "fleet run --no-delay-compensation",
              "fleet run --exchange place", "fleet run --exchange relay --topology star"]  # fmt: skip
    assert sim["config"] == "fleet simulate" and [r["config"] for r in fleets] == labels
    for r in d["rows"]:
        assert r["steps"][1] > r["steps"][0] > 0 and math.isfinite(r["ms_per_robot_step"]), r
        assert r["ms_per_robot_step"] > 0, r
        # Marginals: a difference of two runs, so a small part (simulate's system time) can come out
        # a little negative; system time is part of the total, though, and processes switch.
        assert r["sys_ms_per_robot_step"] < r["ms_per_robot_step"] and math.isfinite(
            r["csw_per_robot_step"]
        ), r
    for r in fleets:
        assert r["ms_per_robot_step"] > sim["ms_per_robot_step"], (r, sim)
        assert r["csw_per_robot_step"] > 0, r
        roles = {"agents", "tracker", "supervisor", *(["ros2"] if r["config"] == "fleet run --ros2" else [])}
        assert roles <= set(r["by_role_ms"]) <= roles | {"launcher"}, r["by_role_ms"]
        assert {"main thread", "zenoh runtime"} <= set(r["by_thread_ms"]), r["by_thread_ms"]
        split = sum(r["by_role_ms"].values())
        assert split == pytest.approx(sum(r["by_thread_ms"].values()), rel=1e-6)  # one sample set
    assert "× simulate" in res.stdout
    if not ros2:
        assert d["ros2"] is None and "fleet run --ros2: skipped" in res.stdout
        return
    with_, without = fleets[2], fleets[0]
    face = with_["by_role_ms"]["ros2"]
    positive(face, "ros2 ms per robot-step")
    assert d["ros2"] == pytest.approx(
        {
            "ms_per_robot_step": face,
            "over_fleet": face / with_["ms_per_robot_step"],
            "over_agents": face / with_["by_role_ms"]["agents"],
            "agents_with_over_without": with_["by_role_ms"]["agents"] / without["by_role_ms"]["agents"],
        }
    )
    assert "the ROS 2 face (role ros2)" in res.stdout and "agents with --ros2 / without" in res.stdout


def test_cpu_harness_names_each_process_by_the_module_it_runs() -> None:
    """The split's roles: the ROS 2 face (``python -m ros2_link``) is not an agent, nor is the
    launcher; a child not yet exec'd (the launcher's command line) stays the launcher's."""
    from benchmarks import bench_cpu

    role = bench_cpu._role
    py = sys.executable
    assert role(f"{py} -m agent --scenario s.toml --robot e1 ") == "agents"
    assert role(f"{py} -m tracker --scenario s.toml ") == "tracker"
    assert role(f"{py} -m supervisor --scenario s.toml ") == "supervisor"
    assert role(f"{py} -m ros2_link --scenario s.toml --connect tcp/127.0.0.1:7447 ") == "ros2"
    assert role(f"{py} -m fleet.cli run s.toml --ros2 ") == "launcher"


def test_cpu_harness_refuses_bad_lengths_in_one_line(tmp_path):
    res = subprocess.run(
        [sys.executable, *_command(), "--cpu", "3", "--cpu-s", "6,2", "--out", str(tmp_path)],
        cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert res.returncode == 2 and res.stderr.strip().splitlines() == [
        "fleet: error: --cpu-s: two lengths 0 < S1 < S2 <= 3600 [s], got '6,2'"
    ], res.stderr


BURN_CHILD = """
import sys, threading, time
seconds = float(sys.argv[-1])
def spin():
    while time.thread_time() < seconds:
        pass
threads = [threading.Thread(target=spin) for _ in range(2)]
for t in threads:
    t.start()
for t in threads:
    t.join()
"""
BURN_PARENT = """
import json, subprocess, sys
from pathlib import Path
code, seconds, out = sys.argv[1], sys.argv[2], Path(sys.argv[3])
kids = [subprocess.Popen([sys.executable, "-c", code, "-m", "agent", seconds]) for _ in range(2)]
assert all(k.wait(timeout=60) == 0 for k in kids)
out.mkdir(parents=True, exist_ok=True)
(out / "summary.json").write_text(json.dumps({"steps": 1}))
"""


def test_cpu_ratio_counts_each_cpu_second_once(tmp_path):
    """The measurement behind the CPU ratio (``fleet bench --cpu``, target: fleet run against
    fleet simulate) is checked on a workload whose CPU is known by construction: two processes
    that look like agents to the harness (``-m agent`` on their command line), each with two
    threads that spin until each has used exactly ``T`` s of CPU (``time.thread_time``).  Run at
    T = 0.2 s and T = 0.8 s, the marginal CPU between the runs is 2 × 2 × 0.6 = 2.4 s, so the
    harness must report 1 CPU second per thread-second, in its exact total and in its sampled
    split by process role and by thread.  Counting a process's threads twice, adding a run's
    CPU to the one before it (RUSAGE_CHILDREN is cumulative), or summing the short run into the
    long one all double a term, which these bounds reject."""
    from benchmarks import bench_cpu

    h = bench_cpu
    measured = []
    for T in (0.2, 0.8):
        out = tmp_path / f"burn_{T}"
        cmd = [sys.executable, "-c", BURN_PARENT, BURN_CHILD, str(T), str(out)]
        total, roles, kinds, wall, counters = h._measure(cmd, out)
        assert 0 <= counters["sys_s"] <= total and counters["csw"] >= 0, counters
        assert wall > 0 and total >= 2 * 2 * T, (T, total)  # at least the spinning itself
        measured.append((total, roles, kinds))
    thread_seconds = 2 * 2 * (0.8 - 0.2)
    m = h.marginal(measured[0], measured[1], thread_seconds)
    per_unit = m["ms_per_robot_step"] / 1e3  # CPU s per thread-second spun
    assert 0.9 < per_unit < 1.15, m
    # The sampled split, role by role: a thread's last poll period (50 ms) before its process
    # exits is missed, up to 0.2 s of the 2.4 s here, in either run.
    assert 0.8 < m["by_role_ms"]["agents"] / 1e3 < 1.15, m
    assert sum(m["by_role_ms"].values()) == pytest.approx(sum(m["by_thread_ms"].values()), rel=1e-9)
    assert m["by_thread_ms"].get("callbacks (python)", 0.0) / 1e3 > 0.8 * per_unit, m  # spun off-main
    with pytest.raises(ValueError, match="no more work"):
        h.marginal(measured[1], measured[0], 0)


def test_targets_quick_prints_and_writes_every_target(tmp_path):
    """``fleet bench --targets``: the four runtime targets of ``fleet run`` with its default flags,
    each with its goal, its figure and its verdict, in the printout and the JSON.  ``--quick``
    measures them on three robots: the plumbing, not the figures.  The verdicts must follow from
    the figures they print (no figure is checked against the machine's speed)."""
    out = tmp_path / "targets.json"
    res = subprocess.run(
        [sys.executable, *_command(), "--targets", "--quick", "--out", str(tmp_path), "--json", str(out)],
        cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    d = json.loads(out.read_text(), parse_constant=_reject_constant)
    assert d["schema"] == "fleet-bench-targets/1" and d["quick"] is True
    t = {x["target"]: x for x in d["targets"]}
    assert sorted(t) == [1, 2, 3, 4]
    sim, run = d["cpu_rows"]
    assert (sim["config"], run["config"]) == ("fleet simulate", "fleet run (defaults)")
    assert t[1]["measured"] == pytest.approx(run["ms_per_robot_step"] / sim["ms_per_robot_step"])
    assert t[1]["met"] == (t[1]["measured"] <= 2.0)
    # Beside it, the floor of a step's fewest messages: three agents on a ring of cells of one,
    # each taking its two neighbours' plans; its least ratio is the floor over the same math.
    # Measured at the pace of a fleet that would meet target 1 on this machine's cores.
    from benchmarks import bench_targets

    floor = t[1]["detail"]["floor"]
    # Per plan of its own: a neighbour may still answer the step at which this agent stopped.
    assert floor["pattern"] == "step" and 1.5 <= floor["plans_per_step"] <= 2.1, floor
    assert set(floor["by_role_ms"]) == {"tracker", "agents", "supervisor"}, floor
    positive(floor["ms_per_robot_step"], "floor.ms_per_robot_step")
    assert floor["rate"] == pytest.approx(
        bench_targets.floor_rate(3, sim["ms_per_robot_step"], d["machine"]["nproc"])
    )
    if sim["ms_per_robot_step"] > 0:
        assert floor["least_ratio"] == pytest.approx(
            1 + floor["ms_per_robot_step"] / sim["ms_per_robot_step"]
        )
        assert f"{floor['least_ratio']:.2f}x fleet simulate here" in res.stdout
    # Processes cost more: in total, for each run length.  (Not the marginal ratio: over --quick's
    # 300 robot-steps fleet simulate's marginal CPU is about 0.1 s, within the spread of its
    # start-up on a loaded machine, and has come out negative.)
    assert all(r > s for r, s in zip(run["cpu_s"], sim["cpu_s"], strict=True)), (run["cpu_s"], sim["cpu_s"])
    r3 = d["realtime_runs"]["3"]
    assert (r3["exchange"], r3["topology"], r3["clock"]) == ("default", "default", "realtime")
    assert t[2]["measured"] == pytest.approx(r3["miss_rate"]) and r3["collisions"] == 0
    # By place (the realtime default), each agent counts the news of places that came later than
    # the reach's proof assumes; the target's detail sums their closing lines.
    late = re.findall(r"(\d+) places heard over \d+ steps late", Path(r3["out"], "fleet.stderr").read_text())
    assert len(late) == 3 and t[2]["detail"]["places_late"] == sum(map(int, late)), late
    assert f"2 at 3 robots: {sum(map(int, late))} places heard later than" in res.stdout
    assert t[2]["met"] == (r3["miss_rate"] < 1e-3 and r3["supervisor_complete"])
    assert t[3]["measured"] == r3["latency"]["pose_to_command_ms"]["p99"]
    assert t[3]["met"] == (t[3]["measured"] <= 5.0)
    # Beside it, the same fleet solving each plan after its tick: its latency, for the same poses.
    beside = t[3]["detail"]["no_delay_compensation"]
    positive(beside["pose_to_command_ms"]["p99"], "no_delay_compensation p99")
    assert beside["pose_to_command_ms"]["n"] > 0 and beside["collisions"] == 0
    assert "3 with --no-delay-compensation: pose -> command p99" in res.stdout
    assert t[2]["detail"]["no_delay_compensation"]["collisions"] == 0  # --quick: one size for both
    assert "2 with --no-delay-compensation:" in res.stdout
    positive(t[4]["measured"], "ready_s")
    assert t[4]["measured"] == r3["ready_s"] and t[4]["met"] == (r3["ready_s"] <= 5.0)
    for k in ("agent_p50", "agent_pss_p50", "tracker", "supervisor"):
        positive(t[4]["detail"]["rss_mb"][k], f"rss_mb.{k}")
    # PSS counts the pages an agent shares (its forked imports, the libraries) as its share.
    assert t[4]["detail"]["rss_mb"]["agent_pss_p50"] < t[4]["detail"]["rss_mb"]["agent_p50"]
    side = t[4]["detail"]["side_by_side"]  # start-up, agents forked and spawned
    for how in ("fork", "spawn"):
        assert len(side["ready_s"][how]) == 1
        positive(side["ready_s"][how][0], f"side_by_side.{how}")
    assert side["spawn_over_fork"] == pytest.approx(side["ready_s"]["spawn"][0] / side["ready_s"]["fork"][0])
    assert "spawn / fork" in res.stdout
    for x in d["targets"]:
        assert f"  {x['target']}     {x['goal']}" in res.stdout and isinstance(x["met"], bool)


def test_bench_harnesses_are_one_a_run(tmp_path):
    res = subprocess.run(
        [sys.executable, *_command(), "--cpu", "3", "--targets", "--out", str(tmp_path)],
        cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert res.returncode == 2 and res.stderr.strip().splitlines() == [
        "fleet: error: --targets: not with --cpu (one harness a run)"
    ], res.stderr


def test_latency_floor_times_every_command_of_its_window():
    """``benchmarks/bench_latency_floor.py``: stand-in agents answer each pose with a command in
    each order (today's, the command a step ahead, spread solves, and the bare paths); the
    observer times every command of the window from its pose's arrival, the driver from its
    put.  Each of the three robots answers each of the window's ten poses once in every order,
    and a command cannot arrive before its pose was put."""
    res = subprocess.run(
        [sys.executable, "-m", "benchmarks.bench_latency_floor",
         "--scenario", "scenarios/paper_three_robots.toml", "--seconds", "1", "--runs", "1"],
        cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr[-2000:]
    rows = {line.split()[0]: line.split()[1:] for line in res.stdout.splitlines()[3:]}
    orders = ["solve-first", "command-first", "command-spread", "echo-inbox", "echo", "echo-callback"]
    assert list(rows) == orders, res.stdout
    for order, (commands, missing, *ms) in rows.items():
        assert int(commands) == 3 * 10 and int(missing) == 0, f"{order}: {res.stdout}"  # 1 s at Ts = 0.1 s
        p50, p99, top, from_put = map(float, ms)
        assert 0 < p50 <= p99 <= top and 0 < from_put, f"{order}: {res.stdout}"


@pytest.mark.parametrize(
    ("script", "args", "field"),
    [("bench_latency_floor", ["--orders", "echo,nope"], "--orders"),
     ("bench_latency_floor", ["--seconds", "0.5"], "--seconds"),
     ("bench_latency_floor", ["--runs", "0"], "--runs"),
     ("bench_reach", ["--reach", "0.3,-1"], "--reach"), ("bench_reach", ["--reach", "far"], "--reach"),
     ("bench_reach", ["--scenarios", "nope.toml"], "--scenarios"),
     ("bench_reach", ["--jobs", "0"], "--jobs"), ("bench_reach", ["--cell", "0"], "--cell"),
     ("bench_zenoh_floor", ["--cell", "0,-4"], "--cell"),
     ("bench_zenoh_floor", ["--modes", "nope"], "--modes"),
     ("bench_zenoh_floor", ["--robots", "1"], "--robots"),
     ("bench_zenoh_floor", ["--seconds", "nan"], "--seconds"),
     ("bench_zenoh_floor", ["--seconds", "inf"], "--seconds"),
     ("bench_zenoh_floor", ["--rate", "inf"], "--rate"),
     ("bench_zenoh_floor", ["--rate", "0.001"], "--rate"),
     ("bench_zenoh_floor", ["--runs", "0"], "--runs"),
     ("bench_zenoh_floor", ["--pattern", "step,nope"], "--pattern"),
     ("bench_zenoh_floor", ["--pattern", "fleet", "--modes", "direct"], "--modes"),
     ("bench_exchange", ["--order", "mesh,nope"], "--order"),
     ("bench_exchange", ["--order", "place/nope"], "--order"),
     ("bench_exchange", ["--seconds", "nan"], "--seconds")],
)  # fmt: skip
def test_floor_benches_refuse_bad_input_in_one_line(script: str, args: list[str], field: str) -> None:
    res = subprocess.run(
        [sys.executable, "-m", f"benchmarks.{script}", *args],
        cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert res.returncode == 2 and res.stdout == ""
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and field in lines[0], res.stderr


def test_fleet_runs_solve_after_the_tick_without_delay_compensation(tmp_path):
    """``fleet bench --no-delay-compensation`` hands the flag to its fleet runs: the row says so,
    and so does the fleet's own summary in the run's directory."""
    out = tmp_path / "bench"
    proc = subprocess.run(
        [sys.executable, *_command(), "--quick", "--lockstep", "3", "--realtime", "",
         "--no-delay-compensation", "--out", str(out), "--json", str(out / "b.json")],
        cwd=ROOT, env=ENV, capture_output=True, text=True, encoding="utf-8", timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    runs = json.loads((out / "b.json").read_text())["fleet_runs"]
    assert [(r["clock"], r["robots"], r["delay_compensation"]) for r in runs] == [("lockstep", 3, False)]
    assert "error" not in runs[0] and runs[0]["collisions"] == 0, runs[0]
    summary = json.loads((Path(runs[0]["out"]) / "summary.json").read_text())
    assert "delay_compensation" not in summary and summary["completed"], summary


def test_the_sized_zenoh_runtime_keeps_a_router_forwarding(tmp_path):
    """The Zenoh runtime every process sizes down by default (:data:`transport.net.RUNTIME`, the
    transmit pool apart), in a star, whose hub forwards every sample between the others: the
    run completes, every goal reached.  With the transmit pool handed over too, the hub
    deadlocked within 20 steps of this scene, every time it was tried (docs/performance.md)."""
    from transport.net import RUNTIME

    assert "tx:" not in RUNTIME  # the transmit pool keeps its own worker
    out = tmp_path / "star"
    env = {k: v for k, v in ENV.items() if k != "ZENOH_RUNTIME"}  # the defaults' sizes
    res = subprocess.run(
        [sys.executable, "-m", "fleet.cli", "run", str(ROOT / "scenarios" / "paper_three_robots.toml"),
         "--out", str(out), "--exchange", "relay", "--topology", "star"],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr[-2000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["completed"] and summary["all_goals_reached"] and summary["collisions"] == 0, summary
    assert summary["network"]["topology"] == "star"


def _rows(stdout: str, first: str) -> list[list[str]]:
    """The table rows of a benchmark's output: the lines after the header line that starts with
    ``first``, split on blanks."""
    lines = stdout.splitlines()
    start = next(i for i, line in enumerate(lines) if line.split()[:1] == [first]) + 1
    return [line.split() for line in lines[start:] if line.strip()]


_REACH_COLUMNS = (
    "scenario", "D", "known", "p99", "share", "cells", "cells_share", "rows", "steps", "cpu", "reached",
    "coll", "min_ref", "need",
)  # fmt: skip
"""The columns of ``bench_reach.py``'s table."""


def test_reach_bench_keeps_the_references_apart_with_only_the_robots_the_split_rule_needs():
    """``benchmarks/bench_reach.py`` shows each agent of ``fleet simulate`` only the robots whose
    committed point is within a reach D of its own.  At D = 2 r + √2·ε·1.01 / s (s = ½, equal
    priorities) every row the split rule would add against a robot left out is implied by the
    ε box (:func:`agent.coordination.split_halfplanes`), so the references stay 2 r apart, as
    with every robot known: the safety a subscription by place relies on.  The agents are
    given fewer neighbours than n − 1, and with D = inf exactly n − 1.  Cells of side D count
    at least the robots within D, and fewer than all."""
    from agent.tube import synthesize
    from ground.scenario import load_scenario

    scenario = load_scenario(ROOT / "scenarios" / "swap_4.toml")
    design = synthesize(scenario.controller, scenario.arena)
    reach = 2 * design.footprint + math.sqrt(2) * design.params.epsilon * 1.01 / 0.5 + 1e-6
    res = subprocess.run(
        [sys.executable, "-m", "benchmarks.bench_reach", "--scenarios", "scenarios/swap_4.toml",
         "--reach", f"{reach:.9f},inf", "--cell", f"{reach:.9f}", "--jobs", "2"],
        cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr[-2000:]
    rows = _rows(res.stdout, "scenario")
    assert [r[0] for r in rows] == ["swap_4", "swap_4"], res.stdout
    near, every = (dict(zip(_REACH_COLUMNS, r, strict=True)) for r in rows)
    assert float(every["known"]) == 3 and float(every["share"]) == 1.0, res.stdout
    assert float(near["known"]) < 3 * 0.9, res.stdout  # some robots were out of reach
    # Square cells of side D, the agent's and the eight around it, hold the disc of radius D
    # about its point: a subscription by place of that size delivers every plan within D.
    assert float(near["known"]) <= float(near["cells"]) < 3, res.stdout
    for r in (near, every):
        assert int(r["coll"]) == 0 and float(r["min_ref"]) >= float(r["need"]) - 1e-3, res.stdout
        assert r["reached"] == "True", res.stdout


def test_zenoh_floor_delivers_only_the_cells_a_process_subscribes_to():
    """``benchmarks/bench_zenoh_floor.py --cell``: ten peers on a ring in cells of two, each
    subscribing to its own cell and the two beside it, take six plans per publication of their
    own (their own included); in one cell, all ten.  Counted by the processes themselves, so
    this is Zenoh's key filtering seen from outside, not the bench's arithmetic."""
    res = subprocess.run(
        [sys.executable, "-m", "benchmarks.bench_zenoh_floor", "--robots", "10", "--cell", "0,2",
         "--modes", "callback", "--seconds", "1"],
        cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr[-2000:]
    rows = _rows(res.stdout, "pattern")
    plans = {int(r[2]): float(r[3]) for r in rows}
    assert set(plans) == {0, 2}, res.stdout
    # A peer that linked up late misses a few of the first puts, never gets more than it subscribed to.
    assert 9.0 <= plans[0] <= 10.0 and 5.4 <= plans[2] <= 6.0, res.stdout


def test_zenoh_floor_runs_a_whole_step_with_a_tracker_and_a_supervisor():
    """``bench_zenoh_floor.py --pattern step,fleet``: a tracker's stand-in drives the steps, ten
    agents answer, a supervisor's stand-in takes every plan.  The floor starts only once the
    tracker has heard every agent and the supervisor every plan, so a pattern whose agents did
    not answer never prints.  Counted by the processes themselves, at their end (one that never
    ended, or ended without saying, makes a count nan):

    * in cells of two on a ring, each agent takes the plans of the five others in its cell and
      the two beside it, never its own back, by callback or from its main thread;
    * per step, the tracker takes one message a robot in ``step`` (the plan that carries the
      command) and two in ``fleet`` (command and plan); the supervisor every plan and one
      message of true poses in ``step``, and in ``fleet`` also every pose and the tick, each
      true pose on its own.  A stand-in that subscribed to more, or answered less, fails."""
    robots = 10
    res = subprocess.run(
        [sys.executable, "-m", "benchmarks.bench_zenoh_floor", "--robots", str(robots), "--cell", "2",
         "--pattern", "step,fleet", "--modes", "callback,drain", "--seconds", "3"],
        cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr[-2000:]
    rows = {(r[0], r[1]): r for r in _rows(res.stdout, "pattern")}
    assert set(rows) == {(p, m) for p in ("step", "fleet") for m in ("callback", "drain")}, res.stdout
    per_step = {"step": {"tracker": robots, "supervisor": robots + 1},
                "fleet": {"tracker": 2 * robots, "supervisor": 3 * robots + 1}}  # fmt: skip
    for (pattern, mode), row in rows.items():
        # Per plan of its own, over its life: an agent that linked up late misses a few of the
        # first plans, and a neighbour may still answer the step at which it stopped; never the
        # six of a cell filter that let its own plan back, or more.
        assert 4.5 <= float(row[3]) <= 5.1, (pattern, mode, res.stdout)
        assert float(row[4]) > 0, res.stdout
        _, by_role, took = " ".join(row[5:]).split("; ")
        roles = dict(part.rsplit(" ", 1) for part in by_role.split(", "))
        assert set(roles) == {"tracker", "agents", "supervisor"}, (pattern, res.stdout)
        took_a_step = {k: float(v) for k, v in (p.rsplit(" ", 1) for p in took.split(": ", 1)[1].split(", "))}
        assert set(took_a_step) == {"tracker", "supervisor"}, res.stdout
        for who, n in per_step[pattern].items():
            # Over their lives: the first steps, before every link was up, took less.
            assert 0.8 * n <= took_a_step[who] <= n + 0.05, (pattern, mode, who, res.stdout)


def test_zenoh_floor_sets_the_math_beside_the_floor():
    """``bench_zenoh_floor.py --math`` measures ``fleet simulate`` of the same robots in the same
    run and prints, per row, (math + floor) / math: recomputed here from the two printed figures,
    so a ratio that dropped or doubled either part fails."""
    res = subprocess.run(
        [sys.executable, "-m", "benchmarks.bench_zenoh_floor", "--robots", "8", "--cell", "0",
         "--modes", "callback", "--seconds", "2", "--math"],
        cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr[-2000:]
    (sim,) = [line.split() for line in res.stdout.splitlines() if line.strip().startswith("fleet simulate:")]
    math_ms = float(sim[2])
    (row,) = [r for r in _rows(res.stdout, "pattern") if r[1] == "callback"]
    floor_ms, ratio = float(row[4]), float(row[5])
    assert math_ms > 0 and floor_ms > 0, res.stdout
    assert ratio == pytest.approx((math_ms + floor_ms) / math_ms, abs=0.01 + 0.01 * ratio), res.stdout


def test_exchange_bench_runs_each_exchange_and_counts_the_plans_taken(tmp_path):
    """``bench_exchange.py`` runs the realtime fleet once per exchange named, in order (``/zenoh``:
    with Zenoh's own runtime sizes), and reads from each agent's closing line how many plans it
    took: every other robot's in the mesh."""
    out = tmp_path / "rows.json"
    res = subprocess.run(
        [sys.executable, "-m", "benchmarks.bench_exchange", "--robots", "3", "--seconds", "3",
         "--order", "mesh,place/zenoh", "--out", str(tmp_path / "runs"), "--json", str(out)],
        cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    rows = json.loads(out.read_text())["rows"]
    assert [r["exchange"] for r in rows] == ["mesh", "place/zenoh"], rows
    for r in rows:
        assert r["collisions"] == 0 and r["steps"] >= 25, r
    # Three robots within reach of each other: both take the two others' plans about every step
    # (a little over two: the agents' last plans come after the tracker's last step counted).
    assert 1.5 <= rows[0]["plans"] <= 2.2 and 1.5 <= rows[1]["plans"] <= 2.2, rows
    # The agents' cores by thread: the MPC runs on the main threads, Zenoh's runtime carries
    # every message, the callback threads decode them; together about the agents' whole CPU
    # (sampled about once a second within the run, the whole CPU every quarter; /proc counts
    # CPU in ticks of 10 ms, so a 3 s run of three agents allows 0.02 cores either way).
    for r in rows:
        parts = (r["main"], r["zenoh"], r["callbacks"])
        assert r["main"] > 0 and r["zenoh"] + r["callbacks"] > 0 and min(parts) >= 0, r
        assert 0.6 * r["agents_cores"] - 0.02 <= sum(parts) <= 1.5 * r["agents_cores"] + 0.02, r
    assert "# medians, and ratios to mesh" in res.stdout
