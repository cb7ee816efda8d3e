"""The ``fleet`` command.

* ``fleet design [SCENARIO.toml] [--preset paper|epuck] [--json]`` prints the
  tube design and exits 1 if it is inadmissible.
* ``fleet simulate SCENARIO.toml [--out DIR] [--seed N] [--no-delay-compensation]`` runs the
  whole fleet in one process (:mod:`fleet.running.simulate`), writes ``DIR/summary.json`` and exits 0
  only if the run completed with zero collisions and every robot reached its goal.
* ``fleet run SCENARIO.toml [--out DIR] [--clock C] [--exchange E] [--seed N] [--viewer]
  [--listen ENDPOINT] [--lease S] [--topology T] [--start-agents fork|spawn]
  [--no-delay-compensation] [--ros2 [--ros-domain N] [--ros-listen E]]``
  runs the fleet as processes over Zenoh (with ``--ros2``, ROS 2 sees it too: docs/ros2.md).
* ``fleet goal SCENARIO.toml --robot ID X Y --connect ENDPOINT`` gives a
  running agent a new goal.
* ``fleet report DIR`` writes the figures of a run.
* ``fleet bench``, ``fleet markers``, ``fleet calibrate``: :mod:`fleet.bench`,
  :mod:`camera_tools.markers`, :mod:`camera_tools.calibrate`.

Bad input gets one line naming the field and the reason, and exit code 2.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import signal
import sys
from pathlib import Path
from typing import Any

from fleet.running.launch import STARTS, TOPOLOGIES
from fleet.running.report import strict_json
from ground.params import PRESETS, preset
from ground.scenario import ConfigError, Scenario, load_scenario
from transport.process import add_delay_compensation_arg, add_exchange_arg, domain_arg, lease_arg, seed_arg

DEFAULT_ARENA = (-1.0, 1.0, -1.0, 1.0)
EXIT_FAIL = 1
EXIT_BAD_INPUT = 2


def _bad(msg: str) -> int:
    print(f"fleet: error: {msg}", file=sys.stderr)
    return EXIT_BAD_INPUT


def check_camera_error(scn: Any) -> None:
    """Refuse a ``controller.pose_noise[0]`` [m] below the camera's measured floor error.

    The floor error is the largest held-out fiducial error of the scenario's homography file
    (``camera.homography``, :meth:`tracker.vision.Calibration.holdout_errors`: each fiducial
    predicted by a homography fitted without it).  No check without a ``[camera]`` table, a
    homography file, 5 or more fiducials in it, or OpenCV.  Raises :class:`ConfigError`
    (``controller.pose_noise``), one line with both figures and the file."""
    cam = getattr(scn, "camera", None)
    if cam is None or cam.homography is None or not Path(cam.homography).is_file():
        return
    try:
        import cv2  # noqa: F401  (the held-out fits need it)
    except ImportError:
        return
    from tracker.vision import Calibration

    held = Calibration.load(cam.homography).holdout_errors()
    if not held:
        return
    worst = max(held, key=lambda i: held[i])
    bound = scn.controller.pose_noise[0]
    if held[worst] > bound:
        raise ConfigError(
            "controller.pose_noise",
            f"[0] = {bound * 1000:.2f} mm is below the camera's floor error {held[worst] * 1000:.2f} mm "
            f"(fiducial {worst}, predicted without it) in {cam.homography}: calibrate the lens "
            "(fleet calibrate --intrinsics) and the floor again, or raise pose_noise[0]",
        )


def cmd_design(args: argparse.Namespace) -> int:
    """``fleet design``: print the tube design of a scenario, or of a preset over
    :data:`DEFAULT_ARENA` (``--json``: as JSON); returns 0 if it is admissible, else
    :data:`EXIT_FAIL` (2 bad input)."""
    if args.scenario:
        scn = load_scenario(args.scenario, preset_override=args.preset)
        check_camera_error(scn)
        params, arena, name = scn.controller, scn.arena, scn.name
    else:
        params, arena, name = preset(args.preset or "epuck"), DEFAULT_ARENA, "(no scenario)"
    from agent.sets import SetComputationError
    from agent.tube import synthesize

    try:
        design = synthesize(params, arena)
    except SetComputationError as e:
        return _bad(f"controller: {e}")
    s: dict[str, Any] = design.summary()
    s["scenario"] = name
    s["arena"] = list(arena)
    if args.json:
        print(json.dumps(strict_json(s), indent=2, ensure_ascii=False))
    else:
        zh, ph = s["Z_half_widths"], s["Psi_half_widths"]
        tight = s["tightened"]
        lines = [
            f"tube design for {name} (preset {params.preset}), Ts = {params.Ts} s, N = {params.horizon}",
            f"  K (u = v̂ + K(x − x̂)), per axis  [{design.K[0, 0]:.4f}, {design.K[0, 1]:.4f}]"
            f"   ρ(A+BK) = {s['spectral_radius_A_K']:.4f}",
            f"  Z   half-widths  {zh['position_m'] * 100:.2f} cm, {zh['velocity_m_s'] * 100:.2f} cm/s"
            f"   ({design.Z.s} terms, α = {design.Z.alpha:.2e}, error ≤ {design.Z.error_bound:.1e},"
            f" {design.Z_F.shape[0]} facets)",
            f"  KZ  {design.KZ[0]:.4f} m/s²",
            f"  Ψ   half-widths  {ph['position_m'] * 100:.2f} cm, {ph['velocity_m_s'] * 100:.2f} cm/s"
            f"   ({design.Psi.s} terms)",
            f"  tightened: |v| ≤ {tight['velocity_m_s']:.4f} m/s,"
            f" |a| ≤ {tight['acceleration_m_s2']:.4f} m/s², walls − {tight['position_margin_m']:.4f} m",
            f"  ε = {params.epsilon * 1000:.2f} mm/step, δ = {params.delta * 100:.2f} cm,"
            f" ρ = {design.rho * 100:.2f} cm, footprint r = {design.footprint:.4f} m",
            f"  wheels: up to {design.wheel_speed:.4f} m/s asked of {params.wheel.max_wheel_speed:.4f} m/s"
            if math.isfinite(design.wheel_speed)
            else "  wheels: unbounded (no look-ahead point)",
        ]
        x_axis = [*design.K[0, :2], design.KZ[0], design.x_bound[1], design.u_hat[0]]
        y_axis = [*design.K[1, 2:], design.KZ[1], design.x_bound[3], design.u_hat[1]]
        if any(not math.isclose(a, b, rel_tol=1e-9) for a, b in zip(x_axis, y_axis, strict=True)):
            # Weights that differ per axis: the lines below are the x axis and the ax input.
            lines.insert(
                1,
                f"  the axes differ; the lines below are x's.  y axis: K [{y_axis[0]:.4f}, {y_axis[1]:.4f}], "
                f"KZ {y_axis[2]:.4f} m/s², |v| ≤ {y_axis[3]:.4f} m/s, |a| ≤ {y_axis[4]:.4f} m/s²",
            )
        if design.admissible:
            lines.append("  admissible: yes")
        else:
            lines.append("  admissible: NO")
            lines += [f"    - {f}" for f in design.failures]
        print("\n".join(lines))
    return 0 if design.admissible else EXIT_FAIL


def _say_forced_order(scn: Scenario, footprint: float) -> None:
    """Say, before a run, whose way home the others' goals wall in (ground.scenario.forced_order),
    and the order of arrival the robots keep to (ground.arrival)."""
    from ground.arrival import arrival
    from ground.scenario import forced_order, forced_order_lines

    forced = forced_order(scn, footprint)
    if forced:
        print(f"layout: {len(forced)} of {len(scn.robots)} robots must be home before others park:")
        print("\n".join(f"  {line}" for line in forced_order_lines(forced)))
        if scn.controller.deadlock:
            print("order of arrival:")
            print("\n".join(f"  {line}" for line in arrival(scn, footprint).lines()))


def cmd_simulate(args: argparse.Namespace) -> int:
    """``fleet simulate``: run the scenario's fleet in one process
    (:func:`fleet.running.simulate.run`, or a script for robots with waypoints:
    :func:`fleet.experiment.api.run_scenario`), write ``summary.json`` in ``--out`` and print
    what happened; returns 0 if the run passed the judge, else :data:`EXIT_FAIL` (2 bad input)."""
    from agent.tube import validated_design
    from fleet.running.simulate import run, save_run

    scn = load_scenario(args.scenario)
    design = validated_design(scn)
    _say_forced_order(scn, design.footprint)
    kills: dict[str, int] = {}
    if args.faults:
        plan, problem = _fault_plan(args.faults, [r.id for r in scn.robots])
        if plan is None:
            return _bad(problem)
        if plan.rules or plan.links:
            return _bad(
                "--faults: fleet simulate takes only kills from a fault plan (messages and radio links "
                "are a process fleet's: fleet run --faults)"
            )
        kills = plan.kills
    out = Path(args.out) if args.out else Path("out") / scn.name
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        return _bad(f"--out: cannot create {out}: {e.strerror}")
    if any(r.waypoints for r in scn.robots):  # missions: run by a script (fleet.experiment.api)
        from fleet.experiment.api import run_scenario

        ahead = args.delay_compensation
        got, why = run_scenario(args.scenario, False, seed=args.seed, out=out, delay_compensation=ahead)
        assert got is not None
        summary = got
    else:
        from supervisor.judge import verdict

        result = run(scn, seed=args.seed, design=design, ahead=args.delay_compensation, kills=kills)
        summary = save_run(result, scn, scn.simulation.seed if args.seed is None else args.seed, out)
        why = verdict(summary)
    st = summary.get("step_time_ms", {"p50": 0.0, "p99": 0.0})
    closest = summary["min_distance_m"]  # None with one robot: no pair to measure
    print(
        f"{scn.name}: {summary['steps']} steps, {summary['sim_time_s']:.1f} s simulated in "
        f"{summary['wall_time_s']:.1f} s; collisions {summary['collisions']}, min distance "
        f"{'none (one robot)' if closest is None else f'{closest:.3f} m'}, goals reached "
        f"{sum(r['reached_goal'] for r in summary['robots'].values())}/{len(summary['robots'])}; "
        f"step time p50 {st['p50']:.2f} ms p99 {st['p99']:.2f} ms"
    )
    if "waypoints_reached" in summary:
        print(f"waypoints reached: {summary['waypoints_reached']}")
    _print_faults(summary)
    print(f"summary: {out / 'summary.json'}")
    if why:
        print(f"fleet: run failed: {why}", file=sys.stderr)
    return EXIT_FAIL if why else 0


def _run_problem(args: argparse.Namespace, scn: Scenario, links: dict[str, str]) -> str | None:
    """What is wrong with ``fleet run``'s fault plan and ROS 2 options for ``scn``, in one line
    naming the option, or None."""
    if args.faults:
        plan, bad = _fault_plan(args.faults, list(links))
        if plan is None:
            return bad
        for rid in plan.links:  # a cut that cuts nothing would pass for a tested fault
            if links[rid] == "sim":
                return (
                    f"--faults: faults.links.{rid}: {rid} has no radio link (link 'sim'); cut emulator links"
                )
    ros2 = args.ros2 or scn.ros2.enabled
    for name, value in (("--ros-domain", args.ros_domain), ("--ros-listen", args.ros_listen)):
        if value is not None and not ros2:
            return f"{name}: the ROS 2 face is off; add --ros2 (or [ros2] enabled = true)"
    if args.ros_listen is not None and args.topology == "star":
        return "--ros-listen: in the star topology ROS 2 tools connect to the hub (--listen)"
    if ros2:
        from ground.scenario import ros2_problem

        problem = ros2_problem([r.id for r in scn.robots])
        if problem is not None:
            return f"--ros2: {problem}"
        if importlib.util.find_spec("rosbags") is None:
            return "--ros2: needs rosbags: pip install 'epuck-fleet[ros2]'"
    return None


def cmd_run(args: argparse.Namespace) -> int:
    """``fleet run``: check the scenario and the options, run the fleet as processes
    (:func:`fleet.running.launch.run_fleet`, or a script for robots with waypoints:
    :func:`fleet.experiment.api.run_scenario`) and print what happened; returns the run's exit code (0 if it
    passed, 2 bad input).  SIGTERM stops it as Ctrl-C does."""
    from fleet.running.launch import run_fleet

    # SIGTERM stops the fleet like Ctrl-C: the launcher's cleanup ends every process by pid.
    signal.signal(signal.SIGTERM, _interrupt)

    from agent.tube import validated_design

    scn = load_scenario(args.scenario)
    check_camera_error(scn)
    design = validated_design(scn)  # every agent checks it too: fail here, once, before starting
    _say_forced_order(scn, design.footprint)
    links = _run_links(scn)
    problem = _run_problem(args, scn, links)
    if problem is not None:
        return _bad(problem)
    ros2 = args.ros2 or scn.ros2.enabled
    emulated = "emulator" in links.values()
    clock = args.clock or ("realtime" if emulated else "lockstep")
    if emulated and clock != "realtime":
        return _bad("--clock: emulated robots move in wall time; use --clock realtime")
    out = Path(args.out) if args.out else Path("out") / scn.name
    out.mkdir(parents=True, exist_ok=True)
    if any(r.waypoints for r in scn.robots):  # missions: run by a script (fleet.experiment.api)
        if emulated:
            return _bad("robots.waypoints: fleet run drives the missions of simulated robots only")
        if args.serve:
            return _bad("--serve: a served fleet takes its goals at run time; its robots have waypoints")
        from fleet.experiment.api import run_scenario

        summary, why = run_scenario(
            str(Path(args.scenario).resolve()), processes=True, seed=args.seed, out=out.resolve(),
            clock=clock, viewer=args.viewer, hub=args.listen, faults=args.faults, exchange=args.exchange,
            lease=args.lease, topology=args.topology, ros2=ros2, ros_domain=args.ros_domain,
            ros_listen=args.ros_listen, fork=args.start_agents == "fork",
            delay_compensation=args.delay_compensation,
        )  # fmt: skip
        code, verdict = (1, why) if why else (0, "ok")
    else:
        code, verdict, summary = run_fleet(
            str(Path(args.scenario).resolve()), [r.id for r in scn.robots], out.resolve(), args.seed,
            viewer=args.viewer, clock=clock, hub=args.listen, links=links, faults=args.faults,
            exchange=args.exchange, lease=args.lease, topology=args.topology, ros2=ros2,
            ros_domain=args.ros_domain, ros_listen=args.ros_listen, fork=args.start_agents == "fork",
            delay_compensation=args.delay_compensation, serve=args.serve,
            timeout=None if args.serve else 600.0,
        )  # fmt: skip
    if summary is not None:
        # Plans by place assume news of places within the lag (docs/method.md §6.7): how often not.
        by_place = summary.get("network", {}).get("exchange") == "place"
        late = summary.get("places_heard_late", 0) if by_place else None
        print(
            f"{scn.name}: {summary['steps']} steps in {summary['wall_time_s']:.1f} s over "
            f"{len(summary.get('processes', {}))} processes ({clock}); "
            f"collisions {summary['collisions']}, "
            f"deadline misses {summary.get('deadline_misses', 0)}, "
            f"{'' if late is None else f'places heard late {late}, '}"
            f"goals reached {sum(r['reached_goal'] for r in summary['robots'].values())}"
            f"/{len(summary['robots'])}"
        )
        _print_faults(summary)
        print(f"summary: {out / 'summary.json'}")
        note = realtime_note(summary, design.params.Ts) if clock == "realtime" else None
        if note:
            print(note)
    if code:
        print(f"fleet: run failed: {verdict}", file=sys.stderr)
    return code


def _fault_plan(text: str, robots: list[str]) -> tuple[Any, str]:
    """(the ``--faults`` plan, "") or (None, the one line that says why it cannot be used): a bad
    plan, or one that cuts the link of or kills a robot the scenario does not have (a fault that
    hits nothing would pass for a tested one)."""
    from transport.faults import FaultPlan, FaultPlanError

    try:
        plan = FaultPlan.parse(text)
    except FaultPlanError as e:
        return None, f"--faults: {e}"
    for name, hit in (("links", plan.links), ("kills", plan.kills)):
        for rid in hit:
            if rid not in robots:
                return None, f"--faults: faults.{name}.{rid}: no robot {rid!r} in the scenario"
    return plan, ""


def _print_faults(summary: dict[str, Any]) -> None:
    """The closing line on what faults did, if they did anything (:func:`supervisor.judge.fault_note`)."""
    from supervisor.judge import fault_note

    note = fault_note(summary)
    if note:
        print(f"faults: {note}")


MISS_NOTE = 0.01
"""Share of robot-steps [1] above which a realtime run's deadline misses are explained."""
LAG_NOTE = 1.05
"""Wall time per simulated time above which a realtime run's lag is explained."""


