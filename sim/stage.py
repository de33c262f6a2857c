"""A mock lift + rotary stage controller speaking the stage's serial command set over a pty.

The command set is specified in ``scanner/serial_link.py`` (``ID?``, ``POS?``, ``MOVE``,
``SERVO``, ``STOP``); the driver ``scanner.stage.SerialStage`` opens :attr:`MockStage.port`.

Dynamics run in real time (integrated in 1 ms steps whenever the controller is asked or
moving): ``MOVE`` drives each axis to its target with an acceleration-limited (trapezoidal)
velocity profile within the speed and acceleration limits; ``SERVO`` ramps the axis reference
linearly to the set-point over ``dt_s`` (no faster than the speed limit) and the axis follows
the reference with a first-order lag; ``STOP`` decelerates at the acceleration limits. Fault on
request: ``protective_stop_after_servo=N`` puts the stage in protective stop right after the
N-th accepted ``SERVO``; :meth:`MockStage.trigger_protective_stop` does it at any time.
Events: "move", "arrived", "servo", "stop", "stopped", "protective_stop", "refused".
"""

from __future__ import annotations

import math
import time

from sim.pty_device import EventCallback, PtyDevice, Refusal, number, parse_floats

STEP_S = 0.001
"""Integration step of the stage dynamics, s."""

AXES = ("rotary", "lift")
UNITS = ("deg", "mm")
_EPS = 1e-6


def _step_toward(
    x: float, v: float, target: float, vmax: float, amax: float, h: float
) -> tuple[float, float, bool]:
    """One step of an acceleration-limited approach to ``target`` (stops there); (x, v, done)."""
    error = target - x
    if abs(error) <= _EPS and abs(v) <= amax * h:
        return target, 0.0, True
    # the fastest speed at the end of this step from which the axis can still brake to rest at
    # the target: v'^2 / (2 a) + v' h / 2 = |error| - v h / 2 (distance left after the step)
    left = abs(error) - math.copysign(v, error) * h / 2.0
    half = amax * h / 2.0
    speed = -half + math.sqrt(half * half + 2.0 * amax * left) if left > 0.0 else 0.0
    v_goal = math.copysign(min(vmax, speed), error)
    v_new = v + max(-amax * h, min(amax * h, v_goal - v))
    x_new = x + 0.5 * (v + v_new) * h
    if (target - x_new) * error <= 0.0 and abs(v_new) <= 2.0 * amax * h:
        return target, 0.0, True  # reached (or crossed at crawl speed) this step
    return x_new, v_new, False


