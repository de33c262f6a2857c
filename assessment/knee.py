"""Assess a knee motion: label volume + per-frame bone poses -> :class:`KneeKinematics`.

Labels follow registration.labels (the phantom's and the segmentation's convention:
femur 2, tibia 3, fibula 4, patella 5) plus :data:`INSERT_LABEL` for a TKA polyethylene insert.
The femur and the tibia are the bodies playing them (registration.roles: the tibia's pose may
be given as "tibia" or "tibia_fibula", the unit registration tracks).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from assessment.anatomy import (
    FemurAnatomy,
    TibiaAnatomy,
    femur_anatomy,
    mirror_x,
    tibia_anatomy,
)
from assessment.kinematics import knee_kinematics
from assessment.results import MLD_FLAG_MM, KneeKinematics
from assessment.screening import screen
from recon.volume import Volume
from registration.labels import BONE_LABELS, INSERT_LABEL, LABELS
from registration.poses import BodyPose, poses_by_frame
from registration.roles import playing


@dataclass(frozen=True)
class KneeAssessment:
    """Result of :func:`assess_knee`: the metrics and the anatomy they were measured on (the
    anatomy of a left knee is mirrored into a right knee's frame)."""

    kinematics: KneeKinematics
    femur: FemurAnatomy
    tibia: TibiaAnatomy


def check_bones_present(labels: Volume, poses: list[BodyPose]) -> None:
    """Every posed bone must exist in the label volume (error names the frame and bone)."""
    present = set(np.unique(labels.data).tolist())
    for pose in poses:
        wanted = BONE_LABELS.get(pose.body)
        if wanted is None:
            raise ValueError(
                f"frame {pose.frame}, body {pose.body}: unknown bone name "
                f"(known: {', '.join(BONE_LABELS)})"
            )
        if not present.intersection(wanted):
            raise ValueError(
                f"frame {pose.frame}, body {pose.body}: the label volume has no "
                f"such bone (labels {list(wanted)}), so it has no mesh"
            )


def assess_knee(
    labels: Volume,
    poses: list[BodyPose],
    side: Literal["right", "left"],
    *,
    tka: bool = False,
    plateau_offset_mm: float = 0.0,
    flag_mm: float = MLD_FLAG_MM,
) -> KneeAssessment:
    """Joint angles, TP-condyle distances and flags of a knee over a motion, from the frames
    whose registration neither failed nor is implausible (assessment.screening).

    Args:
        labels: static-scan label volume (world LPS).
        poses: per-frame ``T_world_body`` of at least the femur and the tibia.
        side: which knee.
        tka: fit the TP plane to the polyethylene insert (label :data:`INSERT_LABEL`).
        plateau_offset_mm: shift of the TP plane along its normal (docs/system.md's configurable
            offset; negative is below the fitted plateau).
        flag_mm: MLD flag threshold.
    """
    if labels.unit != "label":
        raise ValueError(f"labels must be a label volume, got unit {labels.unit!r}")
    if side not in ("right", "left"):
        raise ValueError(f"side must be 'right' or 'left', got {side!r}")
    check_bones_present(labels, poses)
    femur_name, tibia_name = playing((p.body for p in poses), "femur", "tibia")
    frames, stacks = poses_by_frame(poses, (femur_name, tibia_name))
    anatomy_labels = mirror_x(labels) if side == "left" else labels
    femur = femur_anatomy(anatomy_labels, LABELS["femur"])
    if tka:
        if not np.any(anatomy_labels.data == INSERT_LABEL):
            raise ValueError(
                f"--tka needs the polyethylene insert (label {INSERT_LABEL}) in the label volume"
            )
        tibia = tibia_anatomy(anatomy_labels, INSERT_LABEL, plateau_offset_mm)
    else:
        tibia = tibia_anatomy(anatomy_labels, LABELS["tibia"], plateau_offset_mm)
    kinematics = knee_kinematics(
        femur, tibia, frames, stacks[femur_name], stacks[tibia_name], side, flag_mm
    )
    kinematics = screen(
        kinematics,
        poses,
        {femur_name: "femur", tibia_name: "tibia"},
        "the polyethylene insert" if tka else "the tibial plateau",
    )
    return KneeAssessment(kinematics, femur, tibia)
