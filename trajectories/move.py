"""Moves between rest configurations: from where the scanner stands (its measured joints) to
the plan's start, or to park; planned and checked like the plan's approach and retreat.

Both ends must lie within the joint limits and keep the clearance margin. Every leg is a
jerk-limited, time-synchronised rest-to-rest move (ruckig, :func:`trajectories.timing.
point_to_point`, at the planner's share of the velocity and acceleration limits) whose
clearance against the other arm, the lift column, the platform, the floor and the patient
envelope is checked along the whole motion (:func:`trajectories.collision.motion_clearance`,
no body point travelling more than its resolution between checked samples).

Route: the straight joint-space move when it keeps the margin. Otherwise the retract route:
the arms fold to their home postures where the stage stands, the stage (rotary, lift) moves
with the arms folded, and the arms unfold to the goal, each leg checked the same way. When
neither keeps the margin the move is refused with a :class:`~trajectories.errors.
CollisionError` naming, for each route, the leg, the link pair, their clearance and the margin.

Joint values at this module's boundary are the plan's units (rotary deg, lift mm, arm joints
deg, in ``ScannerModel.joint_names`` order); inside, Pinocchio's (rad, m).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from trajectories.collision import Clearance, motion_clearance
from trajectories.errors import CollisionError, JointLimitError, PlanningError
from trajectories.model import ScannerModel
from trajectories.plan import SAMPLE_DT_S
from trajectories.timing import TimedPath, point_to_point, sample

STAND_STILL = 1e-9
"""Largest joint change (rad, m) of a leg that is left out as no motion."""


@dataclass(frozen=True)
class JointMove:
    """A checked, timed move between two rest configurations (plan joint units).

    Attributes:
        target: what it goes to, in words ("the plan's start", "park").
        joint_names: joint order of every configuration (14).
        joint_units: "deg" or "mm" per joint.
        start_q, goal_q: the two rest configurations (14,).
        route: "direct" (one straight joint-space leg) or "retract" (arms fold, stage moves,
            arms unfold).
        legs: (label, start s, end s) of each leg.
        t_s: sample times (M,), s from the start of the move, every ``SAMPLE_DT_S`` within a
            leg and at both ends of each.
        q, qd: positions (M, 14) and velocities (/s) at the samples.
        duration_s: the whole move, s.
        min_clearance_mm: smallest clearance along it, mm.
        min_clearance_at: {"leg", "time_s", "pair"} of that clearance.
        clearance_margin_mm: the margin it was checked against, mm.
        max_speed_share: peak |velocity| / limit per joint (14,).
    """

    target: str
    joint_names: tuple[str, ...]
    joint_units: tuple[str, ...]
    start_q: np.ndarray
    goal_q: np.ndarray
    route: str
    legs: tuple[tuple[str, float, float], ...]
    t_s: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    duration_s: float
    min_clearance_mm: float
    min_clearance_at: dict
    clearance_margin_mm: float
    max_speed_share: np.ndarray

    def summary(self) -> dict:
        """Headline figures (JSON-ready)."""
        return {
            "target": self.target,
            "route": self.route,
            "legs": [label for label, _, _ in self.legs],
            "duration_s": round(self.duration_s, 3),
            "from": np.round(self.start_q, 3).tolist(),
            "to": np.round(self.goal_q, 3).tolist(),
            "min_clearance_mm": round(self.min_clearance_mm, 2),
            "min_clearance_at": self.min_clearance_at,
            "clearance_margin_mm": self.clearance_margin_mm,
            "max_speed_share": round(float(self.max_speed_share.max()), 4),
        }

    def headline(self) -> str:
        """One line: route, duration, the stage's and the arms' changes, minimum clearance."""
        change = self.goal_q - self.start_q
        where = self.min_clearance_at
        legs = " -> ".join(label for label, _, _ in self.legs)
        return (
            f"{self.route} route ({legs}), {self.duration_s:.1f} s: rotary {change[0]:+.1f} deg, "
            f"lift {change[1]:+.1f} mm, arm joints up to {np.abs(change[2:]).max():.1f} deg; "
            f"minimum clearance {self.min_clearance_mm:.1f} mm ({' / '.join(where['pair'])} in "
            f"{where['leg']}; margin {self.clearance_margin_mm:g} mm)"
        )

    def table(self) -> str:
        """The move per joint: from, to, change (fixed-width text)."""
        lines = [f"{'joint':<30}{'from':>10}{'to':>10}{'change':>10}"]
        for name, unit, a, b in zip(
            self.joint_names, self.joint_units, self.start_q, self.goal_q, strict=True
        ):
            lines.append(f"{name + ' (' + unit + ')':<30}{a:>10.2f}{b:>10.2f}{b - a:>+10.2f}")
        return "\n".join(lines)


def park_pose(model: ScannerModel) -> np.ndarray:
    """The park configuration (plan units): rotary 0, lift at its lowest, arms at their home
    postures (``ScannerModel.neutral``; the configuration every plan approaches from).

    Args:
        model: The scanner.
    """
    return model.to_units(model.neutral())


def plan_move(
    model: ScannerModel, start_q: np.ndarray, goal_q: np.ndarray, target: str
) -> JointMove:
    """Plan the move from ``start_q`` to ``goal_q``: direct, or by folding the arms.

    Raises a :class:`~trajectories.errors.PlanningError` naming the joint or link pair, the
    value and the limit when an end is beyond a limit or no route keeps the clearance margin.

    Args:
        model: The scanner.
        start_q: Where the scanner stands (plan units: deg, mm), shape (14,).
        goal_q: Where it goes (plan units), shape (14,).
        target: Name of the goal in messages (for example "start" or "park").
    """
    start = _checked_end(model, start_q, f"move to {target} refused: the scanner stands", "start_q")
    goal = _checked_end(model, goal_q, f"move to {target} refused: the goal", "goal_q")
    margin_m = model.config.obstacles.clearance_margin_mm / 1000.0
    direct = [_leg(model, start, goal, "straight")]
    if direct[0][2].distance_m >= margin_m:
        return _move(model, target, start_q, goal_q, "direct", direct, margin_m)
    folded_start, folded_goal = _folded(model, start), _folded(model, goal)
    route = [
        _leg(model, a, b, label)
        for a, b, label in (
            (start, folded_start, "fold arms"),
            (folded_start, folded_goal, "stage"),
            (folded_goal, goal, "unfold arms"),
        )
        if np.abs(b - a).max() > STAND_STILL
    ]
    worst = min(route, key=lambda leg: leg[2].distance_m)
    if worst[2].distance_m >= margin_m:
        return _move(model, target, start_q, goal_q, "retract", route, margin_m)
    raise CollisionError(
        f"move to {target} refused: the straight move {_too_close(direct[0])}; the retract "
        f"route's {worst[0]} leg {_too_close(worst)}; the clearance margin is "
        f"{margin_m * 1000:g} mm"
    )


def _checked_end(model: ScannerModel, q_units: np.ndarray, what: str, field: str) -> np.ndarray:
    """One end of a move in Pinocchio units, checked for shape, limits and clearance."""
    values = np.asarray(q_units, dtype=np.float64)
    if values.shape != (len(model.joint_names),) or not np.all(np.isfinite(values)):
        raise PlanningError(
            f"{field}: need {len(model.joint_names)} finite joint values "
            f"({', '.join(model.joint_names)}), got {np.asarray(q_units)!r}"
        )
    q = model.from_units(values)
    lower, upper = model.to_units(model.limits.lower), model.to_units(model.limits.upper)
    for k, name in enumerate(model.joint_names):
        if not lower[k] - 1e-6 <= values[k] <= upper[k] + 1e-6:
            unit = "mm" if name == "lift" else "deg"
            raise JointLimitError(
                f"{what} with joint {name} at {values[k]:.2f} {unit}, outside its range "
                f"[{lower[k]:.2f}, {upper[k]:.2f}] {unit}"
            )
    distance, a, b = model.clearance(q)
    margin_m = model.config.obstacles.clearance_margin_mm / 1000.0
    if distance < margin_m:
        raise CollisionError(
            f"{what} with {a} and {b} {distance * 1000:.1f} mm apart, less than the clearance "
            f"margin of {margin_m * 1000:g} mm"
        )
    return q


def _folded(model: ScannerModel, q: np.ndarray) -> np.ndarray:
    """``q`` with both arms at their home postures (rotary and lift kept)."""
    home = model.neutral()
    out = home.copy()
    for name in ("rotary", "lift"):
        out[model.index[name]] = q[model.index[name]]
    return out


def _leg(
    model: ScannerModel, a: np.ndarray, b: np.ndarray, label: str
) -> tuple[str, TimedPath, Clearance]:
    """One jerk-limited rest-to-rest leg, sampled, and its clearance along the whole motion."""
    segment = point_to_point(a, b, model.limits.velocity, model.limits.acceleration, label)
    path = sample(segment, SAMPLE_DT_S)
    clearance = motion_clearance(model, path, lambda t: segment.evaluate(t)[0])
    return label, path, clearance


def _too_close(leg: tuple[str, TimedPath, Clearance]) -> str:
    _, _, c = leg
    return (
        f"brings {c.pair[0]} and {c.pair[1]} to {c.distance_m * 1000:.1f} mm at "
        f"t = {c.time_s:.2f} s"
    )


def _move(
    model: ScannerModel,
    target: str,
    start_q: np.ndarray,
    goal_q: np.ndarray,
    route: str,
    legs: list[tuple[str, TimedPath, Clearance]],
    margin_m: float,
) -> JointMove:
    times, qs, qds, spans, offset = [], [], [], [], 0.0
    for k, (label, path, _) in enumerate(legs):
        keep = slice(0 if k == 0 else 1, None)
        times.append(path.t_s[keep] + offset)
        qs.append(path.q[keep])
        qds.append(path.qd[keep])
        spans.append((label, offset, offset + path.duration_s))
        offset += path.duration_s
    closest = min(range(len(legs)), key=lambda k: legs[k][2].distance_m)
    label, _, clearance = legs[closest]
    qd = np.concatenate(qds)
    vmax = model.limits.velocity
    return JointMove(
        target=target,
        joint_names=model.joint_names,
        joint_units=tuple("mm" if n == "lift" else "deg" for n in model.joint_names),
        start_q=np.asarray(start_q, dtype=np.float64).copy(),
        goal_q=np.asarray(goal_q, dtype=np.float64).copy(),
        route=route,
        legs=tuple(spans),
        t_s=np.concatenate(times),
        q=model.to_units(np.concatenate(qs)),
        qd=model.to_units(qd),
        duration_s=float(offset),
        min_clearance_mm=clearance.distance_m * 1000.0,
        min_clearance_at={
            "leg": label,
            "time_s": round(spans[closest][1] + clearance.time_s, 3),
            "pair": list(clearance.pair),
        },
        clearance_margin_mm=margin_m * 1000.0,
        max_speed_share=np.abs(qd).max(axis=0)[model._order] / vmax[model._order],
    )
