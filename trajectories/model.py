"""Pinocchio model of the scanner: rotary -> lift -> two UR arms with their tools, and the
collision geometry (coal) of links, tube, panel, column, platform, floor and patient.

Joint vector ``q`` (Pinocchio units, radians and metres) is looked up by joint name through
:attr:`ScannerModel.index`, never by position. Public conversions give degrees and mm.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import coal
import numpy as np
import pinocchio as pin
from scipy.spatial.transform import Rotation

from trajectories.arms import ARMS, JOINT_NAMES
from trajectories.config import ArmConfig, Box, Cylinder, Placement, ScannerConfig

ARM_ROLES = ("source", "detector")
SOURCE_TOOL = "source_focal_spot"
DETECTOR_TOOL = "detector_center"


def se3(placement: Placement) -> pin.SE3:
    """Placement (mm, extrinsic xyz degrees) as a pin.SE3 in metres."""
    rot = Rotation.from_euler("xyz", placement.rpy_deg, degrees=True).as_matrix()
    return pin.SE3(rot, np.asarray(placement.xyz_mm) / 1000.0)


def _dh_placement(d: float, a: float, alpha: float) -> pin.SE3:
    """The DH link transform after the joint rotation: Tz(d) Tx(a) Rx(alpha)."""
    rot = Rotation.from_euler("x", alpha).as_matrix()
    return pin.SE3(np.eye(3), np.array([a, 0.0, d])) * pin.SE3(rot, np.zeros(3))


def _segment_placement(p0: np.ndarray, p1: np.ndarray) -> tuple[pin.SE3, float]:
    """Placement of a z-aligned shape spanning p0 -> p1, and the span's length (m)."""
    axis = p1 - p0
    length = float(np.linalg.norm(axis))
    if length < 1e-9:
        return pin.SE3(np.eye(3), p0), 0.0
    rot, _ = Rotation.align_vectors([axis / length], [[0.0, 0.0, 1.0]])
    return pin.SE3(rot.as_matrix(), 0.5 * (p0 + p1)), length


@dataclass(frozen=True)
class Limits:
    """Per-joint limits in Pinocchio units, ordered like ``q``."""

    lower: np.ndarray
    upper: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray


