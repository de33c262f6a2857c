"""What the tracker knows before it looks at a frame: the kinematic prediction (the KPM's
constant velocity), the patellofemoral prior and the depth prior
(docs/algorithms/registration.md).

A prior is a function of the body's pose whose squared norm is its cost in NCC units (each
term scaled, so a least-squares residual stays smooth at zero).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from scipy.spatial.transform import Rotation

from recon.geometry import View
from registration.se3 import twist_exp, twist_of, twist_size
from registration.settings import Settings

Prior = Callable[[np.ndarray], np.ndarray]
"""A prior: pose 4x4 (mm) -> its terms, whose squared norm is its cost."""

MAX_KPM_STEP = (25.0, 25.0)
"""A frame-to-frame motion beyond (mm, deg) is not extrapolated (it is a failure, not motion)."""

KPM_LAMBDA = np.arange(-1.5, 2.51, 0.25)
"""The KPM's scan along the kinematic direction, in steps of the last motion: from reversing
it one and a half times to repeating it two and a half times (then Brent about the best)."""


JOINT_SCAN_DEG = np.arange(-45.0, 45.1, 3.0)
"""The search for a lost body along its motion relative to its partner in the joint: turns
about the screw of that motion (deg), from the last frame's relative pose."""
MIN_JOINT_TURN_DEG = 2.0
"""A relative motion that turned less than this (deg) sets no screw (its axis is noise)."""


def joint_screw(relative: list[np.ndarray]) -> np.ndarray | None:
    """The screw a body moves along relative to its partner in the joint, from its poses in
    the partner's frame (oldest first, 4x4 mm): the twist from the one that turned most from
    the last to the last, scaled to a turn of 1 rad (exponential coordinates, rad and mm a
    rad; ``relative[-1] @ twist_exp(theta * screw)`` turns on by ``theta``); None when none
    turned :data:`MIN_JOINT_TURN_DEG`.

    Examples:
        Flexion about a fixed axis 40 mm from the body's origin, in three steps:

        >>> axis = np.array([[1.0, 0, 0, 0], [0, 1, 0, 40], [0, 0, 1, 0], [0, 0, 0, 1]])
        >>> bent = [axis @ twist_exp(np.array([a, 0, 0, 0, 0, 0])) @ np.linalg.inv(axis)
        ...         for a in (0.0, 0.1, 0.3)]
        >>> np.round(joint_screw(bent), 6).tolist()
        [1.0, 0.0, 0.0, 0.0, 0.0, -40.0]
    """
    last = relative[-1]
    turns = [Rotation.from_matrix((np.linalg.inv(T) @ last)[:3, :3]).magnitude() for T in relative]
    k = int(np.argmax(turns))
    if math.degrees(turns[k]) < MIN_JOINT_TURN_DEG:
        return None
    return twist_of(relative[k], last) / turns[k]


def carried_pose(name: str, carrier: str | None, poses: dict[str, np.ndarray]) -> np.ndarray:
    """The pose of body ``name`` in its ``carrier``'s frame (registration.roles.carriers: the
    patella's is the femur's) when ``poses`` holds it, else in the world, 4x4 (mm)."""
    if carrier not in poses:
        return poses[name]
    return np.linalg.inv(poses[carrier]) @ poses[name]


def carrier_pose(carrier: str | None, poses: dict[str, np.ndarray]) -> np.ndarray:
    """The pose of the body ``carrier`` in ``poses``, else the identity, 4x4 (mm)."""
    return poses[carrier] if carrier in poses else np.eye(4)


def kinematic_twist(
    T_before: np.ndarray, T_last: np.ndarray, center_mm: np.ndarray
) -> np.ndarray | None:
    """The last frame-to-frame motion in the body's frame as exponential coordinates
    ``(rotation vector rad, v mm)`` (``T_last = T_before exp(xi)``), or None when it is too
    large to be motion (:data:`MAX_KPM_STEP`, measured at the body's reference centroid
    ``center_mm``)."""
    xi = twist_of(T_before, T_last)
    c = np.append(center_mm, 1.0)
    step_mm = np.linalg.norm((T_last @ c - T_before @ c)[:3])
    if step_mm > MAX_KPM_STEP[0] or math.degrees(np.linalg.norm(xi[:3])) > MAX_KPM_STEP[1]:
        return None
    return xi


def predict(
    T_before: np.ndarray, T_last: np.ndarray, center_mm: np.ndarray, lam: float = 1.0
) -> np.ndarray:
    """The KPM prediction ``T_last exp(lam xi)``, 4x4 (mm): constant velocity for ``lam = 1``."""
    xi = kinematic_twist(T_before, T_last, center_mm)
    return T_last if xi is None else T_last @ twist_exp(lam * xi)


