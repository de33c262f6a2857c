"""A fake Universal Robots e-series controller at the protocol level, for ur-rtde to connect to.

Run it as its own process, one per host address (ur-rtde connects to fixed ports)::

    python -m sim.ur_controller --host 127.0.0.2 --home-deg 0 -90 90 -90 -90 0 \\
        [--protective-stop-after-servo N] [--silent-after-servo N] [--silent-after-handshake] \\
        [--name source_arm] [--verbose]

or from Python with :class:`FakeURController` (a context manager that starts the process and
waits until its ports accept connections). On that address it serves RTDE on port 30004
(:mod:`sim.ur_controller.rtde`), the dashboard on 29999 (:mod:`~sim.ur_controller.dashboard`)
and URScript uploads on 30001-30003 (:mod:`~sim.ur_controller.script_ports`). ur-rtde's control
script is emulated by its register protocol (:mod:`~sim.ur_controller.control_script`) against
the controller's state (:mod:`~sim.ur_controller.controller`) and a UR5e's joints
(:mod:`~sim.ur_controller.arm`); :mod:`~sim.ur_controller.server` is the process and its entry
point, :mod:`~sim.ur_controller.launcher` starts it.

This package imports nothing from ``scanner`` (docs/design.md: ``sim`` implements the hardware
protocols on its own).
"""

from __future__ import annotations

from sim.ur_controller.launcher import FakeURController
from sim.ur_controller.server import READY_LINE

__all__ = ["READY_LINE", "FakeURController"]
