"""Marginal CPU per robot-step of ``fleet run`` against ``fleet simulate``: ``fleet bench --cpu N``.

The same scene (the shipped antipodal swap of N robots: 3 ``paper_three_robots``, 8, 16 or 32
``swap_N``), the same seed, the lockstep clock, run twice at two durations (``--cpu-s``, default
6 and 46 simulated seconds).  The CPU of the longer run minus the shorter one's, over the
robot-steps between them, is the marginal CPU per robot-step: start-up and shut-down cancel.

* ``fleet simulate`` (the whole fleet in one process) is the math: controllers, plants, judge.
* ``fleet run`` with its defaults, and with ``--exchange relay --topology star``: one process
  per robot, a tracker and a supervisor, talking over Zenoh on loopback.
* ``fleet run`` with its defaults but Zenoh's own runtime sizes (:data:`ZENOH_OWN`), beside
  the defaults, which size it down to one worker thread and a transmit thread
  (:data:`transport.net.RUNTIME`): what Zenoh's own threads cost.
* ``fleet run --no-delay-compensation``: each agent solving its plan after the tick instead of
  a step ahead (one message less a step: no outcome from the tracker).
* ``fleet run --exchange place``: plans by place, the realtime clock's default, here on
  lockstep, where the default sends every plan to every agent: what taking only the plans
  within reach saves when the fleet runs as fast as its CPU allows.
* ``fleet run --ros2``: the defaults plus the fleet's ROS 2 face (``python -m ros2_link``), a
  process of its own that observes the fleet and republishes it as ROS 2 messages.  Its CPU
  is its role's ("ros2") in the split, set against the whole fleet's and the agents'; and the
  agents' CPU with it over the agents' CPU without it (the defaults' row) says whether the
  face costs the control loop anything.  Without rosbags (the ``ros2`` extra) the row is
  skipped.

Each run's total CPU, its system CPU and its context switches are exact (``getrusage`` of the
waited-for process tree).  The split by
process role (agents, tracker, supervisor, ros2, launcher) and by thread (a process's main
thread, the Python threads Zenoh runs subscriber callbacks on, Zenoh's own runtime threads, the
Rerun recorder's threads) comes from ``/proc/PID/task/TID/stat`` sampled every ``POLL``
seconds; a thread's last fraction of a poll before its process exits is missed, and each
process's start-up varies from run to run, so the split is worth reading only where the
marginal work dominates: 8 robots or more at the default lengths.  Figures are ratios to ``fleet
simulate`` measured in the same run, since this machine's speed drifts.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
SCENES = {3: "paper_three_robots", 8: "swap_8", 16: "swap_16", 32: "swap_32"}
SCHEMA = "fleet-bench-cpu/1"
ZENOH_OWN_ROW = "fleet run (defaults), Zenoh's own sizes"
ZENOH_OWN = "()"
"""``ZENOH_RUNTIME`` that leaves every pool of Zenoh's runtime at Zenoh's own size: the
processes of ``fleet run`` size it down unless the variable is set (:func:`transport.net.size_runtime`)."""
POLL = 0.05
"""Seconds between two samples of the fleet's threads."""
LENGTHS = (6.0, 46.0)
"""The two run lengths [simulated s] whose difference is measured, by default."""
CONFIGS: dict[str, list[str]] = {
    "fleet run (defaults)": [],
    ZENOH_OWN_ROW: [],
    "fleet run --ros2": ["--ros2"],
    "fleet run --no-delay-compensation": ["--no-delay-compensation"],
    "fleet run --exchange place": ["--exchange", "place"],
    "fleet run --exchange relay --topology star": ["--exchange", "relay", "--topology", "star"],
}
"""``fleet run``'s flags by row label; ``--ros2`` next to the defaults it is compared with."""
ENVS: dict[str, dict[str, str]] = {ZENOH_OWN_ROW: {"ZENOH_RUNTIME": ZENOH_OWN}}
"""Environment set for a row's runs, by row label."""
ROS2 = ("fleet run --ros2", "fleet run (defaults)")
"""The row with the ROS 2 face and the row without it (the same flags otherwise)."""
ROLES = {"agent": "agents", "tracker": "tracker", "supervisor": "supervisor", "ros2_link": "ros2"}
"""A process's role by the module it runs (``python -m MODULE``); any other is the launcher."""
ZENOH_THREADS = ("rx-", "tx-", "net-", "acc-", "app-")
"""Name prefixes of Zenoh's runtime threads (Rust)."""


