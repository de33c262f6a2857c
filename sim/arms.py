"""Mock arms and stage on a virtual clock: the simulated scanner's moving parts.

A :class:`SimWorld` holds the true joint state of the whole scanner (rotary, lift, six source
and six detector joints, in the plan's joint units) and the virtual time. :class:`MockArm`
drives one joint group of it through the same calls as a real controller: streamed set-points
are ramped over their ``dt`` and followed with a first-order lag plus a little tracking noise;
point-to-point moves are jerk-limited (trajectories.timing's ruckig move); a protective stop
can be injected. Time only passes when the scan sleeps on the :class:`VirtualClock`, so a scan
of half a minute simulates in a fraction of a second.
"""

from __future__ import annotations

import itertools
import math
import threading
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np

from trajectories.model import ScannerModel
from trajectories.timing import point_to_point

STEP_S = 0.001
"""Integration step of the arm dynamics, s."""

GROUPS = {"stage": slice(0, 2), "source_arm": slice(2, 8), "detector_arm": slice(8, 14)}
"""Joint groups of the plan's 14-joint vector."""


class ArmReading(NamedTuple):
    """One reading (the fields of scanner.hardware.JointState)."""

    q: np.ndarray
    t_s: float
    protective_stop: bool


class ArmFault(RuntimeError):
    """A mock controller refused a command; ``protective_stop`` tells which kind."""

    def __init__(self, message: str, protective_stop: bool = False) -> None:
        super().__init__(message)
        self.protective_stop = protective_stop


class SimWorld:
    """The true state of the simulated scanner and its event log.

    Args:
        model: the scanner (joint limits for the jerk-limited moves).
        start_q: initial configuration, plan joint units (14,).
        lag_s: time constant of the arms' set-point tracking, s.
        tracking_noise: standard deviation of the true position about the lagged set-point,
            deg (mm for the lift).
        seed: seed of the tracking noise.
        event_log: a file each event is also appended to as it happens (opened, written and
            closed per event), one line ``sequence,time_s,wall_s,device,event`` (``wall_s``:
            ``time.monotonic()``), so that another process can time the events, also after
            this one was killed.
    """

    def __init__(
        self,
        model: ScannerModel,
        start_q: np.ndarray,
        *,
        lag_s: float = 0.004,
        tracking_noise: float = 0.002,
        seed: int = 0,
        event_log: Path | None = None,
    ) -> None:
        self.model = model
        self.event_log = event_log
        self.t = 0.0
        self.lag_s = lag_s
        self.tracking_noise = tracking_noise
        self.filtered = np.asarray(start_q, dtype=np.float64).copy()
        self.q_true = self.filtered.copy()
        self._ramp_from = self.filtered.copy()
        self._ramp_to = self.filtered.copy()
        self._ramp_t0 = np.zeros(14)
        self._ramp_t1 = np.zeros(14)
        self._moves: dict[str, tuple[float, object]] = {}
        self.protective_stop: dict[str, bool] = dict.fromkeys(GROUPS, False)
        self.exposures = 0
        self.events: list[tuple[int, float, str, str]] = []
        self._seq = itertools.count()
        self._rng = np.random.default_rng(seed)
        self.lock = threading.RLock()
        self.vmax = model.to_units(model.limits.velocity)
        self.amax = model.to_units(model.limits.acceleration)

    def log(self, who: str, what: str) -> None:
        """Append an event (sequence, virtual time, device, event) to the ordered log."""
        with self.lock:
            seq = next(self._seq)
            self.events.append((seq, self.t, who, what))
            if self.event_log is not None:
                line = f"{seq},{self.t:.6f},{time.monotonic():.6f},{who},{what}\n"
                with open(self.event_log, "a", encoding="utf-8") as fh:
                    fh.write(line)

    def command(self, group: str, q: np.ndarray, dt_s: float) -> None:
        """Ramp the group's set-point from where it is to ``q`` over ``dt_s``."""
        idx = GROUPS[group]
        with self.lock:
            self._moves.pop(group, None)
            self._ramp_from[idx] = self._setpoints(np.array([self.t]))[0, idx]
            self._ramp_to[idx] = q
            self._ramp_t0[idx] = self.t
            self._ramp_t1[idx] = self.t + max(dt_s, 0.0)

    def hold(self, group: str) -> None:
        """Stop the group where it is (set-point = present position)."""
        self.command(group, self.filtered[GROUPS[group]].copy(), 0.0)

    def move(self, group: str, goal: np.ndarray) -> float:
        """Start a jerk-limited rest-to-rest move of the group at half its speed and
        acceleration limits (trajectories.timing.point_to_point); returns its duration, s."""
        idx = GROUPS[group]
        goal = np.asarray(goal, dtype=np.float64)
        segment = point_to_point(
            self.filtered[idx].copy(), goal, self.vmax[idx] * 0.5, self.amax[idx] * 0.5, group
        )
        with self.lock:
            self.command(group, goal, 0.0)
            self._moves[group] = (self.t, segment)
        return float(segment.duration)

    def _setpoints(self, times: np.ndarray) -> np.ndarray:
        """The set-points at virtual times ``times`` (n,), (n, 14)."""
        span = np.maximum(self._ramp_t1 - self._ramp_t0, 1e-12)
        w = np.clip((times[:, None] - self._ramp_t0) / span, 0.0, 1.0)
        out = self._ramp_from + w * (self._ramp_to - self._ramp_from)
        for group, (t0, segment) in self._moves.items():
            for row, t in zip(out, times, strict=True):
                row[GROUPS[group]] = segment.evaluate(min(t - t0, segment.duration))[0]
        return out

    def advance(self, t_s: float) -> None:
        """Integrate the arms' tracking up to virtual time ``t_s`` (steps of at most
        :data:`STEP_S`, the set-points of all steps computed at once)."""
        with self.lock:
            steps = math.ceil((t_s - self.t) / STEP_S - 1e-9)
            if steps <= 0:
                return
            h = (t_s - self.t) / steps
            alpha = 1.0 - math.exp(-h / self.lag_s) if self.lag_s > 0 else 1.0
            times = np.empty(steps)
            for k in range(steps):  # the clock's own sum, step by step
                self.t += h
                times[k] = self.t
            for setpoint in self._setpoints(times):
                self.filtered += alpha * (setpoint - self.filtered)
            self.q_true = self.filtered + self._rng.normal(0.0, self.tracking_noise, 14)