def kinematic_direction(carried: list[np.ndarray], center_mm: np.ndarray) -> np.ndarray | None:
    """The twist the KPM searches along, from the last (up to three) poses ``carried``
    (relative to the carrier, oldest first): the last motion, or at a turning point (the last
    motion under half the one before it) the one before; None when the last is no motion
    (:func:`kinematic_twist`)."""
    xi = kinematic_twist(carried[-2], carried[-1], center_mm)
    if xi is None:
        return None
    before = kinematic_twist(carried[0], carried[1], center_mm) if len(carried) == 3 else None
    if before is not None and twist_size(xi, center_mm) < 0.5 * twist_size(before, center_mm):
        return before
    return xi


def held_depth(
    T: np.ndarray, T_last: np.ndarray, center_mm: np.ndarray, source_mm: np.ndarray
) -> np.ndarray:
    """Predictions ``T`` (..., 4, 4) with their depth held at ``T_last``'s: each moved along
    the ray from ``source_mm`` through the body's centroid ``center_mm`` (which therefore
    projects where it did) until the centroid is as far from the source as at ``T_last``."""
    center = np.append(center_mm, 1.0)
    rays = (T @ center)[..., :3] - source_mm
    distance = np.linalg.norm((T_last @ center)[:3] - source_mm)
    held = T.copy()
    held[..., :3, 3] += (distance / np.linalg.norm(rays, axis=-1, keepdims=True) - 1.0) * rays
    return held


def patellofemoral_offsets(
    T_femur: np.ndarray, T_patella: np.ndarray, center_mm: np.ndarray, axis: np.ndarray
) -> np.ndarray:
    """:func:`patellofemoral_deviation` as a vector: the shift (mm), then the rotation vector
    less its component along ``axis`` (deg, 3; its norm is the tilt)."""
    M = np.linalg.inv(T_femur) @ T_patella
    shift = axis @ (M[:3, :3] @ center_mm + M[:3, 3] - center_mm)
    rotvec = Rotation.from_matrix(M[:3, :3]).as_rotvec(degrees=True)
    return np.append(shift, rotvec - (rotvec @ axis) * axis)


def patellofemoral_deviation(
    T_femur: np.ndarray, T_patella: np.ndarray, center_mm: np.ndarray, axis: np.ndarray
) -> tuple[float, float]:
    """The patella's out-of-plane motion relative to the femur since the static scan (both
    poses are identity there): the shift of its centroid ``center_mm`` along the femur's
    medial-lateral ``axis`` (a unit vector in the static scan, which the femur carries with
    it), mm, and its rotation about the two axes perpendicular to that, deg. Flexing about
    any medial-lateral line and sliding in the femur's sagittal plane count nothing."""
    offsets = patellofemoral_offsets(T_femur, T_patella, center_mm, axis)
    return float(offsets[0]), float(np.linalg.norm(offsets[1:]))


def patellofemoral_prior(
    settings: Settings, T_carrier: np.ndarray, center_mm: np.ndarray, view: View
) -> Prior | None:
    """The patellofemoral prior of a carried body (the patella) against its carrier's
    estimate ``T_carrier`` (the femur): its shift and the three components of its tilt, each
    over its ``patellofemoral_sigma``; None when the settings turn it off. The medial-lateral
    axis is the view's normal (a lateral view looks along the static scan's)."""
    if settings.patellofemoral_sigma is None:
        return None
    sigma_mm, sigma_deg = settings.patellofemoral_sigma
    axis = view.normal
    scale = math.sqrt(settings.prior_weight) / np.array([sigma_mm, sigma_deg, sigma_deg, sigma_deg])

    def prior(T: np.ndarray) -> np.ndarray:
        return scale * patellofemoral_offsets(T_carrier, T, center_mm, axis)

    return prior


def depth_prior(
    settings: Settings, sigma_mm: float, view: View, center_mm: np.ndarray, T_before: np.ndarray
) -> Prior:
    """The depth prior's term: the move of the body's centroid ``center_mm`` along the view's
    axis from its pose in the frame before, ``T_before``, over ``sigma_mm``."""
    center = np.append(center_mm, 1.0)
    scale = math.sqrt(settings.prior_weight) / sigma_mm

    def depth_mm(T: np.ndarray) -> float:
        return float(view.depth((T @ center)[:3])[0]) * view.sdd_mm

    before = depth_mm(T_before)
    return lambda T: np.array([scale * (depth_mm(T) - before)])


def joined(priors: list[Prior | None]) -> Prior | None:
    """The priors given (Nones left out) as one: their terms concatenated; None for none."""
    terms = [p for p in priors if p]
    if not terms:
        return None
    if len(terms) == 1:
        return terms[0]
    return lambda T: np.concatenate([term(T) for term in terms])