def realtime_note(summary: dict[str, Any], Ts: float) -> str | None:
    """One line on why a realtime run missed many deadlines or ran slower than the wall
    clock, or None: the machine is short of CPU for this fleet at this period ``Ts`` [s]."""
    steps, n = int(summary.get("steps", 0)), len(summary.get("robots", {}))
    misses = int(summary.get("deadline_misses", 0))
    sim, wall = float(summary.get("sim_time_s", 0.0)), float(summary.get("wall_time_s", 0.0))
    share = misses / max(1, steps * n)
    slow = sim > 0 and wall > LAG_NOTE * sim
    if share <= MISS_NOTE and not slow:
        return None
    what = []
    if share > MISS_NOTE:
        what.append(
            f"{100 * share:.1f} % of the deadlines were missed "
            "(the robots followed their candidates, or braked)"
        )
    if slow:
        what.append(f"the simulated clock ran {wall - sim:.1f} s behind the wall clock")
    return (
        f"note: {' and '.join(what)}: this machine is short of CPU for {n} agents at Ts = {Ts:g} s; "
        "`fleet bench --realtime N` measures what a fleet needs (figure [6])"
    )


def _run_links(scn: Any) -> dict[str, str]:
    """robot id → link kind for ``fleet run``; raises ConfigError for links it cannot drive.

    ``fleet run`` simulates every robot (``sim``) or emulates every robot
    (``emulator``); robots on ``serial:`` or ``tcp:`` links are real, and their
    processes are started by hand (docs/lab.md, "Start the fleet")."""
    from epuck_link.transport import parse_link

    kinds: dict[str, str] = {}
    for i, r in enumerate(scn.robots):
        try:
            kinds[r.id] = parse_link(r.link).kind
        except ValueError as e:
            raise ConfigError(f"robots[{i}].link", str(e)) from None
        if kinds[r.id] not in ("sim", "emulator"):
            raise ConfigError(
                f"robots[{i}].link",
                f"{r.link!r} is a real robot; fleet run drives sim and emulator links "
                "(start real robots' processes by hand: docs/lab.md)",
            )
    if len(set(kinds.values())) > 1:
        raise ConfigError("robots", "fleet run needs every link sim or every link emulator, not a mix")
    return kinds


