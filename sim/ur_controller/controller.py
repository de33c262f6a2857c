"""The fake controller's state: program, modes, protective stop, inputs and outputs.

``--protective-stop-after-servo N``: the N-th servoJ command received puts the arm into a
protective stop, as the real controller does on a fault: ``safety_mode`` PROTECTIVE_STOP (3),
``safety_status_bits`` bit 2 (and bit 10, stopped due to safety), the program paused
(``runtime_state`` PAUSED), the joints decelerated to standstill, further motion refused. The
dashboard's ``unlock protective stop`` clears it, as on the robot not before 5 s have passed;
the program then stays paused (``play`` resumes it, or upload the script again).

``--silent-after-servo N``: the N-th servoJ command makes the controller stop answering
altogether (a hung controller or a cut network behind a switch that keeps the links up): the
joints move no more, no RTDE package goes out, no request on any port is answered, and the
connections stay open. ``--silent-after-handshake``: RTDE answers the protocol-version request
and nothing after it (the dashboard and the script ports still answer).

Events a test or a benchmark times against the host's clock are printed to stdout as
``EVENT <name> <time.monotonic()>`` lines: ``silent``, ``protective_stop``, ``stop`` (a
servoStop, speedStop, stopJ or stopL taken by the control script).
"""

from __future__ import annotations

import logging
import re
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from sim.ur_controller.arm import (
    CONTROL_PERIOD_S,
    PROGRAM_STOP_DECEL_RAD_S2,
    PROTECTIVE_STOP_DECEL_RAD_S2,
    UNLOCK_DELAY_S,
    Joints,
    forward_kinematics,
)
from sim.ur_controller.control_script import CMD_SERVOJ, ControlScript, WriteProgram
from sim.ur_controller.events import print_event

log = logging.getLogger("sim.ur_controller")


CONTROLLER_VERSION = (5, 15, 2, 126234)
"""What ``v`` (get URControl version) answers: major, minor, bugfix, build."""

POLYSCOPE_VERSION = "URSoftware 5.15.2.126234 (Feb 02 2024)"

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


class Controller:
    """The fake controller's state: joints, safety, program, registers. No I/O.

    Args:
        home_deg: the six joint positions at start, deg.
        name: a label for the log.
        protective_stop_after_servo: enter a protective stop on this many servoJ commands.
        silent_after_servo: stop answering anything on this many servoJ commands.
        servo_lag_s: time constant of the servo set-point tracking, s.
    """

    def __init__(
        self,
        home_deg: Sequence[float],
        *,
        name: str = "ur",
        protective_stop_after_servo: int | None = None,
        silent_after_servo: int | None = None,
        servo_lag_s: float = 0.004,
    ) -> None:
        home = np.asarray(home_deg, dtype=np.float64)
        if home.shape != (6,):
            raise ValueError(f"home_deg needs 6 joint positions, got {home.shape}")
        self.name = name
        self.t = 0.0
        self.ticks = 0
        self.joints = Joints(np.deg2rad(home), servo_lag_s)
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
        self.program: ControlScript | WriteProgram | None = None
        self.program_name = "<unnamed>"
        self.protective_stop_after_servo = protective_stop_after_servo
        self.silent_after_servo = silent_after_servo
        self.silent = False
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
        print_event("protective_stop")
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
            self.program = ControlScript(self, off_i, off_d)
            log.info("%s: ur-rtde control script running (register offset %d)", self.name, off_i)
        else:
            self.program = WriteProgram(self, text)
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
        script = self.program if isinstance(self.program, ControlScript) else None
        if script is None or index != script.off_i:
            return
        self.watchdog_last_update = self.t
        if value == CMD_SERVOJ and self.runtime_state == RUNTIME_PLAYING:
            self.servo_commands += 1
            n = self.protective_stop_after_servo
            if n is not None and self.servo_commands == n:
                self.protective_stop(f"injected after {n} servoJ commands")
            if self.servo_commands == self.silent_after_servo:
                self.go_silent(f"injected after {self.servo_commands} servoJ commands")

    def go_silent(self, why: str) -> None:
        """Stop answering: the control loop freezes and no port answers from now on."""
        if not self.silent:
            log.warning("%s: silent (%s) at t=%.3f s", self.name, why, self.t)
            print_event("silent")
            self.silent = True

    # -- the control loop --------------------------------------------------------------------

    def tick(self) -> None:
        """One 2 ms cycle: the program, then the joints (once silent, only the clock runs)."""
        self.ticks += 1
        self.t = self.ticks * CONTROL_PERIOD_S
        if self.silent:
            return
        program = self.program
        if program is not None and self.runtime_state == RUNTIME_PLAYING:
            if isinstance(program, ControlScript) and program.watchdog_period_s is not None:
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
            actual, elbow = forward_kinematics(self.joints.q)
            if np.array_equal(self.joints.q_target, self.joints.q):
                target = actual
            else:
                target, _ = forward_kinematics(self.joints.q_target)
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
