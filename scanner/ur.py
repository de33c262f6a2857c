"""One Universal Robots e-series arm over ur-rtde: the :class:`~scanner.hardware.Arm` protocol.

:class:`URArm` drives one arm through ur-rtde's two interfaces: ``RTDEReceiveInterface`` for the
measured state (RTDE, port 30004) and ``RTDEControlInterface``, which talks to the dashboard
server (29999), uploads ur-rtde's control script (30003) and commands it through RTDE registers.

Units: degrees (and deg/s, deg/s^2) at this class's boundary, radians only in the calls to
ur-rtde. ``JointState.t_s`` is the controller's own ``timestamp`` (s since the controller
started): readings of one arm are exactly spaced, but the clocks of two arms are independent.

Points that matter on hardware:

- ur-rtde's constructors hold the GIL and have no timeout, and its blocking calls (stopJ,
  servoStop) wait on the controller for minutes: a controller that stops answering would freeze
  the whole process. The interfaces therefore live in a worker process
  (:class:`scanner.ur_client.URClient`) and every call has a deadline this process enforces
  (``call_timeout_s``, ``stop_timeout_s``, the connect timeout); past it the worker is killed
  and the call raises :class:`~scanner.hardware.DeviceTimeout`. Before that :meth:`URArm.connect`
  probes the controller itself (an RTDE protocol-version handshake on 30004, the dashboard's
  welcome line on 29999, a TCP connect on 30003), so that a dead port is named as such.
- ``move_to`` starts an asynchronous moveJ and waits for it in Python, so its timeout holds
  (a blocking moveJ only gives up after ur-rtde's 300 s); on timeout the arm is stopped.
- A reading is fresh when the controller's timestamp is no older than ``freshness_s`` by the
  host clock (their offset is tracked with a small allowance for clock drift) and newer than
  the last command sent to the arm (a set-point or a move): a stalled or dropped RTDE stream
  raises instead of returning the last value again, and a pose an exposure is decided on was
  read from a controller that was alive after it was told where to be. A stream that has not
  moved for ``silence_s`` is a silent controller: ``state`` and ``servo`` raise DeviceTimeout at
  once (not at the end of the caller's timeout), so a scan reaches SAFE within ``silence_s``
  plus one set-point period.
- In a protective stop ``state`` still answers (with ``protective_stop=True``, so a caller can
  record where the arm stopped); ``move_to`` and ``servo`` raise
  :class:`~scanner.hardware.ProtectiveStop`. Unlocking is an operator's decision on the pendant
  or dashboard and is not done here.
"""

from __future__ import annotations

import contextlib
import logging
import math
import socket
import struct
import time
from collections.abc import Sequence

import numpy as np

from scanner.hardware import DeviceError, DeviceTimeout, JointState, ProtectiveStop
from scanner.ur_client import URClient

log = logging.getLogger(__name__)

RTDE_PORT = 30004
DASHBOARD_PORT = 29999
SCRIPT_PORT = 30003

SAFETY_MODE_PROTECTIVE_STOP = 3

# ur-rtde's argument limits (rtde_control_interface.h)
_MAX_JOINT_SPEED_DEG_S = math.degrees(3.14)
_MAX_JOINT_ACCEL_DEG_S2 = math.degrees(40.0)
_LOOKAHEAD_RANGE_S = (0.03, 0.2)
_GAIN_RANGE = (100.0, 2000.0)

_RECEIVE_VARIABLES = [
    "timestamp",
    "actual_q",
    "actual_qd",
    "robot_mode",
    "safety_mode",
    "safety_status_bits",
    "runtime_state",
    "robot_status_bits",
]
"""The output recipe URArm asks for (what state() and the safety checks read)."""

_DRIFT_ALLOWANCE = 2e-4
"""How fast (s/s) the controller clock may fall behind the host's before readings look stale."""

SILENCE_S = 0.1
"""Default longest pause of an arm's RTDE stream (50 periods at 500 Hz) before the controller
counts as silent, s."""

_CLOSE_TIMEOUT_S = 3.0
"""Deadline of ur-rtde's disconnect (its destructors sleep 0.5 s each), s."""


