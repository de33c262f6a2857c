"""ur-rtde's control script, emulated: its register protocol run in the control loop.

The control script's register protocol, as ur-rtde 1.6.2 defines it (its ``rtde_control.script``,
checked against the text embedded in ``librtde.so.1.6.2``, and its ``rtde_control_interface.cpp``
and ``rtde.h``); ``i[k]``/``d[k]`` are ``input_int_register_{k+off}`` /
``input_double_register_{k+off}``, ``off`` the script's ``reg_offset_int`` (0, or 24 with
upper-range registers):

- command in ``i[0]``; ``output_int_register_{0+off}`` is 1 (ready for a command) or 2 (done).
  Real-time commands (servoJ 11, and 6, 9, 10, 24-27, 38, 58, 66-71) are processed every cycle
  while ``i[0]`` holds them and answer "ready"; any other command runs once, answers "done" when
  it has finished, and the script answers "ready" again once ``i[0]`` is cleared to 0.
- moveJ (1): q in ``d[0..5]``, speed ``d[6]``, acceleration ``d[7]``, async flag ``i[1]``.
- servoJ (11): q in ``d[0..5]``, time ``d[8]``, lookahead ``d[9]``, gain ``d[10]``.
- speedStop (15), servoStop (16): deceleration ``d[0]``.
- stopL (33), stopJ (34): deceleration ``d[0]``, async flag ``i[1]``.
- setWatchdog (35): minimum frequency ``d[0]`` of updates of ``i[0]``; on a miss the program
  stops. getStepTime (26) writes 0.002 to ``output_double_register_{0+off}``.
  triggerProtectiveStop (31) enters a protective stop. stopScript (255) ends the program.
- async progress in ``output_int_register_{2+off}``: bits 16-22 a write counter, bits 24-30 the
  operation id, bit 15 "running", bits 0-14 the progress (the script's
  ``write_async_progress_register``).

Other commands are acknowledged ("done") without effect, with a warning in the log.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from sim.ur_controller.arm import CONTROL_PERIOD_S
from sim.ur_controller.events import print_event

if TYPE_CHECKING:
    from sim.ur_controller.controller import Controller

log = logging.getLogger("sim.ur_controller")


# -- ur-rtde's control-script commands (rtde.h RobotCommand::Type) -----------------------------

CMD_NO_CMD = 0
CMD_MOVEJ = 1
CMD_SERVOJ = 11
CMD_SPEED_STOP = 15
CMD_SERVO_STOP = 16
CMD_GET_STEPTIME = 26
CMD_PROTECTIVE_STOP = 31
CMD_STOPL = 33
CMD_STOPJ = 34
CMD_SET_WATCHDOG = 35
CMD_STOP_SCRIPT = 255
REALTIME_CMDS = frozenset({24, 11, 9, 10, 6, 25, 26, 27, 38, 58, 66, 67, 68, 69, 70, 71})
"""Commands the script's main loop processes every cycle (rtde_control.script, 1.6.2)."""
SCRIPT_READY = 1
SCRIPT_DONE = 2

# -- the controller ------------------------------------------------------------------------------


