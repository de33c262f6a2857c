"""The one parameterisation of a body's pose change that registration searches, and the
exponential map the kinematic prediction extrapolates with.

A pose ``T_world_body`` (4x4, mm) moves a body from where the static scan saw it to where it
is in a frame. Searches move it by a 6-vector ``x = (t mm, r deg)`` about its current
centroid, in world axes: ``T(x) = [R(r), (I - R(r)) c + t] T0``.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import RigidTransform, Rotation


def compose(x: np.ndarray, T0: np.ndarray, center_mm: np.ndarray) -> np.ndarray:
    """``T(x) = [R, (I - R) c + t] T0`` with c the moved centroid, x = (t mm, r deg).

    Args:
        x: the step (tx, ty, tz mm, then a rotation vector in deg), (6,).
        T0: the pose it starts from, 4x4 (mm).
        center_mm: the body's centroid in its reference frame (the static scan), (3,) mm.

    Returns:
        The moved pose, 4x4 (mm).

    Examples:
        A quarter turn about z moves a body about its own centroid, which stays put; the
        translation then moves it along world axes:

        >>> centroid = np.array([10.0, 0.0, 0.0])
        >>> T = compose(np.array([0.0, 0.0, 5.0, 0.0, 0.0, 90.0]), np.eye(4), centroid)
        >>> (T[:3, :3] @ centroid + T[:3, 3]).round(6).tolist()  # the moved centroid, mm
        [10.0, 0.0, 5.0]
        >>> (T[:3, :3] @ [11.0, 0.0, 0.0] + T[:3, 3]).round(6).tolist()  # 1 mm beside it
        [10.0, 1.0, 5.0]
    """
    R = Rotation.from_rotvec(np.radians(x[3:6])).as_matrix()
    c = T0[:3, :3] @ center_mm + T0[:3, 3]
    M = np.eye(4)
    M[:3, :3] = R
    M[:3, 3] = c - R @ c + x[:3]
    return M @ T0


def twist_exp(xi: np.ndarray) -> np.ndarray:
    """``exp(xi)`` as 4x4 matrices (mm) of exponential coordinates ``(rotation vector rad,
    v mm)``, (..., 6) -> (..., 4, 4) (scipy's RigidTransform)."""
    return RigidTransform.from_exp_coords(xi).as_matrix()


def twist_of(T_before: np.ndarray, T_after: np.ndarray) -> np.ndarray:
    """The motion from ``T_before`` to ``T_after`` in the body's frame as exponential
    coordinates: ``T_after = T_before exp(xi)``, (6,) (rad, mm).

    Examples:
        The inverse of :func:`twist_exp`:

        >>> xi = np.array([0.1, -0.2, 0.3, 4.0, 5.0, -6.0])
        >>> T_before = twist_exp(np.array([0.0, 0.0, 0.5, 10.0, 0.0, 0.0]))
        >>> bool(np.allclose(twist_of(T_before, T_before @ twist_exp(xi)), xi))
        True
    """
    return RigidTransform.from_matrix(np.linalg.inv(T_before) @ T_after).as_exp_coords()


def twist_size(xi: np.ndarray, center_mm: np.ndarray) -> float:
    """The larger of a twist's step at ``center_mm`` (mm, to first order) and its angle (deg).

    Examples:
        A turn of 0.01 rad about z moves a point 100 mm from the axis by 1 mm, more than the
        0.57 deg:

        >>> round(twist_size(np.array([0.0, 0.0, 0.01, 0.0, 0.0, 0.0]), np.array([100.0, 0, 0])), 6)
        1.0
    """
    step_mm = np.linalg.norm(np.cross(xi[:3], center_mm) + xi[3:])
    return max(float(step_mm), math.degrees(np.linalg.norm(xi[:3])))