class _Freshness:
    """Age of the newest reading: host time now minus the controller timestamp, less the
    smallest such offset seen (the transport latency), the offset allowed to creep up by
    :data:`_DRIFT_ALLOWANCE` so that clock drift does not age readings."""

    def __init__(self) -> None:
        self.offset_s: float | None = None
        self.offset_at_s = 0.0

    def age_s(self, timestamp_s: float, now_s: float) -> float:
        offset = now_s - timestamp_s
        if self.offset_s is None:
            self.offset_s, self.offset_at_s = offset, now_s
            return 0.0
        allowed = self.offset_s + _DRIFT_ALLOWANCE * (now_s - self.offset_at_s)
        if offset <= allowed:
            self.offset_s, self.offset_at_s = offset, now_s
            return 0.0
        return offset - allowed


class URArm:
    """One UR arm (six revolute joints, degrees) driven through ur-rtde.

    Args:
        name: the arm's name in the backend (``"source_arm"``), used in every message.
        host: the controller's address.
        joints: the six joint names, base to wrist 3.
        move_speed_deg_s: moveJ speed of the leading joint, deg/s.
        move_accel_deg_s2: moveJ acceleration of the leading joint, deg/s^2.
        stop_decel_deg_s2: stopJ deceleration of the leading joint, deg/s^2.
        servo_stop_decel_mm_s2: servoStop deceleration of the tool, mm/s^2.
        servo_lookahead_s: servoJ lookahead time, s (ur-rtde: 0.03 to 0.2).
        servo_gain: servoJ proportional gain (ur-rtde: 100 to 2000).
        arrival_tolerance_deg: how close to the goal a finished move must be, deg, per joint.
        freshness_s: the oldest reading ``state`` returns, s (5 RTDE periods at 500 Hz: the
            pose an exposure is decided on is at most this old, and newer than the last
            command).
        silence_s: the longest pause of the RTDE stream before the controller counts as
            silent (``state`` and ``servo`` raise at once), s.
        call_timeout_s: deadline of a ur-rtde call that does not wait for motion (readings,
            servoJ, starting a moveJ), s.
        stop_timeout_s: deadline of servoStop / stopJ, which return at standstill, s.
        frequency_hz: RTDE update rate, Hz (None: the controller's, 500 Hz on e-series).
        upper_range_registers: run ur-rtde's script on registers 24-47 (leave 0-23 to a
            fieldbus or another client).
    """

    def __init__(
        self,
        name: str,
        host: str,
        joints: Sequence[str],
        *,
        move_speed_deg_s: float = 30.0,
        move_accel_deg_s2: float = 60.0,
        stop_decel_deg_s2: float = 120.0,
        servo_stop_decel_mm_s2: float = 2000.0,
        servo_lookahead_s: float = 0.1,
        servo_gain: float = 300.0,
        arrival_tolerance_deg: float = 0.05,
        freshness_s: float = 0.01,
        silence_s: float = SILENCE_S,
        call_timeout_s: float = 0.5,
        stop_timeout_s: float = 1.0,
        frequency_hz: float | None = None,
        upper_range_registers: bool = False,
    ) -> None:
        joints = tuple(joints)
        if len(joints) != 6:
            raise ValueError(f"{name}: a UR arm has 6 joints, got {len(joints)}: {joints}")
        _check_range(name, "move_speed_deg_s", move_speed_deg_s, 0.0, _MAX_JOINT_SPEED_DEG_S)
        _check_range(name, "move_accel_deg_s2", move_accel_deg_s2, 0.0, _MAX_JOINT_ACCEL_DEG_S2)
        _check_range(name, "stop_decel_deg_s2", stop_decel_deg_s2, 0.0, _MAX_JOINT_ACCEL_DEG_S2)
        _check_range(name, "servo_lookahead_s", servo_lookahead_s, *_LOOKAHEAD_RANGE_S)
        _check_range(name, "servo_gain", servo_gain, *_GAIN_RANGE)
        for label, value in (
            ("servo_stop_decel_mm_s2", servo_stop_decel_mm_s2),
            ("arrival_tolerance_deg", arrival_tolerance_deg),
            ("freshness_s", freshness_s),
            ("call_timeout_s", call_timeout_s),
            ("stop_timeout_s", stop_timeout_s),
        ):
            if not value > 0:
                raise ValueError(f"{name}: {label} must be > 0, got {value}")
        self.name = name
        self.host = host
        self.joints = joints
        self.move_speed_deg_s = move_speed_deg_s
        self.move_accel_deg_s2 = move_accel_deg_s2
        self.stop_decel_deg_s2 = stop_decel_deg_s2
        self.servo_stop_decel_mm_s2 = servo_stop_decel_mm_s2
        self.servo_lookahead_s = servo_lookahead_s
        self.servo_gain = servo_gain
        self.arrival_tolerance_deg = arrival_tolerance_deg
        if not silence_s >= freshness_s:
            raise ValueError(
                f"{name}: silence_s must be >= freshness_s = {freshness_s}, got {silence_s}"
            )
        self.freshness_s = freshness_s
        self.silence_s = silence_s
        self.call_timeout_s = call_timeout_s
        self.stop_timeout_s = stop_timeout_s
        self.frequency_hz = frequency_hz
        self.upper_range_registers = upper_range_registers
        self._client: URClient | None = None
        self._servoing = False
        self._freshness = _Freshness()
        self._commanded_s = -math.inf  # time.monotonic() once the last command was sent

    def __repr__(self) -> str:
        state = "connected" if self.connected else "not connected"
        return f"URArm({self.name!r}, host={self.host!r}, {state})"

    @property
    def connected(self) -> bool:
        return self._client is not None and self._client.alive

    # -- connection ----------------------------------------------------------------------------

    def connect(self, timeout_s: float) -> None:
        """Probe the controller within ``timeout_s``, then open ur-rtde's interfaces.

        Raises DeviceTimeout (naming host and port) when a port does not answer in time,
        DeviceError when ur-rtde cannot set up (e.g. registers in use by another client).
        """
        if self.connected:
            return
        deadline = time.monotonic() + timeout_s
        self._probe_rtde(deadline, timeout_s)
        self._probe_dashboard(deadline, timeout_s)
        self._probe_port(SCRIPT_PORT, "script server", deadline, timeout_s).close()

        frequency = -1.0 if self.frequency_hz is None else float(self.frequency_hz)
        client = URClient(self.name, self.host)
        client.open(
            frequency,
            _RECEIVE_VARIABLES,
            self.upper_range_registers,
            max(deadline - time.monotonic(), 0.0),
        )
        self._client = client
        self._servoing = False
        self._freshness = _Freshness()
        try:
            running = client.call(
                "control", "isProgramRunning", timeout_s=self.call_timeout_s, what="connect"
            )
            if not running:
                raise DeviceError(
                    f"{self.name}: connect: ur-rtde's control script is not running on {self.host}"
                )
            self.state(max(deadline - time.monotonic(), 4 * self.freshness_s))
        except DeviceError:
            with contextlib.suppress(DeviceError):
                self.close()
            raise
        log.info("%s: connected to %s", self.name, self.host)

    def _probe_port(self, port: int, what: str, deadline: float, timeout_s: float) -> socket.socket:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise DeviceTimeout(
                f"{self.name}: connect: no time left for {what} {self.host}:{port} "
                f"(timeout {timeout_s} s)"
            )
        try:
            sock = socket.create_connection((self.host, port), timeout=remaining)
        except TimeoutError as exc:
            raise DeviceTimeout(
                f"{self.name}: connect: {what} {self.host}:{port} did not answer within "
                f"{timeout_s} s"
            ) from exc
        except OSError as exc:
            raise DeviceTimeout(
                f"{self.name}: connect: {what} {self.host}:{port} unreachable: {exc}"
            ) from exc
        return sock

    def _read_within(
        self, sock: socket.socket, n: int, deadline: float, what: str, timeout_s: float
    ) -> bytes:
        data = b""
        while len(data) < n:
            remaining = deadline - time.monotonic()
            try:
                if remaining <= 0:
                    raise TimeoutError
                sock.settimeout(remaining)
                chunk = sock.recv(n - len(data))
            except TimeoutError as exc:
                raise DeviceTimeout(
                    f"{self.name}: connect: {what} accepted the connection but did not answer "
                    f"within {timeout_s} s"
                ) from exc
            except OSError as exc:
                raise DeviceTimeout(f"{self.name}: connect: {what} failed: {exc}") from exc
            if not chunk:
                raise DeviceTimeout(f"{self.name}: connect: {what} closed the connection")
            data += chunk
        return data

    def _probe_rtde(self, deadline: float, timeout_s: float) -> None:
        """RTDE request-protocol-version handshake (package 'V', version 2)."""
        what = f"RTDE {self.host}:{RTDE_PORT}"
        with self._probe_port(RTDE_PORT, "RTDE", deadline, timeout_s) as sock:
            sock.sendall(struct.pack(">HBH", 5, 86, 2))
            size, kind = struct.unpack(">HB", self._read_within(sock, 3, deadline, what, timeout_s))
            body = self._read_within(sock, max(size - 3, 0), deadline, what, timeout_s)
        if kind != 86 or body[:1] != b"\x01":
            raise DeviceError(
                f"{self.name}: connect: {what} refused RTDE protocol version 2 "
                f"(answer type {kind}, {body!r})"
            )

    def _probe_dashboard(self, deadline: float, timeout_s: float) -> None:
        """The dashboard server's welcome line."""
        what = f"dashboard {self.host}:{DASHBOARD_PORT}"
        with self._probe_port(DASHBOARD_PORT, "dashboard", deadline, timeout_s) as sock:
            line = b""
            while not line.endswith(b"\n") and len(line) < 200:
                line += self._read_within(sock, 1, deadline, what, timeout_s)
        if b"Dashboard" not in line:
            raise DeviceError(f"{self.name}: connect: {what} answered {line!r}")

    # -- readings ------------------------------------------------------------------------------

    def _client_for(self, call: str) -> URClient:
        if self._client is None or not self._client.alive:
            raise DeviceError(f"{self.name}: {call}: not connected to {self.host}")
        return self._client

    def _calls(self, call: str, calls: list, timeout_s: float | None = None) -> list:
        """``calls`` in one round trip to the worker within ``timeout_s`` (``call_timeout_s``)."""
        client = self._client_for(call)
        return client.calls(calls, self.call_timeout_s if timeout_s is None else timeout_s, call)

    def _dropped(self, call: str) -> DeviceError:
        return DeviceError(
            f"{self.name}: {call}: the RTDE connection to {self.host}:{RTDE_PORT} dropped"
        )

    def _silent(self, call: str, age_s: float) -> DeviceTimeout:
        return DeviceTimeout(
            f"{self.name}: {call}: {self.host} is silent: no RTDE package for {age_s:.3f} s "
            f"(limit {self.silence_s} s)"
        )

    def _protective_stopped(self, call: str) -> bool:
        stopped, safety_mode = self._calls(
            call, [("receive", "isProtectiveStopped", ()), ("receive", "getSafetyMode", ())]
        )
        return bool(stopped or safety_mode == SAFETY_MODE_PROTECTIVE_STOP)

    def state(self, timeout_s: float) -> JointState:
        """The measured joints (deg) and the controller timestamp of one fresh RTDE package
        (at most ``freshness_s`` old and newer than the last command: waits for the next
        package, one RTDE period at most, after a set-point); raises DeviceTimeout when none
        is fresh within ``timeout_s``, at once when the stream has been silent for
        ``silence_s``."""
        deadline = time.monotonic() + timeout_s
        age = math.nan
        reading = [
            ("receive", "isConnected", ()),
            ("receive", "getTimestamp", ()),
            ("receive", "getActualQ", ()),
            ("receive", "isProtectiveStopped", ()),
            ("receive", "getSafetyMode", ()),
            ("receive", "getTimestamp", ()),
        ]
        while True:
            connected, t0, q_rad, stopped, safety_mode, t1 = self._calls("state", reading)
            if not connected:
                raise self._dropped("state")
            now = time.monotonic()
            if t0 == t1:  # q and the flags belong to one package
                age = self._freshness.age_s(t1, now)
                if age <= self.freshness_s and now - age > self._commanded_s:
                    q = np.rad2deg(np.asarray(q_rad, dtype=np.float64))
                    if q.shape != (6,):
                        raise DeviceError(
                            f"{self.name}: state: {self.host} sent actual_q of shape {q.shape}"
                        )
                    stopped = bool(stopped or safety_mode == SAFETY_MODE_PROTECTIVE_STOP)
                    return JointState(q=q, t_s=float(t1), protective_stop=stopped)
                if age > self.silence_s:
                    raise self._silent("state", age)
            if now >= deadline:
                raise DeviceTimeout(
                    f"{self.name}: state: no fresh reading from {self.host} within {timeout_s} s "
                    f"(controller timestamp {t1:.3f} s is {age:.3f} s old, limit "
                    f"{self.freshness_s} s)"
                )
            time.sleep(0.001)

    # -- motion --------------------------------------------------------------------------------

    def _goal(self, call: str, q: np.ndarray) -> np.ndarray:
        goal = np.asarray(q, dtype=np.float64)
        if goal.shape != (6,) or not np.all(np.isfinite(goal)):
            raise DeviceError(
                f"{self.name}: {call}: need 6 finite joint positions (deg), got {np.asarray(q)!r}"
            )
        return goal

    def _raise_refused(self, call: str, what: str) -> None:
        if self._protective_stopped(call):
            raise ProtectiveStop(
                f"{self.name}: {call}: {self.host} is in protective stop; refused {what}"
            )
        (running,) = self._calls(call, [("control", "isProgramRunning", ())])
        raise DeviceError(
            f"{self.name}: {call}: {self.host} refused {what} (control script running: {running})"
        )

    def _progress(self, call: str) -> tuple[int, bool]:
        """The controller's async operation: (operation id, running)."""
        (status,) = self._calls(call, [("control", "getAsyncOperationProgressEx", ())])
        return status

    def move_to(self, q: np.ndarray, timeout_s: float) -> None:
        """moveJ to ``q`` (deg) at the configured speed; returns at the goal, raises otherwise."""
        goal = self._goal("move_to", q)
        deadline = time.monotonic() + timeout_s
        start = self.state(timeout_s)
        what = f"moveJ to {np.round(goal, 4).tolist()} deg"
        if start.protective_stop:
            raise ProtectiveStop(
                f"{self.name}: move_to: {self.host} is in protective stop; refused {what}"
            )
        before, _ = self._progress("move_to")
        args = (
            np.deg2rad(goal).tolist(),
            math.radians(self.move_speed_deg_s),
            math.radians(self.move_accel_deg_s2),
            True,
        )
        (ok,) = self._calls("move_to", [("control", "moveJ", args)])
        self._commanded_s = time.monotonic()
        if not ok:
            self._raise_refused("move_to", what)
        self._servoing = False
        started = False
        while True:
            operation, running = self._progress("move_to")
            started = started or operation != before
            if started and not running:
                # the reading that ends the move is a package made after the controller said
                # it was done (the receive stream can trail the control one by freshness_s)
                self._commanded_s = time.monotonic()
            reading = self.state(max(deadline - time.monotonic(), self.freshness_s))
            if reading.protective_stop:
                raise ProtectiveStop(
                    f"{self.name}: move_to: protective stop on {self.host} during {what}, "
                    f"at {np.round(reading.q, 3).tolist()} deg"
                )
            if started and not running:
                break
            if time.monotonic() > deadline:
                self._stop_quietly()
                raise DeviceTimeout(
                    f"{self.name}: move_to: {what} on {self.host} not finished within "
                    f"{timeout_s} s (at {np.round(reading.q, 3).tolist()} deg); stopped"
                )
            time.sleep(0.002)
        error = np.abs(reading.q - goal)
        worst = int(np.argmax(error))
        if error[worst] > self.arrival_tolerance_deg:
            raise DeviceError(
                f"{self.name}: move_to: {what} on {self.host} ended with joint "
                f"{self.joints[worst]} at {reading.q[worst]:.4f} deg, goal {goal[worst]:.4f} deg "
                f"(tolerance {self.arrival_tolerance_deg} deg)"
            )

    def servo(self, q: np.ndarray, dt_s: float) -> None:
        """servoJ to ``q`` (deg), to be reached ``dt_s`` from now; does not wait. Raises
        DeviceTimeout when the controller has been silent for ``silence_s``."""
        goal = self._goal("servo", q)
        if not dt_s > 0:
            raise DeviceError(f"{self.name}: servo: dt_s must be > 0, got {dt_s}")
        connected, t, stopped, safety_mode = self._calls(
            "servo",
            [
                ("receive", "isConnected", ()),
                ("receive", "getTimestamp", ()),
                ("receive", "isProtectiveStopped", ()),
                ("receive", "getSafetyMode", ()),
            ],
        )
        if not connected:
            raise self._dropped("servo")
        age = self._freshness.age_s(t, time.monotonic())
        if age > self.silence_s:
            raise self._silent("servo", age)
        if stopped or safety_mode == SAFETY_MODE_PROTECTIVE_STOP:
            raise ProtectiveStop(
                f"{self.name}: servo: {self.host} is in protective stop; refused servoJ to "
                f"{np.round(goal, 4).tolist()} deg"
            )
        args = (
            np.deg2rad(goal).tolist(),
            0.0,
            0.0,
            float(dt_s),
            self.servo_lookahead_s,
            self.servo_gain,
        )
        (ok,) = self._calls("servo", [("control", "servoJ", args)])
        self._commanded_s = time.monotonic()
        if not ok:
            self._raise_refused("servo", f"servoJ to {np.round(goal, 4).tolist()} deg")
        self._servoing = True

    def stop(self) -> None:
        """Leave servo mode and decelerate to standstill (stopJ) within ``stop_timeout_s``; a
        no-op when not connected or already stopped by a protective stop."""
        if not self.connected:
            return
        (connected,) = self._calls("stop", [("receive", "isConnected", ())])
        if not connected:
            raise self._dropped("stop")
        if self._protective_stopped("stop"):
            self._servoing = False
            return
        if self._servoing:
            decel = self.servo_stop_decel_mm_s2 / 1000.0
            (ok,) = self._calls("stop", [("control", "servoStop", (decel,))], self.stop_timeout_s)
            if not ok:
                self._raise_refused("stop", "servoStop")
            self._servoing = False
        decel = math.radians(self.stop_decel_deg_s2)
        self._calls("stop", [("control", "stopJ", (decel, False))], self.stop_timeout_s)

    def _stop_quietly(self) -> None:
        try:
            decel = math.radians(self.stop_decel_deg_s2)
            self._calls("stop", [("control", "stopJ", (decel, False))], self.stop_timeout_s)
        except DeviceError as exc:
            log.warning("%s: stopJ failed: %s", self.name, exc)

    def close(self) -> None:
        """Stop, end ur-rtde's control script and disconnect; safe to call twice.

        The connection is released even when stopping fails; that failure is raised afterwards.
        """
        client = self._client
        if client is None:
            return
        failure: DeviceError | None = None
        try:
            if client.alive and self._calls("close", [("receive", "isConnected", ())])[0]:
                try:
                    self.stop()
                except DeviceError as exc:
                    failure = exc
                if client.alive and self._calls("close", [("control", "isProgramRunning", ())])[0]:
                    self._calls("close", [("control", "stopScript", ())], self.stop_timeout_s)
        except DeviceError as exc:
            failure = failure or exc
        finally:
            self._client = None
            self._servoing = False
            client.close(_CLOSE_TIMEOUT_S)
            log.info("%s: disconnected from %s", self.name, self.host)
        if failure is not None:
            raise failure

    def __enter__(self) -> URArm:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _check_range(name: str, label: str, value: float, low: float, high: float) -> None:
    if not low <= value <= high:
        raise ValueError(f"{name}: {label} = {value} is outside [{low:g}, {high:g}]")
