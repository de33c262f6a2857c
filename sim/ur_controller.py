"""A fake Universal Robots e-series controller at the protocol level, for ur-rtde to connect to.

Run it as its own process, one per host address (ur-rtde connects to fixed ports)::

    python -m sim.ur_controller --host 127.0.0.2 --home-deg 0 -90 90 -90 -90 0 \\
        [--protective-stop-after-servo N] [--name source_arm] [--verbose]

or from Python with :class:`FakeURController` (a context manager that starts the process and
waits until its ports accept connections). It serves, on that address:

- **RTDE, port 30004** (protocol version 2, as in Universal Robots' RTDE guide): request
  protocol version (``V``), get URControl version (``v``, answers an e-series 5.x), setup outputs
  (``O``: every variable answered with its RTDE type, unknown names ``NOT_FOUND``), setup inputs
  (``I``: recipes numbered from 1 per connection, a field set up by another connection
  ``IN_USE``), start (``S``), pause (``P``), data packages (``U``) both ways, big-endian, the
  outputs at each recipe's frequency from a 500 Hz control loop.
- **Dashboard server, port 29999**: the welcome line and the replies of PolyScope 5 to the
  commands ur-rtde's ``DashboardClient`` sends (``PolyscopeVersion``, ``get serial number``,
  ``is in remote control``, ``robotmode``, ``safetymode``, ``safetystatus``, ``programState``,
  ``running``, ``power on``/``off``, ``brake release``, ``unlock protective stop``,
  ``close safety popup``, ``close popup``, ``stop``, ``play``, ``pause``, ``load``, ...).
- **Script upload, ports 30001, 30002 and 30003**: URScript text is accepted; a ``def`` program
  replaces the running one. ur-rtde's control script (``def rtde_control():``) is not parsed
  but emulated: the fake runs the script's register protocol in its control loop (below).
  Other programs are only scanned for ``write_output_integer_register`` calls (which is what
  ur-rtde's ``sendCustomScriptFunction`` waits on). Nothing is streamed back on these ports.

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

Joint dynamics: the six joints start at ``--home-deg``; moveJ follows a synchronous
trapezoidal profile (leading axis at the requested speed and acceleration, rad/s, rad/s^2);
servoJ targets are followed with a first-order lag (``--servo-lag-s``, 4 ms) under the joint
speed limit; stops decelerate the leading axis at the requested rate with the others scaled to
stop together. ``actual_q`` and ``timestamp`` advance in real time in 2 ms steps.
``actual_TCP_pose``/``target_TCP_pose`` are the forward kinematics of a UR5e (nominal DH).

``--protective-stop-after-servo N``: the N-th servoJ command received puts the arm into a
protective stop, as the real controller does on a fault: ``safety_mode`` PROTECTIVE_STOP (3),
``safety_status_bits`` bit 2 (and bit 10, stopped due to safety), the program paused
(``runtime_state`` PAUSED), the joints decelerated to standstill, further motion refused. The
dashboard's ``unlock protective stop`` clears it, as on the robot not before 5 s have passed;
the program then stays paused (``play`` resumes it, or upload the script again).

This module imports nothing from ``scanner`` (DESIGN.md: ``sim`` implements the hardware
protocols on its own).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import math
import os
import re
import signal
import struct
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

log = logging.getLogger("sim.ur_controller")

# -- ports, versions --------------------------------------------------------------------------

RTDE_PORT = 30004
DASHBOARD_PORT = 29999
SCRIPT_PORTS = (30001, 30002, 30003)
ALL_PORTS = (RTDE_PORT, DASHBOARD_PORT, *SCRIPT_PORTS)

READY_LINE = "sim.ur_controller ready on"
"""Printed to stdout (followed by the host) once every port is open."""

CONTROL_PERIOD_S = 0.002
"""The controller's real-time cycle (500 Hz)."""

CONTROLLER_VERSION = (5, 15, 2, 126234)
"""What ``v`` (get URControl version) answers: major, minor, bugfix, build."""

POLYSCOPE_VERSION = "URSoftware 5.15.2.126234 (Feb 02 2024)"

# -- RTDE package types (RTDE guide) -----------------------------------------------------------

RTDE_REQUEST_PROTOCOL_VERSION = 86  # 'V'
RTDE_GET_URCONTROL_VERSION = 118  # 'v'
RTDE_TEXT_MESSAGE = 77  # 'M'
RTDE_DATA_PACKAGE = 85  # 'U'
RTDE_CONTROL_PACKAGE_SETUP_OUTPUTS = 79  # 'O'
RTDE_CONTROL_PACKAGE_SETUP_INPUTS = 73  # 'I'
RTDE_CONTROL_PACKAGE_START = 83  # 'S'
RTDE_CONTROL_PACKAGE_PAUSE = 80  # 'P'

_HEADER = struct.Struct(">HB")

_TYPE_FORMATS = {
    "BOOL": "?",
    "UINT8": "B",
    "UINT32": "I",
    "UINT64": "Q",
    "INT32": "i",
    "DOUBLE": "d",
    "VECTOR3D": "3d",
    "VECTOR6D": "6d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
}
_TYPE_SIZES = {t: struct.calcsize(">" + f) for t, f in _TYPE_FORMATS.items()}

# -- controller enums (RTDE guide; ur-rtde's rtde_control_interface.h) ------------------------

ROBOT_MODE_POWER_OFF = 3
ROBOT_MODE_IDLE = 5
ROBOT_MODE_RUNNING = 7
ROBOT_MODE_NAMES = {
    -1: "NO_CONTROLLER",
    0: "DISCONNECTED",
    1: "CONFIRM_SAFETY",
    2: "BOOTING",
    3: "POWER_OFF",
    4: "POWER_ON",
    5: "IDLE",
    6: "BACKDRIVE",
    7: "RUNNING",
}
SAFETY_MODE_NORMAL = 1
SAFETY_MODE_PROTECTIVE_STOP = 3
SAFETY_MODE_NAMES = {1: "NORMAL", 2: "REDUCED", 3: "PROTECTIVE_STOP"}
SAFETY_BIT_NORMAL_MODE = 0
SAFETY_BIT_PROTECTIVE_STOPPED = 2
SAFETY_BIT_STOPPED_DUE_TO_SAFETY = 10
ROBOT_BIT_POWER_ON = 0
ROBOT_BIT_PROGRAM_RUNNING = 1
RUNTIME_STOPPED = 1
RUNTIME_PLAYING = 2
RUNTIME_PAUSED = 4
RUNTIME_NAMES = {0: "STOPPING", 1: "STOPPED", 2: "PLAYING", 3: "PAUSING", 4: "PAUSED"}
JOINT_MODE_RUNNING = 253

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

