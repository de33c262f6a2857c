"""The lift + rotary stage over serial: :class:`SerialStage` implements ``Arm``.

Joints ("rotary", "lift") in deg and mm. The command set is specified in
``scanner/serial_link.py``: ``POS?`` reads the position, ``MOVE`` starts an
acceleration-limited point-to-point move that the driver follows by polling ``POS?``,
``SERVO`` streams set-points, ``STOP`` decelerates. A protective stop (``pstop`` in ``POS?``,
``ERR ... PSTOP``) is raised as :class:`ProtectiveStop`.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from scanner.hardware import DeviceError, DeviceTimeout, JointState, ProtectiveStop
from scanner.serial_link import DEFAULT_BAUDRATE, Reply, SerialLink, format_number, time_left

JOINTS = ("rotary", "lift")
UNITS = ("deg", "mm")


class SerialStage:
    """The stage controller on a serial port.

    Args:
        port: device path (``/dev/ttyUSB1``) or pyserial URL.
        baudrate: bits per second.
        name: the device's name in error messages.
        timeout_s: timeout of the calls that take none (``servo``, ``stop``), s.
        poll_s: POS? polling period while a move runs, s.
        tolerance: largest (deg, mm) between target and position at which a move has arrived.
        clock: the backend's clock for ``JointState.t_s`` (default ``time.monotonic``); the
            controller's own time stamp of the last reading is :attr:`controller_t_s`.
    """

    joints = JOINTS

    def __init__(
        self,
        port: str,
        baudrate: int = DEFAULT_BAUDRATE,
        name: str = "stage",
        *,
        timeout_s: float = 0.5,
        poll_s: float = 0.01,
        tolerance: tuple[float, float] = (0.01, 0.01),
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.name = name
        self.timeout_s = timeout_s
        self.poll_s = poll_s
        self.tolerance = np.asarray(tolerance, dtype=np.float64)
        self.clock = clock
        self.ident: str | None = None
        self.controller_t_s: float | None = None
        self._link = SerialLink(port, device=name, baudrate=baudrate)

    def connect(self, timeout_s: float) -> None:
        """Open the port and read the controller's identification (``ID?``)."""
        reply = self._call("ID?", timeout_s=timeout_s)
        self.ident = " ".join(reply.fields)

    def state(self, timeout_s: float) -> JointState:
        """The measured (rotary deg, lift mm); raises ProtectiveStop when the stage is in one."""
        reading, _ = self._read(timeout_s)
        if reading.protective_stop:
            raise ProtectiveStop(f"{self.name}: protective stop at q={reading.q.tolist()}")
        return reading

    def move_to(self, q: np.ndarray, timeout_s: float) -> None:
        """Move to ``q`` = (rotary deg, lift mm) and return once there (polling ``POS?``).

        Raises DeviceTimeout (after sending STOP) when the move cannot finish within
        ``timeout_s`` s, ProtectiveStop on a protective stop, DeviceError when the controller
        refuses the target (its travel limits) or stops short of it.
        """
        deadline = time.monotonic() + timeout_s
        target = self._target(q)
        reply = self._call("MOVE", *(format_number(v) for v in target), timeout_s=timeout_s)
        (planned_s,) = self._link.numbers(reply, 1)
        if time.monotonic() + planned_s > deadline:
            self._stop_quietly()
            raise DeviceTimeout(
                f"{self.name}: MOVE to {target.tolist()} needs {planned_s:.3g} s, "
                f"timeout {timeout_s:.3g} s: stopped"
            )
        while True:
            reading, moving = self._read(time_left(deadline))
            if reading.protective_stop:
                raise ProtectiveStop(
                    f"{self.name}: protective stop during MOVE at q={reading.q.tolist()}"
                )
            if not moving:
                error = np.abs(reading.q - target)
                if np.all(error <= self.tolerance):
                    return
                raise DeviceError(
                    f"{self.name}: MOVE to {target.tolist()} ended at {reading.q.tolist()}"
                )
            if time.monotonic() + self.poll_s > deadline:
                self._stop_quietly()
                raise DeviceTimeout(
                    f"{self.name}: MOVE to {target.tolist()} not done within {timeout_s:.3g} s "
                    f"(at {reading.q.tolist()}): stopped"
                )
            time.sleep(self.poll_s)

    def servo(self, q: np.ndarray, dt_s: float) -> None:
        """Stream one set-point ``q`` = (rotary deg, lift mm), to be reached ``dt_s`` s from now."""
        target = self._target(q)
        self._call("SERVO", *(format_number(v) for v in (*target, dt_s)), timeout_s=self.timeout_s)

    def stop(self) -> None:
        """Decelerate to standstill now (and leave streaming mode)."""
        self._call("STOP", timeout_s=self.timeout_s)

    def close(self) -> None:
        """STOP (best effort, when connected) and release the port; safe to call twice."""
        if self._link.is_open:
            self._stop_quietly()
        self._link.close()

    def __enter__(self) -> SerialStage:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    # -- internals -------------------------------------------------------------------------

    def _call(self, command: str, *args: str, timeout_s: float) -> Reply:
        reply = self._link.request(command, *args, timeout_s=timeout_s)
        if not reply.ok:
            error = ProtectiveStop if reply.code == "PSTOP" else DeviceError
            raise self._link.refused(reply, error)
        return reply

    def _read(self, timeout_s: float) -> tuple[JointState, bool]:
        """POS?: the reading (t_s on :attr:`clock`, mid-request) and the moving flag."""
        t_send = self.clock()
        reply = self._call("POS?", timeout_s=timeout_s)
        t_s = 0.5 * (t_send + self.clock())
        rot, lift, t_controller, pstop, moving = self._link.numbers(reply, 5)
        if pstop not in (0.0, 1.0) or moving not in (0.0, 1.0):
            raise DeviceError(f"{self.name}: 'POS?': flags not 0/1: {reply.line!r}")
        self.controller_t_s = t_controller
        return JointState(np.array([rot, lift]), t_s, bool(pstop)), bool(moving)

    def _target(self, q: np.ndarray) -> np.ndarray:
        target = np.asarray(q, dtype=np.float64).reshape(-1)
        if target.shape != (2,) or not np.all(np.isfinite(target)):
            raise ValueError(f"{self.name}: q must be 2 finite values (rotary deg, lift mm): {q}")
        return target

    def _stop_quietly(self) -> None:
        try:
            self.stop()
        except DeviceError:
            pass
