"""Plan a scan: protocol views -> tool poses -> joint configurations -> checked, timed motion.

1. The protocol's views (recon.geometry) give each view's focal-spot pose (beam along the
   principal ray, x along e_u) and panel pose (centre, x = e_u, y = e_v, z toward the source).
2. Damped least-squares IK places both tools, continuing from the previous view, with the
   rotary at the view's angle, the lift at the view's height and the arms at home as the rest
   posture (trajectories.ik). Every view is checked for reach, joint limits and continuity.
3. Each pass is timed time-optimally (toppra); approach from home and retreat to home are
   jerk-limited moves (ruckig); clearance is checked along all of it (trajectories.collision).

Everything a :class:`Plan` holds is in mm, degrees and seconds; nothing is written unless the
whole plan is valid.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pinocchio as pin

from recon.config import ScanProtocol
from recon.geometry import DetectorSpec, Geometry, View
from recon.rtk_xml import write_rtk_geometry
from trajectories.arms import ARMS
from trajectories.collision import RESOLUTION_M, motion_clearance
from trajectories.errors import (
    CollisionError,
    ContinuityError,
    JointLimitError,
    PlanningError,
    UnreachableError,
)
from trajectories.ik import solve_ik
from trajectories.model import ScannerModel
from trajectories.timing import (
    TimedPath,
    point_to_point,
    rest_to_rest_lower_bound,
    sample,
    time_pass,
)

MAX_ARM_STEP_DEG = 30.0
"""Largest change of an arm joint between consecutive views; more means a branch change."""

POSE_TOLERANCE = (1e-7, 1e-7)
"""IK convergence: metres and radians on both tools."""

SAMPLE_DT_S = 0.02
"""Time step of the stored joint trajectory."""


@dataclass(frozen=True)
class Plan:
    """A checked, timed scan.

    Attributes:
        protocol: the protocol's name.
        joint_names: joint order of ``q`` (rotary, lift, 6 source, 6 detector).
        joint_units: "deg" or "mm" per joint.
        t_s: sample times (M,), seconds from the start of the approach.
        q, qd, qdd: positions, velocities (/s) and accelerations (/s^2), (M, 14), joint units.
        phases: name -> (start, end) seconds for "approach", "scan", "retreat".
        view_times_s: when each view is reached (N,).
        view_q: joint configuration of each view (N, 14), joint units.
        desired, achieved: the protocol's views and the views the configurations realise.
        pose_error_mm, pose_error_deg: per view, (source, detector) (N, 2).
        view_clearance_mm: smallest clearance at each view (N,).
        min_clearance_mm, min_clearance_at: along the whole motion and where
            ({"phase", "time_s", "pair"}).
        clearance_margin_mm: the margin it was checked against.
        duration_s, scan_duration_s, lower_bound_s: total, scan, and the scan's lower bound.
        max_speed_share: peak |velocity| / limit per joint over the whole motion (14,).
        max_accel_share: peak |acceleration| / limit per joint (14,).
        plan_s: wall time spent planning.
    """

    protocol: str
    joint_names: tuple[str, ...]
    joint_units: tuple[str, ...]
    t_s: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    phases: dict[str, tuple[float, float]]
    view_times_s: np.ndarray
    view_q: np.ndarray
    desired: Geometry
    achieved: Geometry
    pose_error_mm: np.ndarray
    pose_error_deg: np.ndarray
    view_clearance_mm: np.ndarray
    min_clearance_mm: float
    min_clearance_at: dict
    clearance_margin_mm: float
    duration_s: float
    scan_duration_s: float
    lower_bound_s: float
    max_speed_share: np.ndarray
    max_accel_share: np.ndarray
    plan_s: float

    def summary(self) -> dict:
        """Headline figures (JSON-ready)."""
        worst = int(np.argmax(self.max_speed_share))
        return {
            "protocol": self.protocol,
            "views": len(self.desired),
            "duration_s": round(self.duration_s, 3),
            "scan_duration_s": round(self.scan_duration_s, 3),
            "lower_bound_s": round(self.lower_bound_s, 3),
            "duration_ratio": round(self.scan_duration_s / self.lower_bound_s, 4)
            if self.lower_bound_s > 0
            else None,
            "min_clearance_mm": round(self.min_clearance_mm, 2),
            "min_clearance_at": self.min_clearance_at,
            "clearance_margin_mm": self.clearance_margin_mm,
            "max_pose_error_mm": float(self.pose_error_mm.max()),
            "max_pose_error_deg": float(self.pose_error_deg.max()),
            "max_speed_share": float(self.max_speed_share[worst]),
            "max_speed_joint": self.joint_names[worst],
            "max_accel_share": float(self.max_accel_share.max()),
            "plan_s": round(self.plan_s, 3),
        }

    def save(self, folder: str | Path) -> list[Path]:
        """Write the plan into ``folder``: trajectory, views, geometry, collision report, summary.

        Args:
            folder: Output folder; must not exist.

        Returns:
            The files written.
        """
        folder = Path(folder)
        if folder.exists():
            raise FileExistsError(f"{folder} exists: a plan is never written over another")
        tmp = folder.with_name(folder.name + ".partial")
        tmp.mkdir(parents=True)
        np.savez_compressed(
            tmp / "trajectory.npz",
            t_s=self.t_s,
            q=self.q,
            qd=self.qd,
            qdd=self.qdd,
            joint_names=np.array(self.joint_names),
            joint_units=np.array(self.joint_units),
            view_times_s=self.view_times_s,
            view_q=self.view_q,
        )
        header = (
            ["view", "time_s"]
            + [
                f"{role}_{axis}_mm"
                for kind in ("desired", "achieved")
                for role in ("source", "detector")
                for axis in (f"{kind}_x", f"{kind}_y", f"{kind}_z")
            ]
            + [
                "source_error_mm",
                "detector_error_mm",
                "source_error_deg",
                "detector_error_deg",
                "clearance_mm",
            ]
        )
        rows = []
        for i, (want, got) in enumerate(zip(self.desired, self.achieved, strict=True)):
            values = [i, self.view_times_s[i]]
            for view in (want, got):
                values += [*view.source_mm, *view.detector_center_mm]
            values += [*self.pose_error_mm[i], *self.pose_error_deg[i], self.view_clearance_mm[i]]
            rows.append(",".join(f"{v:.6g}" if isinstance(v, float) else str(v) for v in values))
        (tmp / "views.csv").write_text(
            ",".join(header) + "\n" + "\n".join(rows) + "\n", encoding="utf-8"
        )
        write_rtk_geometry(tmp / "geometry.xml", self.achieved)
        report = {
            "clearance_margin_mm": self.clearance_margin_mm,
            "resolution_mm": RESOLUTION_M * 1000,
            "min_clearance_mm": self.min_clearance_mm,
            "where": self.min_clearance_at,
            "view_clearance_mm": self.view_clearance_mm.round(3).tolist(),
        }
        (tmp / "collision_report.json").write_text(json.dumps(report, indent=2), encoding="utf-8")
        (tmp / "summary.json").write_text(json.dumps(self.summary(), indent=2), encoding="utf-8")
        tmp.rename(folder)
        return sorted(folder.iterdir())


def tool_targets(view: View) -> tuple[pin.SE3, pin.SE3]:
    """Desired focal-spot and panel-centre poses (metres) of one view."""
    normal = view.normal
    e_u = view.e_u
    source = pin.SE3(np.column_stack((e_u, np.cross(normal, e_u), normal)), view.source_mm / 1000.0)
    detector = pin.SE3(
        np.column_stack((e_u, view.e_v, np.cross(e_u, view.e_v))), view.detector_center_mm / 1000.0
    )
    return source, detector


def view_at(model: ScannerModel, q_units: np.ndarray, panel: DetectorSpec) -> View:
    """The view a joint configuration realises: ``q_units`` in the plan's joint units (rotary
    deg, lift mm, arm joints deg), the panel read out as ``panel``."""
    return _view(model, model.from_units(q_units), panel)


def _view(model: ScannerModel, q: np.ndarray, panel: DetectorSpec) -> View:
    source, detector = model.tool_poses(q)
    rot = detector.rotation
    return View.from_center(
        source.translation * 1000.0, detector.translation * 1000.0, rot[:, 0], rot[:, 1], panel
    )


def _panel(view: View) -> DetectorSpec:
    return DetectorSpec(rows=view.rows, cols=view.cols, pixel_pitch_mm=view.pitch_u_mm)


def _check_panel(model: ScannerModel, protocol: ScanProtocol) -> None:
    physical = model.config.panel.pixels
    asked = protocol.detector
    for what, a, b in (
        ("width", asked.width_mm, physical.width_mm),
        ("height", asked.height_mm, physical.height_mm),
    ):
        if abs(a - b) > 1.0:
            raise PlanningError(
                f"protocol {protocol.name}: detector {what} {a:.1f} mm differs from the "
                f"scanner's panel ({b:.1f} mm); bin the panel's pixels instead"
            )


def _joint_label(model: ScannerModel, name: str, value: float) -> str:
    return f"{value * 1000:.1f} mm" if name == "lift" else f"{math.degrees(value):.2f} deg"


def _solve_views(model: ScannerModel, geometry: Geometry, progress) -> np.ndarray:
    q_home = model.neutral()
    lift = model.index["lift"]
    rotary = model.index["rotary"]
    q_zero_lift = q_home.copy()
    q_zero_lift[lift] = 0.0
    tool_height = model.tool_poses(q_zero_lift)[0].translation[2]
    lo, hi = model.limits.lower, model.limits.upper
    angles = _rotary_angles(geometry, lo[rotary], hi[rotary])
    solutions = []
    q_prev = None
    for i, (view, angle) in enumerate(zip(geometry, angles, strict=True)):
        source_target, detector_target = tool_targets(view)
        rest = q_home.copy()
        rest[rotary] = angle
        rest[lift] = source_target.translation[2] - tool_height
        start = rest if q_prev is None else q_prev
        result = solve_ik(
            model,
            start,
            source_target,
            detector_target,
            rest,
            tolerance_m=POSE_TOLERANCE[0],
            tolerance_rad=POSE_TOLERANCE[1],
        )
        if not result.converged:
            _raise_unreachable(model, i, result, source_target, detector_target)
        q = result.q
        for name, k in model.index.items():
            if not lo[k] - 1e-9 <= q[k] <= hi[k] + 1e-9:
                low, high = (_joint_label(model, name, x) for x in (lo[k], hi[k]))
                raise JointLimitError(
                    f"view {i}: joint {name} = {_joint_label(model, name, q[k])} is outside its "
                    f"range [{low}, {high}]"
                )
        if q_prev is not None:
            for name, k in model.index.items():
                if name in ("rotary", "lift"):
                    continue
                step = abs(math.degrees(q[k] - q_prev[k]))
                if step > MAX_ARM_STEP_DEG:
                    raise ContinuityError(
                        f"view {i}: joint {name} jumps {step:.1f} deg from view {i - 1} "
                        f"(limit {MAX_ARM_STEP_DEG:g} deg): the IK changed branch"
                    )
        solutions.append(q)
        q_prev = q
        if progress is not None:
            progress(i + 1, len(geometry))
    return np.array(solutions)


def _rotary_angles(geometry: Geometry, lower: float, upper: float) -> np.ndarray:
    """The rotary angle (radians) that turns the source to each view: the views' azimuths
    unwrapped along the scan, shifted by whole turns to fit the rotary's range with the
    start nearest zero (when no shift fits, the nearest-zero start is kept and the joint
    limit check names the view)."""
    sources = np.asarray(geometry.sources_mm)
    angles = np.unwrap(np.arctan2(sources[:, 0], -sources[:, 1]))
    turns = np.arange(-3, 4) * 2 * math.pi
    fits = [t for t in turns if angles.min() + t >= lower and angles.max() + t <= upper]
    if not fits:
        fits = list(turns)
    return angles + min(fits, key=lambda t: abs(angles[0] + t))


def _raise_unreachable(model, i, result, source_target, detector_target) -> None:
    errors = result.position_error_m
    role = "source" if errors[0] >= errors[1] else "detector"
    target = source_target if role == "source" else detector_target
    arm = model.config.source_arm if role == "source" else model.config.detector_arm
    spec = ARMS[arm.model]
    raise UnreachableError(
        f"view {i}: the {role} arm ({arm.model}, reach {spec.reach_m * 1000:.0f} mm plus its "
        f"tool) cannot place its tool at {np.round(target.translation * 1000, 1).tolist()} mm: "
        f"residual {max(errors) * 1000:.2f} mm, {math.degrees(max(result.angle_error_rad)):.3f} "
        f"deg after {result.iterations} iterations"
    )


def _passes(protocol: ScanProtocol, n: int) -> list[tuple[int, int]]:
    """(first, last) view indices of each pass; between passes the scanner steps from rest to
    rest (the sweep turns there)."""
    if protocol.orbit.kind == "static":
        return []
    per = n // protocol.orbit.passes
    return [(k * per, (k + 1) * per - 1) for k in range(protocol.orbit.passes)]


def plan_scan(
    model: ScannerModel,
    protocol: ScanProtocol,
    progress: Callable[[int, int], None] | None = None,
) -> Plan:
    """Plan ``protocol`` on ``model``: IK per view, collision check, timed trajectory.

    Raises a :class:`~trajectories.errors.PlanningError` naming the view, joint or link pair
    and the limit when it cannot be done safely.

    Args:
        model: The scanner.
        protocol: The scan protocol (orbit, panel, timing).
        progress: Called with (views solved, views in all) during inverse kinematics.
    """
    started = time.perf_counter()
    _check_panel(model, protocol)
    desired = protocol.orbit.geometry(protocol.detector)
    view_q = _solve_views(model, desired, progress)
    vmax, amax = model.limits.velocity, model.limits.acceleration
    margin_m = model.config.obstacles.clearance_margin_mm / 1000.0

    view_clearance = np.array([model.clearance(q)[0] for q in view_q])
    worst = int(np.argmin(view_clearance))
    if view_clearance[worst] < margin_m:
        d, a, b = model.clearance(view_q[worst])
        raise CollisionError(
            f"view {worst}: {a} and {b} are {d * 1000:.1f} mm apart, less than the clearance "
            f"margin of {margin_m * 1000:g} mm"
        )

    home = model.neutral()
    segments = [("approach", point_to_point(home, view_q[0], vmax, amax, "approach"), None)]
    view_times = np.zeros(len(view_q))
    offset = segments[0][1].duration
    for k, (first, last) in enumerate(_passes(protocol, len(view_q))):
        if k:
            turn = point_to_point(view_q[first - 1], view_q[first], vmax, amax, f"turn {k}")
            segments.append((f"turn {k}", turn, None))
            offset += turn.duration
        segment, times = time_pass(view_q[first : last + 1], vmax, amax, f"pass {k}")
        view_times[first : last + 1] = offset + times
        segments.append((f"pass {k}", segment, (first, last)))
        offset += segment.duration
    if protocol.orbit.kind == "static":
        view_times[:] = offset
    segments.append(("retreat", point_to_point(view_q[-1], home, vmax, amax, "retreat"), None))

    paths, clearances, start = [], [], 0.0
    for label, segment, _ in segments:
        path = sample(segment, SAMPLE_DT_S)
        path = TimedPath(path.t_s + start, path.q, path.qd, path.qdd)
        clearance = motion_clearance(
            model,
            TimedPath(path.t_s - start, path.q, path.qd, path.qdd),
            lambda t, s=segment: s.evaluate(t)[0],
        )
        if clearance.distance_m < margin_m:
            raise CollisionError(
                f"{label} at t = {start + clearance.time_s:.2f} s: {clearance.pair[0]} and "
                f"{clearance.pair[1]} are {clearance.distance_m * 1000:.1f} mm apart, less than "
                f"the clearance margin of {margin_m * 1000:g} mm"
            )
        clearances.append((clearance, label, start))
        paths.append(path)
        start += segment.duration
    t = np.concatenate([p.t_s if k == 0 else p.t_s[1:] for k, p in enumerate(paths)])
    q = np.concatenate([p.q if k == 0 else p.q[1:] for k, p in enumerate(paths)])
    qd = np.concatenate([p.qd if k == 0 else p.qd[1:] for k, p in enumerate(paths)])
    qdd = np.concatenate([p.qdd if k == 0 else p.qdd[1:] for k, p in enumerate(paths)])

    achieved = Geometry(
        [_view(model, qv, _panel(view)) for qv, view in zip(view_q, desired, strict=True)]
    )
    pose_mm, pose_deg = _pose_errors(model, view_q, desired)
    closest, phase, phase_start = min(clearances, key=lambda c: c[0].distance_m)
    scan_start = segments[0][1].duration
    scan_end = start - segments[-1][1].duration
    lower = rest_to_rest_lower_bound(view_q, vmax, amax)
    return Plan(
        protocol=protocol.name,
        joint_names=model.joint_names,
        joint_units=tuple("mm" if n == "lift" else "deg" for n in model.joint_names),
        t_s=t,
        q=model.to_units(q),
        qd=model.to_units(qd),
        qdd=model.to_units(qdd),
        phases={
            "approach": (0.0, scan_start),
            "scan": (scan_start, scan_end),
            "retreat": (scan_end, start),
        },
        view_times_s=view_times,
        view_q=model.to_units(view_q),
        desired=desired,
        achieved=achieved,
        pose_error_mm=pose_mm,
        pose_error_deg=pose_deg,
        view_clearance_mm=view_clearance * 1000.0,
        min_clearance_mm=closest.distance_m * 1000.0,
        min_clearance_at={
            "phase": phase,
            "time_s": round(phase_start + closest.time_s, 3),
            "pair": list(closest.pair),
        },
        clearance_margin_mm=margin_m * 1000.0,
        duration_s=float(start),
        scan_duration_s=float(scan_end - scan_start),
        lower_bound_s=lower,
        max_speed_share=np.abs(qd).max(axis=0)[model._order] / vmax[model._order],
        max_accel_share=np.abs(qdd).max(axis=0)[model._order] / amax[model._order],
        plan_s=time.perf_counter() - started,
    )


def _pose_errors(model: ScannerModel, view_q: np.ndarray, desired: Geometry):
    mm = np.zeros((len(view_q), 2))
    deg = np.zeros((len(view_q), 2))
    for i, (q, view) in enumerate(zip(view_q, desired, strict=True)):
        for k, (got, want) in enumerate(zip(model.tool_poses(q), tool_targets(view), strict=True)):
            delta = got.actInv(want)
            mm[i, k] = np.linalg.norm(delta.translation) * 1000.0
            deg[i, k] = math.degrees(np.linalg.norm(pin.log3(delta.rotation)))
    return mm, deg