# -- arm model ---------------------------------------------------------------------------------

MAX_JOINT_SPEED_RAD_S = math.pi
PROTECTIVE_STOP_DECEL_RAD_S2 = 10.0
PROGRAM_STOP_DECEL_RAD_S2 = 4.0
UNLOCK_DELAY_S = 5.0
"""PolyScope refuses to unlock a protective stop sooner than this after it occurred."""

_UR5E_DH_A_M = (0.0, -0.425, -0.3922, 0.0, 0.0, 0.0)
_UR5E_DH_D_M = (0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996)
_UR5E_DH_ALPHA_RAD = (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)
_DH_ALPHA = np.array(_UR5E_DH_ALPHA_RAD)
_DH_A_ALONG_X = np.column_stack([_UR5E_DH_A_M, np.zeros(6), np.zeros(6)])
_DH_D = np.array(_UR5E_DH_D_M)


def _forward_kinematics(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """UR5e flange pose ``(x, y, z, rx, ry, rz)`` (m, rotation vector) and elbow position (m).

    Standard DH: link i is ``Rz(q_i) Tz(d_i) Tx(a_i) Rx(alpha_i)``.
    """
    links = Rotation.from_euler("ZX", np.column_stack([q, _DH_ALPHA]))
    offsets = links.apply(_DH_A_ALONG_X)
    offsets[:, 2] += _DH_D
    matrices = links.as_matrix()
    rotation = np.eye(3)
    position = np.zeros(3)
    elbow = position
    for i in range(6):
        position = position + rotation @ offsets[i]
        rotation = rotation @ matrices[i]
        if i == 1:
            elbow = position
    return np.concatenate([position, Rotation.from_matrix(rotation).as_rotvec()]), elbow


# -- variables -----------------------------------------------------------------------------------

_OUTPUT_TYPES: dict[str, str] = {
    "timestamp": "DOUBLE",
    **dict.fromkeys(
        (
            "target_q",
            "target_qd",
            "target_qdd",
            "target_current",
            "target_moment",
            "actual_q",
            "actual_qd",
            "actual_current",
            "actual_current_window",
            "joint_control_output",
            "actual_TCP_pose",
            "actual_TCP_speed",
            "actual_TCP_force",
            "target_TCP_pose",
            "target_TCP_speed",
            "joint_temperatures",
            "actual_joint_voltage",
            "ft_raw_wrench",
            "payload_inertia",
        ),
        "VECTOR6D",
    ),
    "actual_digital_input_bits": "UINT64",
    "actual_digital_output_bits": "UINT64",
    "actual_execution_time": "DOUBLE",
    "robot_mode": "INT32",
    "joint_mode": "VECTOR6INT32",
    "safety_mode": "INT32",
    "safety_status": "INT32",
    "actual_tool_accelerometer": "VECTOR3D",
    "speed_scaling": "DOUBLE",
    "target_speed_fraction": "DOUBLE",
    "actual_momentum": "DOUBLE",
    "actual_main_voltage": "DOUBLE",
    "actual_robot_voltage": "DOUBLE",
    "actual_robot_current": "DOUBLE",
    "runtime_state": "UINT32",
    "elbow_position": "VECTOR3D",
    "elbow_velocity": "VECTOR3D",
    "robot_status_bits": "UINT32",
    "safety_status_bits": "UINT32",
    "analog_io_types": "UINT32",
    "standard_analog_input0": "DOUBLE",
    "standard_analog_input1": "DOUBLE",
    "standard_analog_output0": "DOUBLE",
    "standard_analog_output1": "DOUBLE",
    "io_current": "DOUBLE",
    "euromap67_input_bits": "UINT32",
    "euromap67_output_bits": "UINT32",
    "euromap67_24V_voltage": "DOUBLE",
    "euromap67_24V_current": "DOUBLE",
    "tool_mode": "UINT32",
    "tool_analog_input_types": "UINT32",
    "tool_analog_input0": "DOUBLE",
    "tool_analog_input1": "DOUBLE",
    "tool_output_voltage": "INT32",
    "tool_output_current": "DOUBLE",
    "tool_temperature": "DOUBLE",
    "tcp_force_scalar": "DOUBLE",
    "output_bit_registers0_to_31": "UINT32",
    "output_bit_registers32_to_63": "UINT32",
    "input_bit_registers0_to_31": "UINT32",
    "input_bit_registers32_to_63": "UINT32",
    "tool_output_mode": "UINT8",
    "tool_digital_output0_mode": "UINT8",
    "tool_digital_output1_mode": "UINT8",
    "payload": "DOUBLE",
    "payload_cog": "VECTOR3D",
    "script_control_line": "UINT32",
    "joint_position_deviation_ratio": "DOUBLE",
    "collision_detection_ratio": "DOUBLE",
    "time_scale_source": "UINT32",
}
"""Output variables of an e-series 5.15 controller and their RTDE types (RTDE guide); the
numbered registers are matched by :data:`_REGISTER`."""

_INPUT_TYPES: dict[str, str] = {
    "speed_slider_mask": "UINT32",
    "speed_slider_fraction": "DOUBLE",
    "standard_digital_output_mask": "UINT8",
    "standard_digital_output": "UINT8",
    "configurable_digital_output_mask": "UINT8",
    "configurable_digital_output": "UINT8",
    "tool_digital_output_mask": "UINT8",
    "tool_digital_output": "UINT8",
    "standard_analog_output_mask": "UINT8",
    "standard_analog_output_type": "UINT8",
    "standard_analog_output_0": "DOUBLE",
    "standard_analog_output_1": "DOUBLE",
    "input_bit_registers0_to_31": "UINT32",
    "input_bit_registers32_to_63": "UINT32",
    "external_force_torque": "VECTOR6D",
}
"""Input variables (settable by a client) and their RTDE types; registers via :data:`_REGISTER`."""

_REGISTER = re.compile(r"(input|output)_(int|double|bit)_register_(\d+)\Z")
_REGISTER_TYPES = {"int": "INT32", "double": "DOUBLE", "bit": "BOOL"}


def _register(name: str) -> tuple[str, str, int] | None:
    """``(direction, kind, index)`` of a numbered register name, or None."""
    m = _REGISTER.match(name)
    if m is None:
        return None
    direction, kind, index = m.group(1), m.group(2), int(m.group(3))
    valid = 64 <= index <= 127 if kind == "bit" else 0 <= index <= 47
    return (direction, kind, index) if valid else None


def output_type(name: str) -> str:
    """The RTDE type of an output variable, ``"NOT_FOUND"`` when the controller has none."""
    reg = _register(name)
    if reg is not None:
        return _REGISTER_TYPES[reg[1]]
    return _OUTPUT_TYPES.get(name, "NOT_FOUND")


def input_type(name: str) -> str:
    """The RTDE type of an input variable, ``"NOT_FOUND"`` when it cannot be set."""
    reg = _register(name)
    if reg is not None:
        return _REGISTER_TYPES[reg[1]] if reg[0] == "input" else "NOT_FOUND"
    return _INPUT_TYPES.get(name, "NOT_FOUND")


# -- motion --------------------------------------------------------------------------------------


@dataclass
class _Trapezoid:
    """A synchronous joint move along a straight line in joint space (URScript ``movej``)."""

    q0: np.ndarray
    dq: np.ndarray
    distance: float
    accel: float
    peak: float
    t_acc: float
    t_total: float
    t: float = 0.0

    @classmethod
    def plan(cls, q0: np.ndarray, q1: np.ndarray, speed: float, accel: float) -> _Trapezoid:
        dq = q1 - q0
        distance = float(np.abs(dq).max())
        speed = min(max(speed, 1e-6), MAX_JOINT_SPEED_RAD_S)
        accel = max(accel, 1e-6)
        if distance * accel < speed * speed:  # triangular: never reaches the speed
            t_acc = math.sqrt(distance / accel)
            peak = accel * t_acc
            t_total = 2.0 * t_acc
        else:
            t_acc = speed / accel
            peak = speed
            t_total = distance / speed + t_acc
        return cls(q0.copy(), dq, distance, accel, peak, t_acc, t_total)

    def sample(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position, velocity and acceleration at ``t`` s into the move."""
        if self.distance <= 0.0 or t >= self.t_total:
            return self.q0 + self.dq, np.zeros(6), np.zeros(6)
        a, ta, T = self.accel, self.t_acc, self.t_total
        if t < ta:
            s, sd, sdd = 0.5 * a * t * t, a * t, a
        elif t < T - ta:
            s, sd, sdd = 0.5 * a * ta * ta + self.peak * (t - ta), self.peak, 0.0
        else:
            r = T - t
            s, sd, sdd = self.distance - 0.5 * a * r * r, a * r, -a
        u = self.dq / self.distance
        return self.q0 + u * s, u * sd, u * sdd


class _Joints:
    """The six joints and what drives them: hold, a moveJ, servo set-points, or a stop."""

    def __init__(self, home_rad: np.ndarray, servo_lag_s: float) -> None:
        self.q = home_rad.astype(np.float64).copy()
        self.qd = np.zeros(6)
        self.qdd = np.zeros(6)
        self.q_target = self.q.copy()
        self.servo_lag_s = servo_lag_s
        self.mode = "hold"
        self._move: _Trapezoid | None = None
        self._servo_goal = self.q.copy()
        self._decel = 0.0

    @property
    def moving(self) -> bool:
        return self.mode in ("movej", "stop") or bool(np.any(self.qd != 0.0))

    def movej(self, q1: np.ndarray, speed: float, accel: float) -> None:
        self._move = _Trapezoid.plan(self.q, q1, speed, accel)
        self.mode = "movej"

    def servo(self, goal: np.ndarray) -> None:
        self._servo_goal = goal.copy()
        self.mode = "servo"

    def stop(self, decel: float) -> None:
        """Decelerate the leading axis at ``decel`` rad/s^2, the others to stop with it."""
        self._decel = max(decel, 1e-3)
        self._move = None
        self.mode = "stop"

    def step(self, dt: float) -> None:
        if self.mode == "movej" and self._move is not None:
            self._move.t += dt
            self.q, self.qd, self.qdd = self._move.sample(self._move.t)
            self.q_target = self.q.copy()
            if self._move.t >= self._move.t_total:
                self.q = self._move.q0 + self._move.dq
                self.q_target = self.q.copy()
                self._move = None
                self.mode = "hold"
        elif self.mode == "servo":
            alpha = 1.0 - math.exp(-dt / self.servo_lag_s)
            step = np.clip(
                alpha * (self._servo_goal - self.q),
                -MAX_JOINT_SPEED_RAD_S * dt,
                MAX_JOINT_SPEED_RAD_S * dt,
            )
            qd = step / dt
            self.qdd = (qd - self.qd) / dt
            self.qd = qd
            self.q = self.q + step
            self.q_target = self._servo_goal.copy()
        elif self.mode == "stop":
            lead = float(np.abs(self.qd).max())
            if lead <= self._decel * dt:
                self.q = self.q + 0.5 * self.qd * dt
                self.qd = np.zeros(6)
                self.qdd = np.zeros(6)
                self.mode = "hold"
            else:
                qd = self.qd * (1.0 - self._decel * dt / lead)
                self.q = self.q + 0.5 * (self.qd + qd) * dt
                self.qdd = (qd - self.qd) / dt
                self.qd = qd
            self.q_target = self.q.copy()
        else:
            self.qd = np.zeros(6)
            self.qdd = np.zeros(6)
            self.q_target = self.q.copy()


# -- the controller ------------------------------------------------------------------------------


class _ControlScript:
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
            joints.stop(self.in_double(0))
            self.waiting = lambda: joints.mode != "stop"
            return
        elif cmd in (CMD_STOPJ, CMD_STOPL):
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


class _WriteProgram:
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


class Controller:
    """The fake controller's state: joints, safety, program, registers. No I/O.

    Args:
        home_deg: the six joint positions at start, deg.
        name: a label for the log.
        protective_stop_after_servo: enter a protective stop on this many servoJ commands.
        servo_lag_s: time constant of the servo set-point tracking, s.
    """

    def __init__(
        self,
        home_deg: Sequence[float],
        *,
        name: str = "ur",
        protective_stop_after_servo: int | None = None,
        servo_lag_s: float = 0.004,
    ) -> None:
        home = np.asarray(home_deg, dtype=np.float64)
        if home.shape != (6,):
            raise ValueError(f"home_deg needs 6 joint positions, got {home.shape}")
        self.name = name
        self.t = 0.0
        self.ticks = 0
        self.joints = _Joints(np.deg2rad(home), servo_lag_s)
        self.robot_mode = ROBOT_MODE_RUNNING
        self.safety_mode = SAFETY_MODE_NORMAL
        self.runtime_state = RUNTIME_STOPPED
        self.protective_stop_t: float | None = None
        self.in_int = [0] * 48
        self.in_double = [0.0] * 48
        self.in_bits = 0
        self.out_int = [0] * 48
        self.out_double = [0.0] * 48
        self.out_bits = 0
        self.inputs: dict[str, Any] = {"speed_slider_fraction": 1.0}
        self.program: _ControlScript | _WriteProgram | None = None
        self.program_name = "<unnamed>"
        self.protective_stop_after_servo = protective_stop_after_servo
        self.servo_commands = 0
        self.watchdog_last_update = 0.0
        self._fk_cache: tuple[bytes, tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None

    # -- safety and program ------------------------------------------------------------------

    @property
    def protective_stopped(self) -> bool:
        return self.safety_mode == SAFETY_MODE_PROTECTIVE_STOP

    def protective_stop(self, why: str) -> None:
        if self.protective_stopped:
            return
        log.warning("%s: protective stop (%s) at t=%.3f s", self.name, why, self.t)
        self.safety_mode = SAFETY_MODE_PROTECTIVE_STOP
        self.protective_stop_t = self.t
        self.joints.stop(PROTECTIVE_STOP_DECEL_RAD_S2)
        if self.runtime_state == RUNTIME_PLAYING:
            self.runtime_state = RUNTIME_PAUSED

    def unlock_protective_stop(self) -> str:
        if not self.protective_stopped:
            return "Protective stop releasing"
        assert self.protective_stop_t is not None
        if self.t - self.protective_stop_t < UNLOCK_DELAY_S:
            return (
                "Cannot unlock protective stop until 5s after occurrence. "
                "Always inspect cause of protective stop before unlocking"
            )
        self.safety_mode = SAFETY_MODE_NORMAL
        self.protective_stop_t = None
        log.info("%s: protective stop unlocked", self.name)
        return "Protective stop releasing"

    def load_program(self, text: str) -> None:
        """A URScript program arrived on a script port: it replaces the running one."""
        m = re.match(r"\s*(def|sec)\s+(\w+)\s*\(", text)
        if m is None:
            log.warning("%s: ignoring script text that is not a program: %.60r", self.name, text)
            return
        kind, name = m.group(1), m.group(2)
        if kind == "sec":
            log.info("%s: secondary program %s ignored", self.name, name)
            return
        if self.robot_mode != ROBOT_MODE_RUNNING or self.protective_stopped:
            log.warning(
                "%s: program %s not started (robot mode %s, safety mode %s)",
                self.name,
                name,
                ROBOT_MODE_NAMES.get(self.robot_mode),
                SAFETY_MODE_NAMES.get(self.safety_mode),
            )
            return
        if self.program is not None:
            self.stop_program(f"replaced by {name}")
        self.program_name = name
        if "read_input_integer_reg(0)" in text and "signal_ready" in text:
            off_i = _injected_int(text, "reg_offset_int")
            off_d = _injected_int(text, "reg_offset_float")
            self.program = _ControlScript(self, off_i, off_d)
            log.info("%s: ur-rtde control script running (register offset %d)", self.name, off_i)
        else:
            self.program = _WriteProgram(self, text)
            log.info("%s: program %s running", self.name, name)
        self.runtime_state = RUNTIME_PLAYING

    def stop_program(self, why: str) -> None:
        if self.program is None and self.runtime_state == RUNTIME_STOPPED:
            return
        log.info("%s: program stopped (%s)", self.name, why)
        self.program = None
        self.runtime_state = RUNTIME_STOPPED
        if self.joints.mode in ("movej", "servo") or self.joints.moving:
            self.joints.stop(PROGRAM_STOP_DECEL_RAD_S2)

    def play(self) -> bool:
        if self.program is None or self.protective_stopped:
            return False
        if self.robot_mode != ROBOT_MODE_RUNNING:
            return False
        self.runtime_state = RUNTIME_PLAYING
        return True

    def pause(self) -> bool:
        if self.runtime_state != RUNTIME_PLAYING:
            return False
        self.runtime_state = RUNTIME_PAUSED
        self.joints.stop(PROGRAM_STOP_DECEL_RAD_S2)
        return True

    # -- inputs from RTDE clients ------------------------------------------------------------

    def set_input(self, name: str, value: Any) -> None:
        reg = _register(name)
        if reg is not None:
            _, kind, index = reg
            if kind == "int":
                self.in_int[index] = int(value)
                self._int_register_written(index, int(value))
            elif kind == "double":
                self.in_double[index] = float(value)
            else:
                self.in_bits = _set_bit(self.in_bits, index, bool(value))
            return
        if name == "input_bit_registers0_to_31":
            self.in_bits = (self.in_bits & ~0xFFFFFFFF) | int(value)
        elif name == "input_bit_registers32_to_63":
            self.in_bits = (self.in_bits & ~(0xFFFFFFFF << 32)) | (int(value) << 32)
        else:
            self.inputs[name] = value

    def _int_register_written(self, index: int, value: int) -> None:
        script = self.program if isinstance(self.program, _ControlScript) else None
        if script is None or index != script.off_i:
            return
        self.watchdog_last_update = self.t
        if value == CMD_SERVOJ and self.runtime_state == RUNTIME_PLAYING:
            self.servo_commands += 1
            n = self.protective_stop_after_servo
            if n is not None and self.servo_commands == n:
                self.protective_stop(f"injected after {n} servoJ commands")

    # -- the control loop --------------------------------------------------------------------

    def tick(self) -> None:
        """One 2 ms cycle: the program, then the joints."""
        self.ticks += 1
        self.t = self.ticks * CONTROL_PERIOD_S
        program = self.program
        if program is not None and self.runtime_state == RUNTIME_PLAYING:
            if isinstance(program, _ControlScript) and program.watchdog_period_s is not None:
                if self.t - self.watchdog_last_update > program.watchdog_period_s:
                    log.warning("%s: RTDE watchdog expired, stopping the program", self.name)
                    self.stop_program("watchdog")
                    program = None
            if program is not None:
                program.cycle()
        self.joints.step(CONTROL_PERIOD_S)

    # -- outputs -----------------------------------------------------------------------------

    def _fk(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Actual and target flange poses and the elbow position, computed once per change."""
        key = self.joints.q.tobytes() + self.joints.q_target.tobytes()
        if self._fk_cache is None or self._fk_cache[0] != key:
            actual, elbow = _forward_kinematics(self.joints.q)
            if np.array_equal(self.joints.q_target, self.joints.q):
                target = actual
            else:
                target, _ = _forward_kinematics(self.joints.q_target)
            self._fk_cache = (key, (actual, target, elbow))
        return self._fk_cache[1]

    def safety_status_bits(self) -> int:
        if self.protective_stopped:
            return (1 << SAFETY_BIT_PROTECTIVE_STOPPED) | (1 << SAFETY_BIT_STOPPED_DUE_TO_SAFETY)
        return 1 << SAFETY_BIT_NORMAL_MODE

    def robot_status_bits(self) -> int:
        bits = 0
        if self.robot_mode >= 4:
            bits |= 1 << ROBOT_BIT_POWER_ON
        if self.runtime_state == RUNTIME_PLAYING:
            bits |= 1 << ROBOT_BIT_PROGRAM_RUNNING
        return bits

    def output_getter(self, name: str) -> Callable[[], object]:
        """A function returning the current value of output variable ``name``."""
        reg = _register(name)
        if reg is not None:
            direction, kind, index = reg
            if kind == "int":
                regs = self.out_int if direction == "output" else self.in_int
                return lambda: regs[index]
            if kind == "double":
                dregs = self.out_double if direction == "output" else self.in_double
                return lambda: dregs[index]
            if direction == "output":
                return lambda: bool((self.out_bits >> index) & 1)
            return lambda: bool((self.in_bits >> index) & 1)
        j = self.joints
        zeros6, zeros3 = (0.0,) * 6, (0.0,) * 3
        getters: dict[str, Callable[[], object]] = {
            "timestamp": lambda: self.t,
            "target_q": lambda: tuple(j.q_target),
            "target_qd": lambda: tuple(j.qd),
            "target_qdd": lambda: tuple(j.qdd),
            "actual_q": lambda: tuple(j.q),
            "actual_qd": lambda: tuple(j.qd),
            "actual_TCP_pose": lambda: tuple(self._fk()[0]),
            "target_TCP_pose": lambda: tuple(self._fk()[1]),
            "elbow_position": lambda: tuple(self._fk()[2]),
            "joint_temperatures": lambda: (31.0,) * 6,
            "actual_joint_voltage": lambda: (47.5,) * 6,
            "actual_execution_time": lambda: 0.35,
            "robot_mode": lambda: self.robot_mode,
            "joint_mode": lambda: (JOINT_MODE_RUNNING,) * 6,
            "safety_mode": lambda: self.safety_mode,
            "safety_status": lambda: self.safety_mode,
            "actual_tool_accelerometer": lambda: (0.0, 0.0, -9.81),
            "speed_scaling": lambda: 0.0 if self.protective_stopped else 1.0,
            "target_speed_fraction": lambda: float(self.inputs["speed_slider_fraction"]),
            "actual_main_voltage": lambda: 48.0,
            "actual_robot_voltage": lambda: 47.8,
            "actual_robot_current": lambda: 0.6,
            "runtime_state": lambda: self.runtime_state,
            "robot_status_bits": self.robot_status_bits,
            "safety_status_bits": self.safety_status_bits,
            "output_bit_registers0_to_31": lambda: self.out_bits & 0xFFFFFFFF,
            "output_bit_registers32_to_63": lambda: (self.out_bits >> 32) & 0xFFFFFFFF,
            "input_bit_registers0_to_31": lambda: self.in_bits & 0xFFFFFFFF,
            "input_bit_registers32_to_63": lambda: (self.in_bits >> 32) & 0xFFFFFFFF,
            "tool_temperature": lambda: 33.0,
            "payload": lambda: 0.0,
        }
        if name in getters:
            return getters[name]
        kind = _OUTPUT_TYPES[name]
        if kind == "VECTOR6D":
            return lambda: zeros6
        if kind == "VECTOR3D":
            return lambda: zeros3
        if kind == "VECTOR6INT32":
            return lambda: (0,) * 6
        if kind == "DOUBLE":
            return lambda: 0.0
        if kind == "BOOL":
            return lambda: False
        return lambda: 0


def _set_bit(bits: int, index: int, value: bool) -> int:
    return bits | (1 << index) if value else bits & ~(1 << index)


def _injected_int(script: str, variable: str) -> int:
    """The value ur-rtde injected after ``global <variable> = # ... register offset``."""
    m = re.search(rf"global\s+{variable}\s*=\s*(?:#[^\n]*\n\s*)?(\d+)", script)
    return int(m.group(1)) if m else 0


# -- RTDE server ---------------------------------------------------------------------------------


@dataclass
class _OutputRecipe:
    recipe_id: int
    names: list[str]
    getters: list[Callable[[], object]]
    packer: struct.Struct
    period_s: float
    next_t: float = 0.0


@dataclass
class _InputRecipe:
    recipe_id: int
    names: list[str]
    unpacker: struct.Struct
    vector: list[int]  # per field: number of values it takes from the unpacked tuple


class _RTDESession(asyncio.Protocol):
    """One RTDE client connection."""

    def __init__(self, server: FakeServer) -> None:
        self.server = server
        self.ctl = server.controller
        self.buffer = bytearray()
        self.transport: asyncio.Transport | None = None
        self.outputs: list[_OutputRecipe] = []
        self.inputs: dict[int, _InputRecipe] = {}
        self.started = False
        self.peer = "?"
        self.owners = server.input_owners

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        host, port = transport.get_extra_info("peername")[:2]
        self.peer = f"{host}:{port}"
        self.server.rtde_sessions.add(self)
        log.debug("%s: RTDE connection from %s", self.ctl.name, self.peer)

    def connection_lost(self, exc: Exception | None) -> None:
        self.server.rtde_sessions.discard(self)
        for name, owner in list(self.owners.items()):
            if owner is self:
                del self.owners[name]
        log.debug("%s: RTDE connection from %s closed", self.ctl.name, self.peer)

    def send(self, kind: int, payload: bytes = b"") -> None:
        if self.transport is not None and not self.transport.is_closing():
            self.transport.write(_HEADER.pack(len(payload) + 3, kind) + payload)

    def data_received(self, data: bytes) -> None:
        self.buffer += data
        while len(self.buffer) >= 3:
            size, kind = _HEADER.unpack_from(self.buffer)
            if size < 3:
                log.warning("%s: RTDE package size %d from %s", self.ctl.name, size, self.peer)
                assert self.transport is not None
                self.transport.close()
                return
            if len(self.buffer) < size:
                return
            payload = bytes(self.buffer[3:size])
            del self.buffer[:size]
            try:
                self.handle(kind, payload)
            except Exception:
                log.exception("%s: RTDE package %r from %s", self.ctl.name, chr(kind), self.peer)

    def handle(self, kind: int, payload: bytes) -> None:
        if kind == RTDE_DATA_PACKAGE:
            self.data_package(payload)
            return
        self.server.record(f"rtde {chr(kind)} {self._describe(kind, payload)}")
        if kind == RTDE_REQUEST_PROTOCOL_VERSION:
            (version,) = struct.unpack(">H", payload[:2])
            self.send(kind, struct.pack(">B", 1 if version == 2 else 0))
        elif kind == RTDE_GET_URCONTROL_VERSION:
            self.send(kind, struct.pack(">IIII", *CONTROLLER_VERSION))
        elif kind == RTDE_CONTROL_PACKAGE_SETUP_OUTPUTS:
            self.setup_outputs(payload)
        elif kind == RTDE_CONTROL_PACKAGE_SETUP_INPUTS:
            self.setup_inputs(payload)
        elif kind == RTDE_CONTROL_PACKAGE_START:
            ok = bool(self.outputs) or bool(self.inputs)
            self.started = self.started or ok
            for recipe in self.outputs:
                recipe.next_t = self.ctl.t
            self.send(kind, struct.pack(">B", 1 if ok else 0))
        elif kind == RTDE_CONTROL_PACKAGE_PAUSE:
            self.started = False
            self.send(kind, struct.pack(">B", 1))
        elif kind == RTDE_TEXT_MESSAGE:
            log.info("%s: RTDE text message from %s: %r", self.ctl.name, self.peer, payload)
        else:
            log.warning("%s: unknown RTDE package type %d from %s", self.ctl.name, kind, self.peer)

    @staticmethod
    def _describe(kind: int, payload: bytes) -> str:
        if kind == RTDE_REQUEST_PROTOCOL_VERSION and len(payload) >= 2:
            return str(struct.unpack(">H", payload[:2])[0])
        if kind == RTDE_CONTROL_PACKAGE_SETUP_OUTPUTS and len(payload) >= 8:
            return f"{struct.unpack('>d', payload[:8])[0]:g} Hz {payload[8:].decode()}"
        if kind == RTDE_CONTROL_PACKAGE_SETUP_INPUTS:
            return payload.decode()
        return ""

    def setup_outputs(self, payload: bytes) -> None:
        (frequency,) = struct.unpack(">d", payload[:8])
        names = [n for n in payload[8:].decode().split(",") if n]
        types = [output_type(n) for n in names]
        ok = names and "NOT_FOUND" not in types and 0.0 < frequency <= 500.0
        recipe_id = len(self.outputs) + 1 if ok else 0
        if ok:
            fmt = ">B" + "".join(_TYPE_FORMATS[t] for t in types)
            self.outputs.append(
                _OutputRecipe(
                    recipe_id,
                    names,
                    [self.ctl.output_getter(n) for n in names],
                    struct.Struct(fmt),
                    1.0 / frequency,
                )
            )
        else:
            log.warning(
                "%s: output recipe refused (%g Hz): %s",
                self.ctl.name,
                frequency,
                [n for n, t in zip(names, types, strict=True) if t == "NOT_FOUND"],
            )
        self.send(RTDE_CONTROL_PACKAGE_SETUP_OUTPUTS, bytes([recipe_id]) + ",".join(types).encode())

    def setup_inputs(self, payload: bytes) -> None:
        names = [n for n in payload.decode().split(",") if n]
        types = []
        for n in names:
            t = input_type(n)
            owner = self.owners.get(n)
            types.append("IN_USE" if t != "NOT_FOUND" and owner not in (None, self) else t)
        ok = names and all(t in _TYPE_FORMATS for t in types)
        recipe_id = len(self.inputs) + 1 if ok else 0
        if ok:
            fmt = ">" + "".join(_TYPE_FORMATS[t] for t in types)
            counts = [int(_TYPE_FORMATS[t][:-1] or 1) for t in types]
            self.inputs[recipe_id] = _InputRecipe(recipe_id, names, struct.Struct(fmt), counts)
            for n in names:
                self.owners[n] = self
        else:
            log.warning(
                "%s: input recipe refused: %s", self.ctl.name, dict(zip(names, types, strict=True))
            )
        self.send(RTDE_CONTROL_PACKAGE_SETUP_INPUTS, bytes([recipe_id]) + ",".join(types).encode())

    def data_package(self, payload: bytes) -> None:
        if not payload:
            return
        recipe = self.inputs.get(payload[0])
        if recipe is None or len(payload) - 1 != recipe.unpacker.size:
            log.warning(
                "%s: data package for unknown recipe %d (%d bytes) from %s",
                self.ctl.name,
                payload[0],
                len(payload),
                self.peer,
            )
            return
        values = recipe.unpacker.unpack_from(payload, 1)
        i = 0
        for name, count in zip(recipe.names, recipe.vector, strict=True):
            value = values[i] if count == 1 else values[i : i + count]
            i += count
            self.ctl.set_input(name, value)

    def publish(self) -> None:
        """Send the data packages that are due at the controller's current time."""
        if not self.started or self.transport is None or self.transport.is_closing():
            return
        if self.transport.get_write_buffer_size() > 1 << 20:
            return  # the client does not read: drop packages rather than buffer without end
        t = self.ctl.t
        for recipe in self.outputs:
            if t + 1e-9 < recipe.next_t:
                continue
            recipe.next_t += recipe.period_s
            if recipe.next_t <= t:
                recipe.next_t = t + recipe.period_s
            args: list[object] = [recipe.recipe_id]
            for getter in recipe.getters:
                value = getter()
                if isinstance(value, tuple):
                    args.extend(value)
                else:
                    args.append(value)
            self.send(RTDE_DATA_PACKAGE, recipe.packer.pack(*args))


# -- dashboard server ----------------------------------------------------------------------------


class _DashboardSession(asyncio.Protocol):
    """One dashboard-server connection: a line in, a line out."""

    def __init__(self, server: FakeServer) -> None:
        self.server = server
        self.ctl = server.controller
        self.buffer = b""
        self.transport: asyncio.Transport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        transport.write(b"Connected: Universal Robots Dashboard Server\n")

    def data_received(self, data: bytes) -> None:
        self.buffer += data
        while b"\n" in self.buffer:
            line, self.buffer = self.buffer.split(b"\n", 1)
            command = line.decode(errors="replace").strip()
            if not command:
                continue
            self.server.record(f"dashboard {command}")
            reply = self.reply(command)
            assert self.transport is not None
            self.transport.write(reply.encode() + b"\n")
            if command.lower() == "quit":
                self.transport.close()
                return

    def reply(self, command: str) -> str:
        ctl = self.ctl
        lower = command.lower()
        word, _, rest = command.partition(" ")
        if lower == "polyscopeversion":
            return POLYSCOPE_VERSION
        if lower == "version":
            return ".".join(str(v) for v in CONTROLLER_VERSION)
        if lower == "get serial number":
            return self.server.serial_number
        if lower == "get robot model":
            return "UR5"
        if lower == "is in remote control":
            return "true"
        if lower == "robotmode":
            return f"Robotmode: {ROBOT_MODE_NAMES.get(ctl.robot_mode, 'UNKNOWN')}"
        if lower in ("safetymode", "safetystatus"):
            label = "Safetymode" if lower == "safetymode" else "Safetystatus"
            return f"{label}: {SAFETY_MODE_NAMES.get(ctl.safety_mode, 'FAULT')}"
        if lower == "programstate":
            return f"{RUNTIME_NAMES.get(ctl.runtime_state, 'STOPPED')} {ctl.program_name}"
        if lower == "running":
            return f"Program running: {str(ctl.runtime_state == RUNTIME_PLAYING).lower()}"
        if lower == "get loaded program":
            return f"Loaded program: {ctl.program_name}"
        if lower == "isprogramsaved":
            return f"true {ctl.program_name}"
        if lower == "get operational mode":
            return "NONE"
        if lower == "power on":
            if ctl.robot_mode == ROBOT_MODE_POWER_OFF:
                ctl.robot_mode = ROBOT_MODE_IDLE
            return "Powering on"
        if lower == "power off":
            ctl.stop_program("power off")
            ctl.robot_mode = ROBOT_MODE_POWER_OFF
            return "Powering off"
        if lower == "brake release":
            if ctl.robot_mode in (ROBOT_MODE_IDLE, 4):
                ctl.robot_mode = ROBOT_MODE_RUNNING
            return "Brake releasing"
        if lower == "unlock protective stop":
            return ctl.unlock_protective_stop()
        if lower == "close safety popup":
            return "closing safety popup"
        if lower == "close popup":
            return "closing popup"
        if word.lower() == "popup":
            return "showing popup"
        if word.lower() == "addtolog":
            return "Added log message"
        if lower == "restart safety":
            ctl.safety_mode = SAFETY_MODE_NORMAL
            ctl.stop_program("restart safety")
            ctl.robot_mode = ROBOT_MODE_POWER_OFF
            return "Restarting safety"
        if lower == "stop":
            ctl.stop_program("dashboard stop")
            return "Stopped"
        if lower == "pause":
            return "Pausing program" if ctl.pause() else "Failed to execute: pause"
        if lower == "play":
            return "Starting program" if ctl.play() else "Failed to execute: play"
        if word.lower() == "load":
            ctl.program_name = rest.strip()
            return f"Loading program: {rest.strip()}"
        if lower == "shutdown":
            return "Shutting down"
        if lower == "quit":
            return "Disconnected"
        return f"could not understand: '{command}'"


# -- script ports --------------------------------------------------------------------------------

_PROGRAM_END = re.compile(r"^end[ \t]*(#[^\n]*)?(\n|\Z)", re.MULTILINE)


class _ScriptSession(asyncio.Protocol):
    """One connection to a script port (30001/30002/30003): URScript text in, nothing out."""

    def __init__(self, server: FakeServer, port: int) -> None:
        self.server = server
        self.port = port
        self.text = ""

    def data_received(self, data: bytes) -> None:
        self.text += data.decode(errors="replace")
        while True:
            stripped = self.text.lstrip()
            if not stripped:
                self.text = ""
                return
            if re.match(r"(def|sec)\s", stripped):
                m = _PROGRAM_END.search(stripped)
                if m is None:
                    self.text = stripped
                    return  # wait for the rest of the program
                program, self.text = stripped[: m.end()], stripped[m.end() :]
                first = program.splitlines()[0]
                self.server.record(f"script:{self.port} {first} ... ({len(program)} chars)")
                self.server.controller.load_program(program)
            else:
                if "\n" not in stripped:
                    self.text = stripped
                    return
                line, self.text = stripped.split("\n", 1)
                self.server.record(f"script:{self.port} {line.strip()}")
                log.warning(
                    "%s: one-line script command not emulated: %s",
                    self.server.controller.name,
                    line.strip(),
                )


# -- the server process --------------------------------------------------------------------------


class FakeServer:
    """The fake controller's servers and 500 Hz loop on one host address (asyncio)."""

    def __init__(self, host: str, controller: Controller, serial_number: str = "20235500001"):
        self.host = host
        self.controller = controller
        self.serial_number = serial_number
        self.rtde_sessions: set[_RTDESession] = set()
        self.input_owners: dict[str, _RTDESession] = {}
        self.requests: list[str] = []

    def record(self, request: str) -> None:
        """Log one request from a client (``--verbose`` prints them)."""
        if len(self.requests) < 1000:
            self.requests.append(request)
        log.debug("%s: %s", self.controller.name, request)

    async def serve(self, stop: asyncio.Event) -> None:
        loop = asyncio.get_running_loop()
        servers = [
            await loop.create_server(lambda: _RTDESession(self), self.host, RTDE_PORT),
            await loop.create_server(lambda: _DashboardSession(self), self.host, DASHBOARD_PORT),
        ]
        for port in SCRIPT_PORTS:
            servers.append(
                await loop.create_server(
                    lambda port=port: _ScriptSession(self, port), self.host, port
                )
            )
        log.info("%s: serving on %s ports %s", self.controller.name, self.host, ALL_PORTS)
        print(f"{READY_LINE} {self.host}", flush=True)
        control = asyncio.create_task(self._control_loop())
        await stop.wait()
        control.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await control
        for server in servers:
            server.close()
        for session in list(self.rtde_sessions):
            if session.transport is not None:
                session.transport.close()
        for server in servers:
            await server.wait_closed()

    async def _control_loop(self) -> None:
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        ctl = self.controller
        while True:
            due = t0 + (ctl.ticks + 1) * CONTROL_PERIOD_S
            delay = due - loop.time()
            if delay > 0:
                await asyncio.sleep(delay)
            behind = int((loop.time() - t0) / CONTROL_PERIOD_S) - ctl.ticks
            if behind > 250:  # stalled (e.g. a suspended process): do not replay the gap
                t0 += (behind - 1) * CONTROL_PERIOD_S
                behind = 1
            try:
                for _ in range(max(behind, 1)):
                    ctl.tick()
                for session in list(self.rtde_sessions):
                    session.publish()
            except Exception:
                log.exception("%s: control loop", ctl.name)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m sim.ur_controller", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument("--host", default="127.0.0.2", help="address to serve on")
    parser.add_argument(
        "--home-deg", type=float, nargs=6, required=True, metavar="Q", help="start joints, deg"
    )
    parser.add_argument("--protective-stop-after-servo", type=int, default=None, metavar="N")
    parser.add_argument("--servo-lag-s", type=float, default=0.004)
    parser.add_argument("--name", default=None, help="label in the log")
    parser.add_argument("--verbose", action="store_true", help="log every client request")
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.WARNING,
        format="%(asctime)s %(levelname)s %(message)s",
        stream=sys.stderr,
    )
    controller = Controller(
        args.home_deg,
        name=args.name or f"ur@{args.host}",
        protective_stop_after_servo=args.protective_stop_after_servo,
        servo_lag_s=args.servo_lag_s,
    )
    server = FakeServer(args.host, controller)

    async def run() -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, stop.set)
        await server.serve(stop)

    try:
        asyncio.run(run())
    except OSError as exc:
        log.error("%s: cannot serve on %s: %s", controller.name, args.host, exc)
        return 1
    return 0


