"""The E-puck link: the robot side of one real (or emulated) E-puck.

* :mod:`epuck_link.protocol` — advanced sercom and the e-puck2 Wi-Fi packet, pure functions;
* :mod:`epuck_link.transport` — link strings, serial and TCP transports, reconnection;
* :mod:`epuck_link.emulator` — a firmware emulator (``python -m epuck_link.emulator``);
* :mod:`epuck_link.link` — the link process (``python -m epuck_link``).
"""
