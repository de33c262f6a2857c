"""Inverse kinematics of both tools at once: damped least squares on Pinocchio Jacobians.

The task stacks the 6-D errors of the focal-spot frame and the panel-centre frame (local
frames, ``log6``); the 14 joints solve it by weighted damped least squares, so cheap axes
(rotary, lift) move before the arms, and the remaining freedom (14 - 12 = 2) pulls toward a
rest posture in the task's null space: away from joint limits and toward the arms' collision-
free home postures.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from trajectories.model import ScannerModel


@dataclass(frozen=True)
class IKResult:
    """Joint solution and residual pose errors of both tools.

    Attributes:
        q: joint configuration (Pinocchio units).
        position_error_m: residual translation error of (source, detector), metres.
        angle_error_rad: residual rotation error of (source, detector), radians.
        iterations: iterations used.
        converged: both errors below the tolerances.
    """

    q: np.ndarray
    position_error_m: tuple[float, float]
    angle_error_rad: tuple[float, float]
    iterations: int
    converged: bool


def _errors(model: ScannerModel, q: np.ndarray, targets: tuple[pin.SE3, pin.SE3]):
    pin.computeJointJacobians(model.model, model.data, q)
    pin.updateFramePlacements(model.model, model.data)
    errors, jacobians = [], []
    for frame, target in zip((model.source_frame, model.detector_frame), targets, strict=True):
        current = model.data.oMf[frame]
        errors.append(pin.log6(current.actInv(target)).vector)
        jacobians.append(
            pin.getFrameJacobian(model.model, model.data, frame, pin.ReferenceFrame.LOCAL)
        )
    return np.concatenate(errors), np.vstack(jacobians)


def solve_ik(
    model: ScannerModel,
    q_start: np.ndarray,
    source_target: pin.SE3,
    detector_target: pin.SE3,
    q_rest: np.ndarray,
    *,
    joint_weights: np.ndarray | None = None,
    tolerance_m: float = 1e-7,
    tolerance_rad: float = 1e-7,
    damping: float = 1e-6,
    rest_gain: float = 0.2,
    max_iterations: int = 60,
) -> IKResult:
    """Move ``q_start`` until both tool frames reach their targets.

    Args:
        model: the scanner.
        q_start: initial configuration (continue from the previous view for continuity).
        source_target, detector_target: desired world poses of the two tool frames (metres).
        q_rest: posture preferred in the null space.
        joint_weights: cost of moving each joint (larger moves less); default: rotary and lift
            cheap, arms dear.
        tolerance_m, tolerance_rad: convergence thresholds on both tools' errors.
        damping: Levenberg damping of the least-squares step.
        rest_gain: share of the distance to ``q_rest`` recovered per iteration in the null space.
        max_iterations: give up after this many steps (``converged`` False).
    """
    if joint_weights is None:
        joint_weights = np.ones(model.model.nv) * 10.0
        joint_weights[model.index["rotary"]] = 0.1
        joint_weights[model.index["lift"]] = 0.1
    w_inv = 1.0 / np.asarray(joint_weights, dtype=np.float64)
    targets = (source_target, detector_target)
    q = np.array(q_start, dtype=np.float64)
    identity = np.eye(model.model.nv)
    for iteration in range(1, max_iterations + 1):
        error, J = _errors(model, q, targets)
        pos = (np.linalg.norm(error[:3]), np.linalg.norm(error[6:9]))
        ang = (np.linalg.norm(error[3:6]), np.linalg.norm(error[9:12]))
        if max(pos) < tolerance_m and max(ang) < tolerance_rad:
            return IKResult(q, pos, ang, iteration - 1, True)
        JW = J * w_inv
        gram = JW @ J.T
        step = JW.T @ np.linalg.solve(gram + damping * np.eye(len(gram)), error)
        # the rest posture moves only within the task's null space: an exact (undamped)
        # projector, so it never leaks into the tools' poses
        null = identity - JW.T @ np.linalg.pinv(gram) @ J
        step += null @ (rest_gain * (q_rest - q))
        q = pin.integrate(model.model, q, step)
    error, _ = _errors(model, q, targets)
    pos = (np.linalg.norm(error[:3]), np.linalg.norm(error[6:9]))
    ang = (np.linalg.norm(error[3:6]), np.linalg.norm(error[9:12]))
    return IKResult(
        q, pos, ang, max_iterations, max(pos) < tolerance_m and max(ang) < tolerance_rad
    )