class VirtualClock:
    """Virtual time of a :class:`SimWorld`: sleeping advances the world."""

    def __init__(self, world: SimWorld) -> None:
        self.world = world

    def now(self) -> float:
        return self.world.t

    def sleep_until(self, t_s: float) -> None:
        self.world.advance(t_s)


class MockArm:
    """One joint group of a :class:`SimWorld`, driven like a robot controller.

    ``protective_stop_after`` (exposures) injects a protective stop at the first streamed
    set-point after that many exposures have been delivered.
    """

    def __init__(
        self,
        world: SimWorld,
        group: str,
        joints: tuple[str, ...],
        *,
        arrival_tolerance: float = 0.01,
        protective_stop_after: int | None = None,
    ) -> None:
        self.world = world
        self.name = group
        self.joints = joints
        self._idx = GROUPS[group]
        self.arrival_tolerance = arrival_tolerance
        self.protective_stop_after = protective_stop_after
        self.connected = False

    def _check(self, call: str) -> None:
        if not self.connected:
            raise ArmFault(f"{self.name}.{call}: not connected")
        if self.world.protective_stop[self.name]:
            raise ArmFault(f"{self.name}.{call}: arm is in protective stop", True)

    def connect(self, timeout_s: float) -> None:
        self.connected = True
        self.world.log(self.name, "connect")

    def state(self, timeout_s: float) -> ArmReading:
        if not self.connected:
            raise ArmFault(f"{self.name}.state: not connected")
        with self.world.lock:
            return ArmReading(
                self.world.q_true[self._idx].copy(),
                self.world.t,
                self.world.protective_stop[self.name],
            )

    def move_to(self, q: np.ndarray, timeout_s: float) -> None:
        self._check("move_to")
        duration = self.world.move(self.name, np.asarray(q, dtype=np.float64))
        if duration > timeout_s:
            self.world.hold(self.name)
            raise ArmFault(f"{self.name}.move_to: the move takes {duration:.1f} s > {timeout_s} s")
        self.world.advance(self.world.t + duration + 5 * self.world.lag_s)
        error = np.abs(self.world.filtered[self._idx] - q).max()
        if error > self.arrival_tolerance:
            raise ArmFault(f"{self.name}.move_to: {error:.3f} from the goal after the move")

    def servo(self, q: np.ndarray, dt_s: float) -> None:
        self._check("servo")
        if (
            self.protective_stop_after is not None
            and self.world.exposures >= self.protective_stop_after
        ):
            self.protective_stop_after = None
            with self.world.lock:
                self.world.protective_stop[self.name] = True
                self.world.hold(self.name)
            self.world.log(self.name, "protective_stop")
            raise ArmFault(f"{self.name}.servo: protective stop (injected fault)", True)
        self.world.command(self.name, np.asarray(q, dtype=np.float64), dt_s)

    def stop(self) -> None:
        self.world.hold(self.name)
        self.world.log(self.name, "stop")

    def close(self) -> None:
        if self.connected:
            self.stop()
        self.connected = False