def _tasks(pid: int) -> dict[int, tuple[str, float]]:
    """{tid: (thread name, CPU s so far)} of process ``pid`` ({} once it is gone)."""
    hz = os.sysconf("SC_CLK_TCK")
    out: dict[int, tuple[str, float]] = {}
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return out
    for tid in tids:
        try:
            st = Path(f"/proc/{pid}/task/{tid}/stat").read_text()
        except OSError:
            continue
        name = st[st.index("(") + 1 : st.rindex(")")]
        f = st[st.rindex(")") + 2 :].split()
        out[int(tid)] = (name, (int(f[11]) + int(f[12])) / hz)
    return out


def _descendants(root: int) -> dict[int, str]:
    """{pid: command line} of every live process below ``root`` (and ``root`` itself)."""
    parent: dict[int, int] = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                st = Path(f"/proc/{d}/stat").read_text()
                parent[int(d)] = int(st[st.rindex(")") + 2 :].split()[1])
            except OSError:
                continue
    out, todo = {}, [root]
    while todo:
        p = todo.pop()
        try:
            out[p] = Path(f"/proc/{p}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        todo += [c for c, pp in parent.items() if pp == p]
    return out


def _role(cmdline: str) -> str:
    for module, role in ROLES.items():
        if f"-m {module} " in cmdline:
            return role
    return "launcher"


def _thread_kind(pid: int, tid: int, name: str) -> str:
    if tid == pid:
        return "main thread"
    if name.startswith(ZENOH_THREADS):
        return "zenoh runtime"
    if name == "python":
        return "callbacks (python)"
    return "other (rerun, allocator)"


def cpu_by_kind(pid: int) -> dict[str, float]:
    """CPU s so far of the live threads of process ``pid``, by thread kind ({} once it is gone)."""
    out: dict[str, float] = {}
    for tid, (name, cpu) in _tasks(pid).items():
        kind = _thread_kind(pid, tid, name)
        out[kind] = out.get(kind, 0.0) + cpu
    return out


def _measure(
    cmd: list[str], out: Path, extra_env: dict[str, str] | None = None
) -> tuple[float, dict[str, float], dict[str, float], float, dict[str, float]]:
    """Run ``cmd`` to its end, with ``extra_env`` added to this process's environment: (exact
    CPU s of its whole tree, sampled CPU s by role, by thread kind, wall s, and the tree's exact
    system CPU s and context switches, ``{"sys_s", "csw"}``).  Exit code 1 with a summary in
    ``out`` is the expected end of a run capped before every robot arrived ("goal not reached")."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.monotonic()
    env = {**os.environ, "OMP_NUM_THREADS": "1", "RERUN_ANALYTICS": "0", **(extra_env or {})}
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    last: dict[tuple[int, int], tuple[str, str, float]] = {}
    roles_of: dict[int, str] = {}
    while proc.poll() is None:
        for pid, cmdline in _descendants(proc.pid).items():
            # A process's role is its command line once exec'd; a child between fork and exec
            # shows the launcher's, and an exiting one (a zombie) shows none: keep the first
            # role that is not the launcher's.
            if cmdline.strip() and roles_of.get(pid, "launcher") == "launcher":
                roles_of[pid] = _role(cmdline)
            role = roles_of.get(pid, "launcher")
            for tid, (name, cpu) in _tasks(pid).items():
                last[(pid, tid)] = (role, _thread_kind(pid, tid, name), cpu)
        time.sleep(POLL)
    wall = time.monotonic() - t0
    err = proc.stderr.read().decode(errors="replace") if proc.stderr else ""
    if proc.returncode not in (0, 1) or not (out / "summary.json").is_file():
        raise RuntimeError(f"{' '.join(cmd[2:5])} exited {proc.returncode}: {err.strip()[-400:]}")
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    total = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    counters = {
        "sys_s": after.ru_stime - before.ru_stime,
        "csw": float(after.ru_nvcsw - before.ru_nvcsw + after.ru_nivcsw - before.ru_nivcsw),
    }
    roles: dict[str, float] = {}
    kinds: dict[str, float] = {}
    for role, kind, cpu in last.values():
        roles[role] = roles.get(role, 0.0) + cpu
        kinds[kind] = kinds.get(kind, 0.0) + cpu
    return total, roles, kinds, wall, counters


def _scene(n: int, seconds: float, tmp: Path) -> Path:
    """A copy of the shipped scene of ``n`` robots lasting ``seconds`` (simulated)."""
    import tomllib

    from fleet.running.scenes import scene_to_toml

    src = ROOT / "scenarios" / f"{SCENES[n]}.toml"
    data = tomllib.loads(src.read_text())
    data["duration"] = float(seconds)
    path = tmp / f"{SCENES[n]}_{seconds:g}.toml"
    path.write_text(scene_to_toml(data))
    return path


def _steps(out: Path) -> int:
    return int(json.loads((out / "summary.json").read_text())["steps"])


def marginal(
    short: tuple[float, dict[str, float], dict[str, float]],
    long: tuple[float, dict[str, float], dict[str, float]],
    units: float,
) -> dict[str, Any]:
    """The marginal CPU per unit of work [ms] between two measured runs, each (exact CPU s of
    the tree, sampled CPU s by role, by thread kind), that differ by ``units`` (robot-steps):
    the whole, and its split by role and by thread kind.  Start-up and shut-down, the same in
    both runs, cancel."""
    if units <= 0:
        raise ValueError(f"the longer run did no more work ({units} units)")
    (c0, r0, k0), (c1, r1, k1) = short, long
    return {
        "ms_per_robot_step": 1e3 * (c1 - c0) / units,
        "by_role_ms": {k: 1e3 * (r1.get(k, 0.0) - r0.get(k, 0.0)) / units for k in r1},
        "by_thread_ms": {k: 1e3 * (k1.get(k, 0.0) - k0.get(k, 0.0)) / units for k in k1},
    }


def marginal_rows(
    n: int, lengths: tuple[float, float], seed: int, runs: dict[str, list[str]]
) -> list[dict[str, Any]]:
    """One row per entry of ``runs`` (label → ``fleet`` subcommand and flags): the swap of ``n``
    robots run at both ``lengths`` [simulated s], and the marginal CPU per robot-step between
    them (:func:`marginal`)."""
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmpdir:
        tmp = Path(tmpdir)
        scenes = {s: _scene(n, s, tmp) for s in lengths}
        for label, extra in runs.items():
            got = {}
            for s, scn in scenes.items():
                d = tmp / f"{len(rows)}_{s:g}"
                cmd = [sys.executable, "-m", "fleet.cli", extra[0], str(scn), "--out", str(d),
                       "--seed", str(seed), *extra[1:]]  # fmt: skip
                got[s] = (*_measure(cmd, d, ENVS.get(label)), _steps(d))
            (c0, r0, k0, w0, x0, s0), (c1, r1, k1, w1, x1, s1) = got[lengths[0]], got[lengths[1]]
            try:
                m = marginal((c0, r0, k0), (c1, r1, k1), (s1 - s0) * n)
            except ValueError:
                raise RuntimeError(f"{label}: the longer run took no more steps ({s0}, {s1})") from None
            units = (s1 - s0) * n
            rows.append({
                "config": label, "steps": [s0, s1], "cpu_s": [c0, c1], "wall_s": [w0, w1], **m,
                "sys_ms_per_robot_step": 1e3 * (x1["sys_s"] - x0["sys_s"]) / units,
                "csw_per_robot_step": (x1["csw"] - x0["csw"]) / units,
            })  # fmt: skip
            print(f"  {label}: {m['ms_per_robot_step']:.2f} ms per robot-step", flush=True)
    return rows


def ros2_share(rows: list[dict[str, Any]]) -> dict[str, float] | None:
    """What the ROS 2 face costs, from the rows of one run: its role's CPU per robot-step, that
    over the whole fleet's (exact total) and over the agents' in the same run, and the agents'
    CPU with the face over the agents' without it.  None without a ``--ros2`` row."""
    by = {r["config"]: r for r in rows}
    if ROS2[0] not in by or ROS2[1] not in by:
        return None
    with_, without = by[ROS2[0]], by[ROS2[1]]
    ms = with_["by_role_ms"].get("ros2", 0.0)
    agents = with_["by_role_ms"]["agents"]
    return {
        "ms_per_robot_step": ms,
        "over_fleet": ms / with_["ms_per_robot_step"],
        "over_agents": ms / agents,
        "agents_with_over_without": agents / without["by_role_ms"]["agents"],
    }


def run(args: argparse.Namespace) -> int:
    n = int(args.cpu)
    if n not in SCENES:
        print(f"fleet: error: --cpu: one of {sorted(SCENES)} robots, got {n}", file=sys.stderr)
        return 2
    try:
        short, long = (float(s) for s in str(args.cpu_s).split(","))
        if not 0 < short < long <= 3600:
            raise ValueError
    except ValueError:
        print(
            f"fleet: error: --cpu-s: two lengths 0 < S1 < S2 <= 3600 [s], got {args.cpu_s!r}", file=sys.stderr
        )
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    json_path = Path(args.json) if args.json else out / "cpu.json"
    print(f"fleet bench --cpu {n}: {SCENES[n]}, lockstep, seed {args.seed}, {short:g} s and {long:g} s")
    print(f"machine: nproc {os.cpu_count()}, {platform.processor() or platform.machine()}; "
          f"python {platform.python_version()}; load average {os.getloadavg()}", flush=True)  # fmt: skip
    runs = {"fleet simulate": ["simulate"], **{k: ["run", *v] for k, v in CONFIGS.items()}}
    if importlib.util.find_spec("rosbags") is None:
        del runs[ROS2[0]]
        print(f"  {ROS2[0]}: skipped (needs rosbags: pip install 'epuck-fleet[ros2]')", flush=True)
    rows = marginal_rows(n, (short, long), args.seed, runs)
    base = rows[0]["ms_per_robot_step"]
    lines = [f"{'how it ran':<46} {'ms/robot-step':>13} {'× simulate':>10} {'sys ms':>7} {'switches':>8}"]
    for r in rows:
        ms = r["ms_per_robot_step"]
        lines.append(
            f"{r['config']:<46} {ms:>13.2f} {ms / base:>10.1f} {r['sys_ms_per_robot_step']:>7.2f}"
            f" {r['csw_per_robot_step']:>8.1f}"
        )
    for r in rows[1:]:
        lines.append(f"\n{r['config']}, marginal CPU per robot-step [ms] by process and by thread:")
        lines += [f"  {k:<28} {v:6.2f}" for k, v in sorted(r["by_role_ms"].items(), key=lambda kv: -kv[1])]
        lines += [f"  {k:<28} {v:6.2f}" for k, v in sorted(r["by_thread_ms"].items(), key=lambda kv: -kv[1])]
    ros2 = ros2_share(rows)
    if ros2 is not None:
        lines += [
            f"\nthe ROS 2 face (role ros2): {ros2['ms_per_robot_step']:.2f} ms per robot-step, "
            f"{ros2['over_fleet']:.3f} of the fleet's, {ros2['over_agents']:.3f} of the agents'",
            f"agents with --ros2 / without: {ros2['agents_with_over_without']:.3f}",
        ]
    print("\n".join(lines), flush=True)
    out_json = {"schema": SCHEMA, "robots": n, "rows": rows, "ros2": ros2, "table": lines}
    json_path.write_text(json.dumps(out_json, indent=1))
    print(f"figures: {json_path}", flush=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cpu", type=int, default=16, metavar="N", help="robots: 3, 8, 16 or 32 (default 16)")
    lengths = ",".join(f"{s:g}" for s in LENGTHS)
    ap.add_argument(
        "--cpu-s", default=lengths, metavar="S,S", help=f"the two durations [s] (default {lengths})"
    )
    ap.add_argument("--seed", type=int, default=0, help="seed of every run (default 0)")
    ap.add_argument("--out", default="out/bench", help="directory of the JSON (default out/bench)")
    ap.add_argument("--json", default=None, help="where the JSON goes (default OUT/cpu.json)")
    return run(ap.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