class ControlScript:
    """ur-rtde's ``rtde_control`` program, emulated through the RTDE registers.

    Mirrors the script's main loop: each cycle read the command in ``input_int_register_{off}``;
    real-time commands are processed every cycle and answer "ready"; others run once and answer
    "done" when finished; a cleared command (0) answers "ready".
    """

    def __init__(self, ctl: Controller, reg_offset_int: int, reg_offset_float: int) -> None:
        self.ctl = ctl
        self.off_i = reg_offset_int
        self.off_d = reg_offset_float
        self.executing = False
        self.waiting: Callable[[], bool] | None = None
        self.async_move = False
        self.async_stop = False
        self.watchdog_period_s: float | None = None
        self.async_wr_count = 0
        self.async_op_id = 0
        self._unemulated_warned: set[int] = set()
        self.write_async_progress(-1)  # reset_async_progress()
        self.signal(SCRIPT_READY)

    # registers as the script sees them
    def in_int(self, k: int) -> int:
        return self.ctl.in_int[k + self.off_i]

    def in_double(self, k: int) -> float:
        return self.ctl.in_double[k + self.off_d]

    def q_from_registers(self, k: int) -> np.ndarray:
        return np.array([self.in_double(k + j) for j in range(6)])

    def signal(self, value: int) -> None:
        self.ctl.out_int[0 + self.off_i] = value

    def write_async_progress(self, value: int) -> None:
        self.async_wr_count += 1
        if self.async_wr_count > 127:
            self.async_wr_count = 0
        if value == 0:
            self.async_op_id += 1
            if self.async_op_id > 127:
                self.async_op_id = 0
        reg = self.async_wr_count * 65536 + self.async_op_id * 16777216
        if value >= 0:
            reg += min(value, 32767) + 32768
        self.ctl.out_int[2 + self.off_i] = reg

    def stop_async_move(self) -> None:
        if self.async_move:
            self.async_move = False
            self.write_async_progress(-1)

    def cycle(self) -> None:
        """One 2 ms cycle of the script's main loop."""
        joints = self.ctl.joints
        if self.async_move and joints.mode != "movej":
            self.async_move = False
            self.write_async_progress(-1)
        if self.async_stop and joints.mode != "stop":
            self.async_stop = False
            self.write_async_progress(-1)
        if self.waiting is not None:
            if not self.waiting():
                return
            self.waiting = None
            self.signal(SCRIPT_DONE)
            self.executing = True
            return
        cmd = self.in_int(0)
        if cmd in REALTIME_CMDS:
            self.process(cmd)
            self.signal(SCRIPT_READY)
        elif cmd == CMD_NO_CMD:
            self.executing = False
            self.signal(SCRIPT_READY)
        elif not self.executing:
            self.executing = True
            self.process(cmd)

    def process(self, cmd: int) -> None:
        ctl, joints = self.ctl, self.ctl.joints
        if cmd == CMD_SERVOJ:
            joints.servo(self.q_from_registers(0))
            return
        if cmd == CMD_GET_STEPTIME:
            ctl.out_double[0 + self.off_d] = CONTROL_PERIOD_S
            return
        if cmd in REALTIME_CMDS:
            self._unemulated(cmd)
            return
        if cmd == CMD_MOVEJ:
            q = self.q_from_registers(0)
            speed, accel = self.in_double(6), self.in_double(7)
            self.stop_async_move()
            joints.movej(q, speed, accel)
            if self.in_int(1) == 1:
                self.async_move = True
                self.write_async_progress(0)
            else:
                self.waiting = lambda: joints.mode != "movej"
                return
        elif cmd in (CMD_SERVO_STOP, CMD_SPEED_STOP):
            print_event("stop")
            joints.stop(self.in_double(0))
            self.waiting = lambda: joints.mode != "stop"
            return
        elif cmd in (CMD_STOPJ, CMD_STOPL):
            print_event("stop")
            self.stop_async_move()
            joints.stop(self.in_double(0))
            if self.in_int(1) == 1:
                self.async_stop = True
                self.write_async_progress(0)
            else:
                self.waiting = lambda: joints.mode != "stop"
                return
        elif cmd == CMD_SET_WATCHDOG:
            frequency = self.in_double(0)
            self.watchdog_period_s = 1.0 / frequency if frequency > 0 else None
            ctl.watchdog_last_update = ctl.t
        elif cmd == CMD_PROTECTIVE_STOP:
            ctl.protective_stop("triggerProtectiveStop")
            return
        elif cmd == CMD_STOP_SCRIPT:
            ctl.stop_program("stopScript")
            return
        else:
            self._unemulated(cmd)
        self.signal(SCRIPT_DONE)

    def _unemulated(self, cmd: int) -> None:
        if cmd not in self._unemulated_warned:
            self._unemulated_warned.add(cmd)
            log.warning("%s: control-script command %d is not emulated", self.ctl.name, cmd)


class WriteProgram:
    """A non-ur-rtde program: only its ``write_output_integer_register`` calls take effect,
    one per cycle, then it ends."""

    _WRITE = re.compile(
        r"write_output_integer_register\(\s*(\d+)\s*(?:\+\s*(\d+))?\s*,\s*(-?\d+)\s*\)"
    )

    def __init__(self, ctl: Controller, text: str) -> None:
        self.ctl = ctl
        self.writes = [(int(a) + int(b or 0), int(v)) for a, b, v in self._WRITE.findall(text)]
        others = [
            line.strip()
            for line in text.splitlines()[1:-1]
            if line.strip() and not self._WRITE.search(line)
        ]
        if others:
            log.warning("%s: program lines not emulated: %s", ctl.name, others[:5])

    def cycle(self) -> None:
        if self.writes:
            index, value = self.writes.pop(0)
            if 0 <= index < 48:
                self.ctl.out_int[index] = value
        else:
            self.ctl.stop_program("end of program")