class ScannerModel:
    """Kinematics and collision geometry of one scanner configuration.

    Attributes:
        config: the hardware description it was built from.
        model, data: Pinocchio kinematic model and its workspace.
        geometry, geometry_data: coal collision objects and the checked pairs.
        joint_names: the 14 joint names in ``q`` order (rotary, lift, 6 source, 6 detector).
        index: joint name -> index into ``q``.
        limits: position, velocity and acceleration limits, radians / metres.
    """

    def __init__(self, config: ScannerConfig) -> None:
        self.config = config
        self.model = pin.Model()
        self.model.name = config.name
        self._arm_bodies: dict[str, list[int]] = {}
        inertia = pin.Inertia.FromSphere(1.0, 0.05)
        rotary = self.model.addJoint(0, pin.JointModelRZ(), pin.SE3.Identity(), "rotary")
        self.model.appendBodyToJoint(rotary, inertia, pin.SE3.Identity())
        lift = self.model.addJoint(rotary, pin.JointModelPZ(), pin.SE3.Identity(), "lift")
        self.model.appendBodyToJoint(lift, inertia, pin.SE3.Identity())
        self._joint_ids = {"rotary": rotary, "lift": lift}
        self._segments: list[tuple[str, int, pin.SE3, float]] = []
        for role, arm in self.arms():
            self._add_arm(role, arm, lift, inertia)
        self.data = self.model.createData()
        self.joint_names = tuple(
            ["rotary", "lift"] + [f"{r}_{j}" for r in ARM_ROLES for j in JOINT_NAMES]
        )
        self.index = {
            name: self.model.joints[self.model.getJointId(name)].idx_q for name in self.joint_names
        }
        self._order = np.array([self.index[n] for n in self.joint_names])
        self.limits = self._limits()
        self.source_frame = self.model.getFrameId(SOURCE_TOOL)
        self.detector_frame = self.model.getFrameId(DETECTOR_TOOL)
        self.geometry = self._collision_geometry()
        self.geometry_data = pin.GeometryData(self.geometry)

    # -- building ---------------------------------------------------------------------------

    def _add_arm(self, role: str, arm: ArmConfig, parent: int, inertia: pin.Inertia) -> None:
        spec = ARMS[arm.model]
        placement = se3(arm.mount)
        joints = []
        for k, name in enumerate(JOINT_NAMES):
            jid = self.model.addJoint(parent, pin.JointModelRZ(), placement, f"{role}_{name}")
            self.model.appendBodyToJoint(jid, inertia, pin.SE3.Identity())
            joints.append(jid)
            placement = _dh_placement(spec.d_m[k], spec.a_m[k], spec.alpha_rad[k])
            self._segments.append((f"{role}_link{k + 1}", jid, placement, spec.link_radius_m[k]))
            parent = jid
        flange = self.model.addFrame(
            pin.Frame(f"{role}_flange", parent, placement, pin.FrameType.OP_FRAME)
        )
        tool_name = SOURCE_TOOL if role == "source" else DETECTOR_TOOL
        self.model.addFrame(
            pin.Frame(tool_name, parent, flange, placement * se3(arm.tool), pin.FrameType.OP_FRAME)
        )
        self._arm_bodies[role] = joints
        self._joint_ids.update({f"{role}_{n}": j for n, j in zip(JOINT_NAMES, joints, strict=True)})

    def _limits(self) -> Limits:
        n = self.model.nq
        lower, upper = np.zeros(n), np.zeros(n)
        vel, acc = np.zeros(n), np.zeros(n)
        rot, lift = self.config.rotary, self.config.lift
        i = self.index["rotary"]
        lower[i], upper[i] = np.radians(rot.range_deg)
        vel[i], acc[i] = math.radians(rot.max_speed_deg_s), math.radians(rot.max_accel_deg_s2)
        i = self.index["lift"]
        lower[i], upper[i] = np.asarray(lift.range_mm) / 1000.0
        vel[i], acc[i] = lift.max_speed_mm_s / 1000.0, lift.max_accel_mm_s2 / 1000.0
        for role, arm in self.arms():
            spec = ARMS[arm.model]
            for k, name in enumerate(JOINT_NAMES):
                i = self.index[f"{role}_{name}"]
                lower[i], upper[i] = -math.radians(spec.range_deg), math.radians(spec.range_deg)
                vel[i] = math.radians(spec.max_speed_deg_s[k]) * arm.speed_scale
                acc[i] = math.radians(spec.max_accel_deg_s2[k]) * arm.accel_scale
        return Limits(lower, upper, vel, acc)

    def _collision_geometry(self) -> pin.GeometryModel:
        geom = pin.GeometryModel()
        owner: dict[str, tuple[str, int]] = {}  # name -> (group, chain position)

        def add(name: str, joint: int, placement: pin.SE3, shape, group: str, pos: int) -> None:
            geom.addGeometryObject(pin.GeometryObject(name, joint, placement, shape))
            owner[name] = (group, pos)

        # arm links: capsules from each joint to the next (DH origins), tools on the last joint
        for k, (name, jid, to_next, radius) in enumerate(self._segments):
            role = name.split("_")[0]
            place, length = _segment_placement(np.zeros(3), to_next.translation.copy())
            if length > 0:
                add(name, jid, place, coal.Capsule(radius, length), role, k % 6 + 1)
            else:
                add(name, jid, place, coal.Sphere(radius), role, k % 6 + 1)
        for role, _ in self.arms():
            wrist = self._arm_bodies[role][-1]
            tool = self.model.frames[
                self.model.getFrameId(SOURCE_TOOL if role == "source" else DETECTOR_TOOL)
            ].placement
            if role == "source":
                box = self.config.tube.housing
            else:
                panel = self.config.panel
                border = 2 * panel.housing_border_mm
                box = Box(
                    center_mm=(0.0, 0.0, -0.5 * panel.housing_thickness_mm),
                    size_mm=(
                        panel.pixels.width_mm + border,
                        panel.pixels.height_mm + border,
                        panel.housing_thickness_mm,
                    ),
                )
            add(f"{role}_tool", wrist, tool * _box_placement(box), _box_shape(box), role, 7)
        obstacles = self.config.obstacles
        add(
            "platform",
            0,
            _cylinder_placement(obstacles.platform),
            _cylinder_shape(obstacles.platform),
            "world",
            0,
        )
        add(
            "floor",
            0,
            pin.SE3(np.eye(3), np.array([0.0, 0.0, obstacles.platform.z_min_mm / 1000 - 0.05])),
            coal.Box(20.0, 20.0, 0.1),
            "world",
            0,
        )
        add(
            "column",
            self._joint_ids["rotary"],
            _box_placement(obstacles.column),
            _box_shape(obstacles.column),
            "world",
            0,
        )
        for k, cyl in enumerate(obstacles.patient):
            add(f"patient{k}", 0, _cylinder_placement(cyl), _cylinder_shape(cyl), "world", 0)
        names = [g.name for g in geom.geometryObjects]
        for a in range(len(names)):
            for b in range(a + 1, len(names)):
                ga, pa = owner[names[a]]
                gb, pb = owner[names[b]]
                if ga == gb == "world":
                    continue
                if ga == gb and abs(pa - pb) <= (3 if 7 in (pa, pb) else 2):
                    continue  # same arm: neighbours share joints; the tool sits on the wrist
                geom.addCollisionPair(pin.CollisionPair(a, b))
        return geom

    # -- kinematics --------------------------------------------------------------------------

    def arms(self) -> tuple[tuple[str, ArmConfig], ...]:
        """(role, arm) for the source and the detector arm."""
        return (("source", self.config.source_arm), ("detector", self.config.detector_arm))

    def neutral(self) -> np.ndarray:
        """The home configuration: rotary 0, lift at its lowest, arms at their home postures."""
        q = pin.neutral(self.model)
        q[self.index["lift"]] = self.limits.lower[self.index["lift"]]
        for role, arm in self.arms():
            for name, value in zip(JOINT_NAMES, arm.home_deg, strict=True):
                q[self.index[f"{role}_{name}"]] = math.radians(value)
        return q

    def tool_poses(self, q: np.ndarray) -> tuple[pin.SE3, pin.SE3]:
        """World poses (metres) of the focal spot frame and the panel-centre frame.

        Args:
            q: Configuration (Pinocchio's: radians, metres), shape (nq,).
        """
        pin.framesForwardKinematics(self.model, self.data, q)
        return self.data.oMf[self.source_frame].copy(), self.data.oMf[self.detector_frame].copy()

    def clearance(self, q: np.ndarray) -> tuple[float, str, str]:
        """Smallest distance (m) over the checked pairs and the pair's names (negative: overlap).

        Args:
            q: Configuration (Pinocchio's: radians, metres), shape (nq,).
        """
        k = pin.computeDistances(self.model, self.data, self.geometry, self.geometry_data, q)
        pair = self.geometry.collisionPairs[k]  # Pinocchio returns the nearest pair's index
        objects = self.geometry.geometryObjects
        distance = self.geometry_data.distanceResults[k].min_distance
        return float(distance), objects[pair.first].name, objects[pair.second].name

    def to_units(self, q: np.ndarray) -> np.ndarray:
        """``q`` as the public joint vector in ``joint_names`` order.

        Args:
            q: Configurations (radians, metres), shape (..., nq).

        Returns:
            Rotary (deg), lift (mm), arm joints (deg), shape (..., 14).
        """
        out = np.degrees(np.asarray(q)[..., self._order])
        out[..., 1] = np.asarray(q)[..., self.index["lift"]] * 1000.0
        return out

    def from_units(self, values: np.ndarray) -> np.ndarray:
        """Inverse of :meth:`to_units`.

        Args:
            values: Rotary (deg), lift (mm), arm joints (deg), shape (..., 14).

        Returns:
            Configurations (radians, metres), shape (..., nq).
        """
        values = np.asarray(values, dtype=np.float64)
        q = np.empty((*values.shape[:-1], self.model.nq))
        q[..., self._order] = np.radians(values)
        q[..., self.index["lift"]] = values[..., 1] / 1000.0
        return q


def _box_placement(box: Box) -> pin.SE3:
    return pin.SE3(np.eye(3), np.asarray(box.center_mm) / 1000.0)


def _box_shape(box: Box):
    return coal.Box(*(s / 1000.0 for s in box.size_mm))


def _cylinder_placement(cyl: Cylinder) -> pin.SE3:
    x, y = cyl.center_xy_mm
    return pin.SE3(np.eye(3), np.array([x, y, 0.5 * (cyl.z_min_mm + cyl.z_max_mm)]) / 1000.0)


def _cylinder_shape(cyl: Cylinder):
    return coal.Cylinder(cyl.radius_mm / 1000.0, (cyl.z_max_mm - cyl.z_min_mm) / 1000.0)
