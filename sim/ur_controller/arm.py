"""The fake controller's arm: a UR5e's forward kinematics (nominal DH) and joint dynamics.

Joint dynamics: the six joints start at ``--home-deg``; moveJ follows a synchronous
trapezoidal profile (leading axis at the requested speed and acceleration, rad/s, rad/s^2);
servoJ targets are followed with a first-order lag (``--servo-lag-s``, 4 ms) under the joint
speed limit; stops decelerate the leading axis at the requested rate with the others scaled to
stop together. ``actual_q`` and ``timestamp`` advance in real time in 2 ms steps.
``actual_TCP_pose``/``target_TCP_pose`` are the forward kinematics of a UR5e (nominal DH).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

CONTROL_PERIOD_S = 0.002
"""The controller's real-time cycle (500 Hz)."""

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


def forward_kinematics(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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


class Joints:
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
