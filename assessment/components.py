"""A knee replacement's anatomy from its components: the femoral component's condylar surfaces
and the tibial plateau plane of the polyethylene insert (or of the tray), in the components'
own frames, so that the tracked components' poses give the knee's kinematics, TP-condyle
distances, MLD and DDV as bones from a static scan do.

The component meshes are taken in the implant makers' and OpenSim's anatomical convention: x
anterior, y superior (proximal), z to the patient's right (lateral for a right knee); the
insert (or tray) in the frame of the tracked tray. The femoral component's medial and lateral
extremes stand for the epicondyles (a component has none), its articular points are its
outer surface's distal and posterior faces, a compartment each side of the notch.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Literal

import numpy as np
import trimesh

from assessment.anatomy import FemurAnatomy, TibiaAnatomy
from assessment.kinematics import knee_kinematics
from assessment.knee import KneeAssessment
from assessment.results import MLD_FLAG_MM
from assessment.screening import screen
from registration.poses import BodyPose, poses_by_frame
from registration.roles import playing

NOTCH_HALF_WIDTH_MM = 8.0
"""Half the intercondylar notch's width: articular points nearer the component's mid-plane are
left out."""
ARTICULAR_COS = 0.3
"""An articular point's outward normal points at least this much distally or posteriorly."""
PLATEAU_COS = 0.7
"""A plateau point's outward normal points at least this much proximally."""


def femoral_anatomy(femoral: trimesh.Trimesh) -> FemurAnatomy:
    """The femoral component's landmarks in its frame (a right knee's convention).

    Args:
        femoral: The femoral component, closed, in its anatomical frame (mm).

    Returns:
        Its anatomy: centre, medial and lateral extremes, axes and articular points.
    """
    vertices, normals = np.asarray(femoral.vertices), np.asarray(femoral.vertex_normals)
    low, high = vertices.min(axis=0), vertices.max(axis=0)
    center = 0.5 * (low + high)
    lateral, proximal = np.array([0.0, 0.0, 1.0]), np.array([0.0, 1.0, 0.0])
    articular = (normals[:, 1] < -ARTICULAR_COS) | (normals[:, 0] < -ARTICULAR_COS)
    side = vertices[:, 2] - center[2]
    medial_points = vertices[articular & (side < -NOTCH_HALF_WIDTH_MM)]
    lateral_points = vertices[articular & (side > NOTCH_HALF_WIDTH_MM)]
    if min(len(medial_points), len(lateral_points)) < 10:
        raise ValueError(
            "the femoral component shows no condyles either side of its notch along z: give "
            "its mesh in the anatomical frame (x anterior, y superior, z to the right)"
        )
    return FemurAnatomy(
        center_mm=center,
        medial_epicondyle_mm=np.array([center[0], center[1], low[2]]),
        lateral_epicondyle_mm=np.array([center[0], center[1], high[2]]),
        lateral_axis=lateral,
        proximal_axis=proximal,
        medial_condyle_mm=medial_points,
        lateral_condyle_mm=lateral_points,
    )


def plateau_anatomy(plateau: trimesh.Trimesh, offset_mm: float = 0.0) -> TibiaAnatomy:
    """The tibial plateau plane of the insert (or tray): fitted to its top surface's proximal
    faces, shifted by ``offset_mm`` along its normal.

    Args:
        plateau: The insert (or tray), closed, in the tracked tray's frame (mm).
        offset_mm: Shift of the plane along its normal, mm (negative: below).

    Returns:
        The plateau's anatomy: centre, normal and axes.
    """
    centers, normals = np.asarray(plateau.triangles_center), np.asarray(plateau.face_normals)
    top = (normals[:, 1] > PLATEAU_COS) & (centers[:, 1] > np.median(centers[:, 1]))
    if top.sum() < 10:
        raise ValueError(
            "the insert shows no proximal surface along +y: give its mesh in the tray's "
            "anatomical frame (x anterior, y superior, z to the right)"
        )
    areas = np.asarray(plateau.area_faces)[top]
    center = np.average(centers[top], axis=0, weights=areas)
    _, _, vt = np.linalg.svd((centers[top] - center) * np.sqrt(areas)[:, None], full_matrices=False)
    normal = vt[2] * np.sign(vt[2][1])
    return TibiaAnatomy(
        plateau_center_mm=center + offset_mm * normal,
        plateau_normal=normal,
        proximal_axis=np.array([0.0, 1.0, 0.0]),
        lateral_axis=np.array([0.0, 0.0, 1.0]),
        surface_mm=centers[top],
    )


def assess_components(
    femoral: trimesh.Trimesh,
    plateau: trimesh.Trimesh,
    poses: list[BodyPose],
    side: Literal["right", "left"] = "right",
    plateau_offset_mm: float = 0.0,
    flag_mm: float = MLD_FLAG_MM,
    *,
    insert: bool = True,
) -> KneeAssessment:
    """Joint angles, TP-condyle distances and flags of a knee replacement over a motion, from
    its components' poses in the frames whose registration neither failed nor is implausible
    (assessment.screening).

    Args:
        femoral: The femoral component (its frame is the femur's tracked pose's).
        plateau: The insert, or the tray where there is no insert mesh (the tray's frame).
        poses: Per frame the pose of the body playing the femur (the femoral component) and
            of the one playing the tibia (the tray), registration.roles.
        side: Which knee; a left one is refused (the components' frames are not mirrored yet).
        plateau_offset_mm: Shift of the TP plane along its normal, mm.
        flag_mm: MLD flag threshold, mm.
        insert: ``plateau`` is the insert, on which the femoral component rests (its gaps are
            measured from contact); False for a tray, which the condyles do not touch (no
            gaps: neither sunk nor lifted frames are found).

    Returns:
        The kinematics and the components' anatomy.
    """
    if side != "right":
        raise ValueError(
            f"--tka from component meshes: side {side!r}; only right knees so far (a left "
            "knee's component frames are not mirrored into a right one's yet)"
        )
    femur_name, tibia_name = playing((p.body for p in poses), "femur", "tibia")
    frames, stacks = poses_by_frame(poses, (femur_name, tibia_name))
    femur = femoral_anatomy(femoral)
    tibia = plateau_anatomy(plateau, plateau_offset_mm)
    if not insert:
        tibia = replace(tibia, surface_mm=None)
    kinematics = knee_kinematics(
        femur, tibia, frames, stacks[femur_name], stacks[tibia_name], side, flag_mm, (0.0, 0.0)
    )
    kinematics = screen(
        kinematics,
        poses,
        {femur_name: "femoral component", tibia_name: "tibial tray"},
        "the insert" if insert else "the tray",
    )
    return KneeAssessment(kinematics, femur, tibia)
