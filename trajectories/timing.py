"""Timing: time-optimal traversal of the scan path (toppra) and jerk-limited point-to-point
moves (ruckig), both under the joints' velocity and acceleration limits.

The scan path runs through every view's configuration. Each pass of a reverse spiral is timed
separately (it starts and ends at rest where the sweep turns); within a pass a cubic spline
through the views is parametrised by TOPP-RA on a grid that contains every view, with the
constant-acceleration parametrizer, so each view gets an exact time. Limits are applied at
:data:`LIMIT_SHARE` of their value to absorb the spline's behaviour between grid points.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import toppra
import toppra.algorithm
import toppra.constraint
from ruckig import InputParameter, Result, Ruckig, Trajectory

from trajectories.errors import TimingError

LIMIT_SHARE = 0.99
"""Share of each velocity/acceleration limit given to the planners."""

GRID_PER_VIEW = 4
"""TOPP-RA grid intervals between consecutive views."""

JERK_TIME_S = 0.1
"""Ruckig moves reach full acceleration in this time: max jerk = max accel / JERK_TIME_S."""


@dataclass(frozen=True)
class TimedPath:
    """A joint trajectory sampled in time.

    Attributes:
        t_s: sample times, seconds, starting at 0, (M,).
        q: positions (Pinocchio units), (M, n).
        qd: velocities, (M, n).
        qdd: accelerations, (M, n).
    """

    t_s: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray

    @property
    def duration_s(self) -> float:
        return float(self.t_s[-1])


class _SegmentTrajectory:
    """One rest-to-rest trajectory that can be evaluated at any time."""

    def __init__(self, evaluate, duration: float) -> None:
        self.evaluate = evaluate
        self.duration = duration


def time_pass(
    waypoints: np.ndarray, vmax: np.ndarray, amax: np.ndarray, label: str
) -> tuple[_SegmentTrajectory, np.ndarray]:
    """Time-optimal rest-to-rest traversal of the spline through ``waypoints`` (K, n).

    Returns the trajectory and the time at which it passes each waypoint (K,).
    """
    k = len(waypoints)
    if k == 1:
        q0 = waypoints[0]
        zeros = np.zeros_like(q0)
        return _SegmentTrajectory(lambda t: (q0, zeros, zeros), 0.0), np.zeros(1)
    steps = np.linalg.norm(np.diff(waypoints, axis=0), axis=1)
    if np.any(steps <= 0):
        raise TimingError(f"{label}: two consecutive views share one configuration")
    ss = np.concatenate(([0.0], np.cumsum(steps)))
    path = toppra.SplineInterpolator(ss, waypoints)
    grid = np.concatenate(
        [np.linspace(ss[i], ss[i + 1], GRID_PER_VIEW, endpoint=False) for i in range(k - 1)]
        + [ss[-1:]]
    )
    share = LIMIT_SHARE
    constraints = [
        toppra.constraint.JointVelocityConstraint(np.column_stack((-vmax, vmax)) * share),
        toppra.constraint.JointAccelerationConstraint(np.column_stack((-amax, amax)) * share),
    ]
    instance = toppra.algorithm.TOPPRA(
        constraints, path, gridpoints=grid, parametrizer="ParametrizeConstAccel"
    )
    _, sd_vec, _ = instance.compute_parameterization(0.0, 0.0)
    if sd_vec is None or not np.all(np.isfinite(sd_vec)):
        raise TimingError(f"{label}: no timing satisfies the joint velocity/acceleration limits")
    sd = np.maximum(sd_vec, 0.0)
    ds = np.diff(grid)
    dt = 2.0 * ds / np.maximum(sd[:-1] + sd[1:], 1e-12)
    times = np.concatenate(([0.0], np.cumsum(dt)))
    parametrized = toppra.parametrizer.ParametrizeConstAccel(path, grid, sd)
    view_times = times[::GRID_PER_VIEW]

    def evaluate(t):
        t = np.clip(t, 0.0, parametrized.duration)
        return parametrized.eval(t), parametrized.evald(t), parametrized.evaldd(t)

    return _SegmentTrajectory(evaluate, float(times[-1])), view_times


def point_to_point(
    start: np.ndarray, goal: np.ndarray, vmax: np.ndarray, amax: np.ndarray, label: str
) -> _SegmentTrajectory:
    """Jerk-limited, time-synchronised rest-to-rest move (ruckig, offline).

    Args:
        start: joint positions (n,) at rest, in the joints' units (rad, m).
        goal: joint positions (n,) to come to rest at.
        vmax: per-joint velocity limits (n,), per s; the move uses :data:`LIMIT_SHARE` of them.
        amax: per-joint acceleration limits (n,), per s^2; the same share, reached by the jerk
            in :data:`JERK_TIME_S`.
        label: names the move in a TimingError.
    """
    n = len(start)
    otg = Ruckig(n)
    inp = InputParameter(n)
    inp.current_position = list(start)
    inp.current_velocity = [0.0] * n
    inp.current_acceleration = [0.0] * n
    inp.target_position = list(goal)
    inp.target_velocity = [0.0] * n
    inp.target_acceleration = [0.0] * n
    inp.max_velocity = list(vmax * LIMIT_SHARE)
    inp.max_acceleration = list(amax * LIMIT_SHARE)
    inp.max_jerk = list(amax * LIMIT_SHARE / JERK_TIME_S)
    trajectory = Trajectory(n)
    result = otg.calculate(inp, trajectory)
    if result not in (Result.Working, Result.Finished):
        raise TimingError(f"{label}: ruckig could not plan the move ({result})")

    def evaluate(t):
        if np.ndim(t) == 0:
            p, v, a = trajectory.at_time(float(t))
            return np.array(p), np.array(v), np.array(a)
        samples = [trajectory.at_time(float(x)) for x in np.atleast_1d(t)]
        return tuple(np.array([s[i] for s in samples]) for i in range(3))

    return _SegmentTrajectory(evaluate, float(trajectory.duration))


def sample(segment: _SegmentTrajectory, dt_s: float) -> TimedPath:
    """Samples every ``dt_s`` (and at both ends)."""
    count = max(2, math.ceil(segment.duration / dt_s) + 1)
    t = np.linspace(0.0, segment.duration, count)
    q, qd, qdd = segment.evaluate(t)
    return TimedPath(t, np.atleast_2d(q), np.atleast_2d(qd), np.atleast_2d(qdd))


def rest_to_rest_lower_bound(q_path: np.ndarray, vmax: np.ndarray, amax: np.ndarray) -> float:
    """Shortest possible duration: each joint's path split into monotonic runs, each run
    covered from rest to rest at the joint's limits (trapezoid or triangle profile); the
    slowest joint sets the bound (seconds).

    Args:
        q_path: joint positions along the path (K, n).
        vmax: per-joint velocity limits (n,), per s.
        amax: per-joint acceleration limits (n,), per s^2.
    """
    worst = 0.0
    for j in range(q_path.shape[1]):
        x = q_path[:, j]
        steps = np.diff(x)
        steps = steps[np.abs(steps) > 1e-12]
        if steps.size == 0:
            continue
        runs, current = [], steps[0]
        for step in steps[1:]:
            if np.sign(step) == np.sign(current):
                current += step
            else:
                runs.append(abs(current))
                current = step
        runs.append(abs(current))
        v, a = vmax[j], amax[j]
        total = sum(
            length / v + v / a if length >= v * v / a else 2.0 * math.sqrt(length / a)
            for length in runs
        )
        worst = max(worst, total)
    return worst
