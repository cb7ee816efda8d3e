"""The robot side of one real (or emulated) E-puck, and of every simulated one.

* :mod:`epuck_link.unicycle` — the unicycle, its inner loops, wheel speeds, simulated plants;
* :mod:`epuck_link.robot_side` — each step's command, shifted candidate or brake;
* :mod:`epuck_link.drive` — the inner loop against a real robot, the watchdog, wheel odometry;
* :mod:`epuck_link.protocol` — advanced sercom and the e-puck2 Wi-Fi packet, pure functions;
* :mod:`epuck_link.transport` — link strings, serial and TCP transports, reconnection;
* :mod:`epuck_link.emulator` — a firmware emulator (``python -m epuck_link.emulator``);
* :mod:`epuck_link.link` — the link process (``python -m epuck_link``).
"""