def cmd_goal(args: argparse.Namespace) -> int:
    """``fleet goal``: give a running robot's agent a new goal (:func:`fleet.running.operator.send_goal`)
    and print its answer; returns the exit code (2 unless exactly one of ``--connect`` and
    ``--zenoh-config`` is given)."""
    from fleet.running.operator import send_goal

    goal = (args.x, args.y)
    if not _one_way_in(args, "fleet goal"):
        return 2
    code, line = send_goal(
        args.scenario, args.robot, goal, args.connect or [], args.fleet, args.timeout, args.zenoh_config
    )
    print(line, file=sys.stdout if code == 0 else sys.stderr)
    return code


def cmd_stop(args: argparse.Namespace) -> int:
    """``fleet stop``: end a served fleet's run (:func:`fleet.running.operator.stop_fleet`) and
    print the answer; returns the exit code (2 unless exactly one of ``--connect`` and
    ``--zenoh-config`` is given)."""
    from fleet.running.operator import stop_fleet

    if not _one_way_in(args, "fleet stop"):
        return 2
    code, line = stop_fleet(args.connect or [], args.fleet, args.timeout, args.zenoh_config)
    print(line, file=sys.stdout if code == 0 else sys.stderr)
    return code


def _one_way_in(args: argparse.Namespace, prog: str) -> bool:
    """Exactly one of ``--connect`` and ``--zenoh-config`` is given; else False, said in one line."""
    if bool(args.connect) != bool(args.zenoh_config):
        return True
    what = "both given" if args.connect else "neither given"
    print(
        f"{prog}: error: --connect: give the hub or a --zenoh-config, one of them ({what})", file=sys.stderr
    )
    return False