# -- launcher for tests and tools ----------------------------------------------------------------


class FakeURController:
    """Run ``python -m sim.ur_controller`` as a subprocess for the life of a ``with`` block.

    Waits until the process reports that all its ports are open (raises RuntimeError with the
    process's log when it exits first, e.g. because another process holds a port on ``host``,
    or when ``startup_timeout_s`` passes), and terminates it (SIGTERM, then SIGKILL) on exit.
    One fake per host address.
    """

    def __init__(
        self,
        host: str,
        home_deg: Sequence[float],
        *,
        protective_stop_after_servo: int | None = None,
        name: str | None = None,
        servo_lag_s: float | None = None,
        verbose: bool = False,
        startup_timeout_s: float = 15.0,
    ) -> None:
        if len(home_deg) != 6:
            raise ValueError(f"home_deg needs 6 joint positions, got {len(home_deg)}")
        self.host = host
        self.home_deg = tuple(float(v) for v in home_deg)
        self.name = name or f"ur@{host}"
        self.startup_timeout_s = startup_timeout_s
        self.args = [
            sys.executable,
            "-m",
            "sim.ur_controller",
            "--host",
            host,
            "--home-deg",
            *(repr(v) for v in self.home_deg),
            "--name",
            self.name,
        ]
        if protective_stop_after_servo is not None:
            self.args += ["--protective-stop-after-servo", str(protective_stop_after_servo)]
        if servo_lag_s is not None:
            self.args += ["--servo-lag-s", repr(servo_lag_s)]
        if verbose:
            self.args.append("--verbose")
        self.process: subprocess.Popen[bytes] | None = None
        self._log = tempfile.TemporaryFile()

    def start(self) -> FakeURController:
        root = Path(__file__).resolve().parents[1]
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(p for p in (str(root), env.get("PYTHONPATH", "")) if p)
        self.process = subprocess.Popen(
            self.args, stdin=subprocess.DEVNULL, stdout=self._log, stderr=self._log, env=env
        )
        deadline = time.monotonic() + self.startup_timeout_s
        ready = f"{READY_LINE} {self.host}\n"
        while ready not in self.log_text():
            if self.process.poll() is not None:
                raise RuntimeError(
                    f"fake UR controller {self.name} exited with {self.process.returncode}:\n"
                    + self.log_text()
                )
            if time.monotonic() > deadline:
                self.stop()
                raise RuntimeError(
                    f"fake UR controller {self.name} did not open its ports on {self.host} "
                    f"within {self.startup_timeout_s} s:\n" + self.log_text()
                )
            time.sleep(0.02)
        return self

    def log_text(self) -> str:
        """What the process wrote to stdout and stderr so far."""
        self._log.seek(0)
        return self._log.read().decode(errors="replace")

    def stop(self) -> None:
        process, self.process = self.process, None
        if process is None or process.poll() is not None:
            return
        process.terminate()
        try:
            process.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(timeout=5.0)

    def __enter__(self) -> FakeURController:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def __del__(self) -> None:
        with contextlib.suppress(Exception):
            self.stop()
            self._log.close()


if __name__ == "__main__":
    sys.exit(main())
