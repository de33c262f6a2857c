"""UR-class arm catalogue: the makers' published DH parameters and joint limits.

Denavit-Hartenberg parameters (standard convention, metres and radians) are Universal Robots'
published tables for the e-Series ("DH parameters for calculations of kinematics and dynamics",
Universal Robots support article). Joint ranges are +-360 degrees on every joint; maximum joint
speeds are the datasheet values (UR3e: 180 deg/s on the base, shoulder and elbow, 360 deg/s on
the wrists; UR5e: 180 deg/s on all joints; UR10e: 120 deg/s on base and shoulder, 180 deg/s on
the others). The datasheets give no joint acceleration limit; we use the controller's default
joint acceleration for moveJ, 1.4 rad/s^2 (80 deg/s^2), as the limit for scanning motion.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class ArmModel:
    """One arm type: DH table (d, a, alpha per joint) and limits per joint.

    Attributes:
        name: "ur3e", "ur5e" or "ur10e".
        d_m, a_m: DH offsets along z and x, metres, per joint (6,).
        alpha_rad: DH twists, radians (6,).
        range_deg: symmetric joint range, degrees.
        max_speed_deg_s: per-joint speed limits (6,).
        max_accel_deg_s2: per-joint acceleration limits (6,).
        link_radius_m: collision capsule radius per link (6,), from the outer diameters.
    """

    name: str
    d_m: tuple[float, ...]
    a_m: tuple[float, ...]
    alpha_rad: tuple[float, ...]
    range_deg: float
    max_speed_deg_s: tuple[float, ...]
    max_accel_deg_s2: tuple[float, ...]
    link_radius_m: tuple[float, ...]

    @property
    def reach_m(self) -> float:
        """Shoulder-to-flange reach with the arm stretched, metres (|a2| + |a3| + d5 + d6)."""
        return abs(self.a_m[1]) + abs(self.a_m[2]) + self.d_m[4] + self.d_m[5]


_ALPHA = (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)
_ACCEL = (80.0,) * 6

ARMS: dict[str, ArmModel] = {
    "ur3e": ArmModel(
        "ur3e",
        d_m=(0.15185, 0.0, 0.0, 0.13105, 0.08535, 0.0921),
        a_m=(0.0, -0.24355, -0.2132, 0.0, 0.0, 0.0),
        alpha_rad=_ALPHA,
        range_deg=360.0,
        max_speed_deg_s=(180.0, 180.0, 180.0, 360.0, 360.0, 360.0),
        max_accel_deg_s2=_ACCEL,
        link_radius_m=(0.045, 0.045, 0.04, 0.035, 0.035, 0.035),
    ),
    "ur5e": ArmModel(
        "ur5e",
        d_m=(0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996),
        a_m=(0.0, -0.425, -0.3922, 0.0, 0.0, 0.0),
        alpha_rad=_ALPHA,
        range_deg=360.0,
        max_speed_deg_s=(180.0,) * 6,
        max_accel_deg_s2=_ACCEL,
        link_radius_m=(0.075, 0.06, 0.05, 0.045, 0.045, 0.045),
    ),
    "ur10e": ArmModel(
        "ur10e",
        d_m=(0.1807, 0.0, 0.0, 0.17415, 0.11985, 0.11655),
        a_m=(0.0, -0.6127, -0.57155, 0.0, 0.0, 0.0),
        alpha_rad=_ALPHA,
        range_deg=360.0,
        max_speed_deg_s=(120.0, 120.0, 180.0, 180.0, 180.0, 180.0),
        max_accel_deg_s2=_ACCEL,
        link_radius_m=(0.095, 0.075, 0.065, 0.055, 0.055, 0.055),
    ),
}

ARM_JOINTS = ("base", "shoulder", "elbow", "wrist1", "wrist2", "wrist3")
"""An arm's joints as its controller and the devices name them, base to wrist (the same order
as :data:`JOINT_NAMES`, the kinematic model's)."""
JOINT_NAMES = ("shoulder_pan", "shoulder_lift", "elbow", "wrist_1", "wrist_2", "wrist_3")