class MockStage(PtyDevice):
    """The mock stage controller (see the module docstring).

    Args:
        start: initial (rotary deg, lift mm).
        rot_speed_dps: rotary speed limit, deg/s.
        rot_accel_dps2: rotary acceleration limit, deg/s^2.
        lift_speed_mms: lift speed limit, mm/s.
        lift_accel_mms2: lift acceleration limit, mm/s^2.
        rot_limits_deg: rotary travel (low, high), deg.
        lift_limits_mm: lift travel (low, high), mm.
        servo_lag_s: time constant of the set-point following, s.
        protective_stop_after_servo: protective stop right after this many SERVO set-points.
        on_event: ``on_event(name, info)`` for every logged event.
        name: device name.
    """

    MODEL = "MOCKSTAGE"

    def __init__(
        self,
        *,
        start: tuple[float, float] = (0.0, 0.0),
        rot_speed_dps: float = 30.0,
        rot_accel_dps2: float = 30.0,
        lift_speed_mms: float = 100.0,
        lift_accel_mms2: float = 200.0,
        rot_limits_deg: tuple[float, float] = (-360.0, 360.0),
        lift_limits_mm: tuple[float, float] = (0.0, 800.0),
        servo_lag_s: float = 0.02,
        protective_stop_after_servo: int | None = None,
        on_event: EventCallback | None = None,
        name: str = "stage",
    ) -> None:
        super().__init__(name, on_event)
        self.vmax = (rot_speed_dps, lift_speed_mms)
        self.amax = (rot_accel_dps2, lift_accel_mms2)
        self.travel = (rot_limits_deg, lift_limits_mm)
        self.servo_lag_s = servo_lag_s
        self.protective_stop_after_servo = protective_stop_after_servo
        for axis, unit, value, (low, high) in zip(AXES, UNITS, start, self.travel, strict=True):
            if not low <= value <= high:
                raise ValueError(f"start {axis} {value} {unit} outside [{low}, {high}]")
        self._x = [float(start[0]), float(start[1])]
        self._v = [0.0, 0.0]
        self._mode = "idle"  # idle | move | servo | stop
        self._target = list(self._x)
        self._ref = list(self._x)  # servo reference
        self._ramp = [(x, x, 0.0, 0.0) for x in self._x]  # (from, to, t0, t1) per axis
        self._t_sim = time.monotonic()
        self._pstop = False
        self._servo_count = 0

    @classmethod
    def of_scanner(cls, scanner, start, **options) -> MockStage:
        """A stage with the travel, speed and acceleration of ``scanner``'s rotary axis and
        lift (a trajectories.config.ScannerConfig), standing at ``start`` (rotary deg, lift
        mm); ``options`` as for the constructor."""
        rotary, lift = scanner.rotary, scanner.lift
        return cls(
            start=(float(start[0]), float(start[1])),
            rot_limits_deg=tuple(rotary.range_deg),
            lift_limits_mm=tuple(lift.range_mm),
            rot_speed_dps=rotary.max_speed_deg_s,
            rot_accel_dps2=rotary.max_accel_deg_s2,
            lift_speed_mms=lift.max_speed_mm_s,
            lift_accel_mms2=lift.max_accel_mm_s2,
            **options,
        )

    # -- Python-side controls and readings -------------------------------------------------

    @property
    def position(self) -> tuple[float, float]:
        """True (rotary deg, lift mm) now."""
        with self._lock:
            self._advance(time.monotonic())
            return (self._x[0], self._x[1])

    @property
    def moving(self) -> bool:
        with self._lock:
            self._advance(time.monotonic())
            return self._mode != "idle"

    @property
    def protective_stop(self) -> bool:
        with self._lock:
            return self._pstop

    @property
    def servo_count(self) -> int:
        """SERVO set-points accepted since start."""
        with self._lock:
            return self._servo_count

    def trigger_protective_stop(self) -> None:
        """Halt now and latch a protective stop."""
        with self._lock:
            self._advance(time.monotonic())
            self._protective_stop()

    def clear_protective_stop(self) -> None:
        """Unlatch the protective stop (at the controller: there is no host command)."""
        with self._lock:
            self._pstop = False
            self._event("protective_stop_cleared")

    # -- protocol --------------------------------------------------------------------------

    def _handle(self, command: str, args: list[str], now: float) -> str | None:
        self._advance(now)
        if command in ("ID?", "POS?", "STOP") and args:
            raise Refusal("SYNTAX", f"{command} takes no arguments")
        if command == "ID?":
            return f"OK ID? {self.MODEL} {self.VERSION}"
        if command == "POS?":
            rot, lift = self._x
            moving = int(self._mode != "idle")
            t = now - self._t0
            return f"OK POS? {rot:.4f} {lift:.4f} {t:.4f} {int(self._pstop)} {moving}"
        if command == "MOVE":
            target = parse_floats(command, args, 2)
            self._check_travel(target)
            self._check_pstop()
            return self._move(target)
        if command == "SERVO":
            *target, dt_s = parse_floats(command, args, 3)
            self._check_travel(target)
            if not 0.0 < dt_s <= 1.0:
                raise Refusal("RANGE", f"dt {number(dt_s)} s outside (0, 1]")
            self._check_pstop()
            return self._servo(target, dt_s, now)
        if command == "STOP":
            if self._mode != "idle":
                self._mode = "stop"
            self._event("stop")
            return "OK STOP"
        raise Refusal("UNKNOWN", f"unknown command {command}")

    def _check_travel(self, target: list[float]) -> None:
        for axis, unit, value, (low, high) in zip(AXES, UNITS, target, self.travel, strict=True):
            if value < low:
                raise Refusal("RANGE", f"{axis} {number(value)} {unit} below limit {number(low)}")
            if value > high:
                raise Refusal("RANGE", f"{axis} {number(value)} {unit} above limit {number(high)}")

    def _check_pstop(self) -> None:
        if self._pstop:
            raise Refusal("PSTOP", "protective stop")

    def _move(self, target: list[float]) -> str:
        self._target = list(target)
        self._mode = "move"
        duration = 0.0
        for x, goal, vmax, amax in zip(self._x, target, self.vmax, self.amax, strict=True):
            d = abs(goal - x)  # planned duration from rest: trapezoid or triangle
            t = d / vmax + vmax / amax if d >= vmax**2 / amax else 2.0 * math.sqrt(d / amax)
            duration = max(duration, t)
        self._event("move", target=tuple(target), duration_s=duration)
        return f"OK MOVE {duration:.4f}"

    def _servo(self, target: list[float], dt_s: float, now: float) -> str:
        if self._mode != "servo":
            self._ref = list(self._x)
            self._ramp = [(x, x, now, now) for x in self._x]
        self._ramp = [
            (self._ramp_value(i, now), target[i], now, now + dt_s) for i in range(len(AXES))
        ]
        self._mode = "servo"
        self._servo_count += 1
        self._event("servo", target=tuple(target), dt_s=dt_s, count=self._servo_count)
        if self._servo_count == self.protective_stop_after_servo:
            self._protective_stop()
        return "OK SERVO"

    def _ramp_value(self, i: int, t: float) -> float:
        start, end, t0, t1 = self._ramp[i]
        if t >= t1:
            return end
        return start + (end - start) * max(0.0, (t - t0) / (t1 - t0))

    def _protective_stop(self) -> None:
        self._pstop = True
        self._mode = "idle"
        self._v = [0.0, 0.0]
        self._event("protective_stop", position=tuple(self._x))

    # -- dynamics --------------------------------------------------------------------------

    def _advance(self, now: float) -> None:
        while self._mode != "idle" and self._t_sim + STEP_S <= now:
            self._t_sim += STEP_S
            self._step(self._t_sim)
        if self._mode == "idle":
            self._t_sim = now

    def _step(self, t: float) -> None:
        h = STEP_S
        if self._mode == "move":
            done = []
            for i in range(len(AXES)):
                self._x[i], self._v[i], ok = _step_toward(
                    self._x[i], self._v[i], self._target[i], self.vmax[i], self.amax[i], h
                )
                done.append(ok)
            if all(done):
                self._mode = "idle"
                self._event("arrived", position=tuple(self._x))
        elif self._mode == "servo":
            alpha = 1.0 - math.exp(-h / self.servo_lag_s) if self.servo_lag_s > 0 else 1.0
            settled = True
            for i in range(len(AXES)):
                goal = self._ramp_value(i, t)
                step = self.vmax[i] * h
                self._ref[i] += max(-step, min(step, goal - self._ref[i]))
                x_new = self._x[i] + (self._ref[i] - self._x[i]) * alpha
                self._v[i] = (x_new - self._x[i]) / h
                self._x[i] = x_new
                settled &= t >= self._ramp[i][3] and abs(goal - self._x[i]) <= _EPS
            if settled:
                self._x = [self._ramp[i][1] for i in range(len(AXES))]
                self._v = [0.0, 0.0]
                self._mode = "idle"
        elif self._mode == "stop":
            for i in range(len(AXES)):
                v = self._v[i]
                v_new = v - math.copysign(min(abs(v), self.amax[i] * h), v)
                self._x[i] += 0.5 * (v + v_new) * h
                self._v[i] = v_new
            if all(v == 0.0 for v in self._v):
                self._mode = "idle"
                self._event("stopped", position=tuple(self._x))

    def _tick(self, now: float) -> None:
        self._advance(now)

    def _next_wakeup(self, now: float) -> float | None:
        return 0.01 if self._mode != "idle" else None