def _interrupt(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt


def _calibrate_arguments(ap: argparse.ArgumentParser) -> None:
    from camera_tools.calibrate import add_arguments

    add_arguments(ap)


def _bench_arguments(ap: argparse.ArgumentParser) -> None:
    from fleet.bench import add_arguments

    add_arguments(ap)


def cmd_bench(args: argparse.Namespace) -> int:
    """``fleet bench``: :func:`fleet.bench.run`; returns its exit code."""
    from fleet.bench import run

    return int(run(args))


def _markers_arguments(ap: argparse.ArgumentParser) -> None:
    from camera_tools.markers import add_arguments

    add_arguments(ap)


def cmd_markers(args: argparse.Namespace) -> int:
    """``fleet markers``: :func:`camera_tools.markers.run`; returns its exit code."""
    from camera_tools.markers import run

    return int(run(args))


def cmd_calibrate(args: argparse.Namespace) -> int:
    """``fleet calibrate``: :func:`camera_tools.calibrate.run`; returns its exit code."""
    from camera_tools.calibrate import run

    return int(run(args))


def cmd_report(args: argparse.Namespace) -> int:
    """``fleet report``: write the figures of the run in ``DIR``
    (:func:`fleet.running.report.write_report`) and print their paths; 2 if ``DIR`` has no ``trace.npz``."""
    from fleet.running.report import write_report

    out = Path(args.dir)
    if not (out / "trace.npz").is_file():
        return _bad(f"DIR: {out / 'trace.npz'} not found (run fleet simulate or fleet run with --out {out})")
    for p in write_report(out):
        print(p)
    return 0


def _endpoint(text: str) -> str:
    """A Zenoh TCP endpoint ``tcp/HOST:PORT``."""
    proto, _, rest = text.partition("/")
    host, _, port = rest.rpartition(":")
    if proto != "tcp" or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise argparse.ArgumentTypeError(f"expected tcp/HOST:PORT, got {text!r}")
    return text


def _run_arguments(r: argparse.ArgumentParser) -> None:
    """Declare the options of ``fleet run`` on ``r``."""
    r.add_argument("scenario", help="scenario TOML file")
    r.add_argument("--out", help="output directory (default out/<scenario name>)")
    r.add_argument("--seed", type=seed_arg, help="override the scenario's [simulation] seed")
    r.add_argument("--viewer", action="store_true", help="open the Rerun viewer live")
    r.add_argument(
        "--serve", action="store_true",
        help="keep the fleet up once every robot is home, for goals from scripts (Fleet.connect), "
        "fleet goal and ROS 2, until Ctrl-C, SIGTERM or fleet stop --connect HUB; the summary is "
        "written when it stops",
    )  # fmt: skip
    r.add_argument(
        "--clock", choices=["lockstep", "realtime"], default=None,
        help="default lockstep; realtime when the robots are emulated (link = \"emulator\")",
    )  # fmt: skip
    r.add_argument(
        "--listen", metavar="ENDPOINT", type=_endpoint,
        help="Zenoh endpoint of the fleet's hub, e.g. tcp/127.0.0.1:7447, so an operator can connect "
        "(default: a free loopback port)",
    )  # fmt: skip
    r.add_argument(
        "--faults", metavar="JSON",
        help="fault plan for every process (JSON text or file; transport/faults.py): drop or delay messages",
    )  # fmt: skip
    add_exchange_arg(r)
    r.add_argument(
        "--lease", metavar="SECONDS", type=lease_arg,
        help="Zenoh transport lease of every process [s] (default 10 in the mesh, 1 in the star): how "
        "soon neighbours see a hung agent as not alive; at 1 s the keep-alives of a 16-robot mesh "
        "take a third of a core, of a star a few %% (docs/design.md, \"Liveliness lease\")",
    )  # fmt: skip
    r.add_argument(
        "--topology", choices=TOPOLOGIES, default="mesh",
        help="how the processes link: mesh (every one a Zenoh peer, default) or star (the tracker a "
        "router, the others its clients: one link each, and a 1 s lease; with --exchange relay, the "
        "lightest for large realtime fleets; docs/design.md, \"Topology\")",
    )  # fmt: skip
    add_delay_compensation_arg(r)
    r.add_argument(
        "--start-agents", choices=STARTS, default=STARTS[0],
        help="fork (Linux only, and its default): fork every agent from one process that imported the "
        "agent's code once, which saves each its imports; spawn: start each agent as its own "
        "interpreter (docs/performance.md, \"Start-up\")",
    )  # fmt: skip
    r.add_argument(
        "--ros2", action="store_true",
        help="also show the fleet to ROS 2 over rmw_zenoh, with no bridge: /<id>/pose, plan, reference, "
        "goal_pose and /fleet/footprints (docs/ros2.md; needs the [ros2] extra)",
    )  # fmt: skip
    r.add_argument(
        "--ros-domain", metavar="N", type=domain_arg,
        help="ROS 2 domain id of --ros2, 0 … 232 (default the scenario's [ros2] domain, else 0)",
    )  # fmt: skip
    r.add_argument(
        "--ros-listen", metavar="ENDPOINT", type=_endpoint,
        help="where ROS 2 tools connect to the fleet's ROS face, e.g. tcp/127.0.0.1:7447 (default a free "
        "loopback port, printed; in the star topology, the hub)",
    )  # fmt: skip


def build_parser() -> argparse.ArgumentParser:
    """The ``fleet`` command's argument parser: one subcommand each, whose ``func`` is the
    ``cmd_*`` that runs it."""
    ap = argparse.ArgumentParser(prog="fleet", description="Distributed robust tube MPC for E-puck fleets")
    sub = ap.add_subparsers(dest="command", required=True)
    d = sub.add_parser("design", help="print the tube design of a scenario or preset")
    d.add_argument("scenario", nargs="?", help="scenario TOML file")
    d.add_argument("--preset", choices=PRESETS, help="controller preset (overrides the scenario's)")
    d.add_argument("--json", action="store_true", help="machine-readable output")
    d.set_defaults(func=cmd_design)
    s = sub.add_parser("simulate", help="run a scenario's whole fleet in one process (fast, closed loop)")
    s.add_argument("scenario", help="scenario TOML file")
    s.add_argument("--out", help="output directory (default out/<scenario name>)")
    s.add_argument("--seed", type=seed_arg, help="override the scenario's [simulation] seed")
    add_delay_compensation_arg(s)
    s.add_argument(
        "--faults", metavar="JSON",
        help="fault plan (JSON text or file; see transport/faults.py): its kills end robots' agents at "
        "chosen steps",
    )  # fmt: skip
    s.set_defaults(func=cmd_simulate)
    r = sub.add_parser("run", help="run the fleet as separate processes over Zenoh (lockstep clock)")
    _run_arguments(r)
    r.set_defaults(func=cmd_run)
    g = sub.add_parser("goal", help="give a running agent a new goal and wait until it takes it")
    g.add_argument("scenario", help="scenario TOML file of the running fleet")
    g.add_argument("--robot", required=True, help="robot id")
    g.add_argument("x", type=float, help="goal x [m], world frame")
    g.add_argument("y", type=float, help="goal y [m], world frame")
    g.add_argument("--connect", action="append", type=_endpoint, help="the fleet's hub (peer-to-peer)")
    g.add_argument(
        "--zenoh-config", metavar="FILE",
        help="Zenoh JSON5 configuration instead of --connect (secure deployment: deploy/operator.json5)",
    )  # fmt: skip
    g.add_argument("--fleet", default="lab", help="fleet name in the Zenoh keys (default lab)")
    g.add_argument("--timeout", type=float, default=30.0, help="wait limit [s]")
    g.set_defaults(func=cmd_goal)
    st = sub.add_parser("stop", help="end a served fleet's run (fleet run --serve), as at its duration")
    st.add_argument("--connect", action="append", type=_endpoint, help="the fleet's hub (peer-to-peer)")
    st.add_argument("--zenoh-config", metavar="FILE", help="Zenoh JSON5 configuration instead of --connect")
    st.add_argument("--fleet", default="lab", help="fleet name in the Zenoh keys (default lab)")
    st.add_argument("--timeout", type=float, default=30.0, help="wait limit [s]")
    st.set_defaults(func=cmd_stop)
    b = sub.add_parser(
        "bench", help="step times, solvers, real-time factors, latency and memory (prints, writes JSON)"
    )
    _bench_arguments(b)
    b.set_defaults(func=cmd_bench)
    mk = sub.add_parser("markers", help="write the scenario's ArUco markers as a printable PDF (and PNGs)")
    _markers_arguments(mk)
    mk.set_defaults(func=cmd_markers)
    c = sub.add_parser("calibrate", help="fit the camera's floor homography from the scenario's fiducials")
    _calibrate_arguments(c)
    c.set_defaults(func=cmd_calibrate)
    rp = sub.add_parser("report", help="write PNG figures of a run (trajectories, pairwise distances)")
    rp.add_argument("dir", help="output directory of fleet simulate or fleet run")
    rp.set_defaults(func=cmd_report)
    return ap


def main(argv: list[str] | None = None) -> int:
    """``fleet``: run the subcommand; returns its exit code (2 bad input, 130 when interrupted, 0
    when the reader of the output went away)."""
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args))
    except ConfigError as e:
        return _bad(str(e))
    except KeyboardInterrupt:
        print("fleet: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # The reader went away (e.g. `fleet design --json | head`): not an error of ours.
        sys.stderr.close()
        return 0


if __name__ == "__main__":
    sys.exit(main())
