"""Knee kinematics per frame: Grood-Suntay joint angles and tibial-plateau-condyle distances.

Poses move each bone from its reference (the static scan) to a frame. Left knees are mirrored
into right knees (x -> -x on points, ``M T M`` on poses) so both sides share one convention:

- joint coordinate system (Grood & Suntay 1983): e1 = the femur's medial-lateral axis (TEA),
  e3 = the tibia's long axis, e2 = e3 x e1 (floating, anterior). Flexion is the rotation about
  e1 between the femur's anterior axis and e2 (positive flexing), varus the angle by which e3
  leans from the plane normal to e1 (positive when the tibia is adducted), internal rotation
  the rotation about e3 between e2 and the tibia's anterior axis (positive internal).
  Translations of the tibia's origin from the femur's along e1, e2, e3: lateral shift,
  anterior drawer, proximal position.
- Scarvell's distances: for each femoral condyle, the signed distance of its lowest point
  (closest to the plateau) to the tibial plateau (TP) plane, and that point projected onto the
  plane in the plane's (medial, anterior) axes.
- Gaps: how far each condyle stands above the plateau's surface (assessment.contact), less
  its rest: its gap in the static scan (the joint space of a knee standing), or contact (0)
  for a femoral component on its insert.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from assessment.anatomy import FemurAnatomy, TibiaAnatomy
from assessment.contact import PlateauSurface
from assessment.results import MLD_FLAG_MM, KneeKinematics

MIRROR = np.diag([-1.0, 1.0, 1.0, 1.0])


def mirror_poses(poses: np.ndarray) -> np.ndarray:
    """Left-knee poses (F, 4, 4) expressed for the mirrored (right) knee: M T M."""
    return MIRROR @ poses @ MIRROR


def _angle(a: np.ndarray, b: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Signed angle (degrees) from a to b about ``axis``, row-wise (F, 3)."""
    return np.degrees(
        np.arctan2(np.einsum("ij,ij->i", np.cross(a, b), axis), np.einsum("ij,ij->i", a, b))
    )


def knee_kinematics(
    femur: FemurAnatomy,
    tibia: TibiaAnatomy,
    frames: np.ndarray,
    femur_poses: np.ndarray,
    tibia_poses: np.ndarray,
    side: Literal["right", "left"],
    flag_mm: float = MLD_FLAG_MM,
    rest_gap_mm: tuple[float, float] | None = None,
) -> KneeKinematics:
    """Angles, translations, TP-condyle distances and gaps per frame.

    Args:
        femur: reference anatomy of the femur, already mirrored for a left knee.
        tibia: reference anatomy of the tibia, already mirrored for a left knee.
        frames: frame numbers (F,).
        femur_poses: the femur's ``T_world_body`` per frame (F, 4, 4), mm, as registered
            (the function mirrors left-knee poses itself).
        tibia_poses: the tibia's, likewise.
        side: which knee the poses belong to.
        flag_mm: MLD flag threshold (mm).
        rest_gap_mm: the (medial, lateral) gaps at rest, mm; None: those of the reference
            poses (the static scan). Without surface points on ``tibia`` there are no gaps.
    """
    if side == "left":
        femur_poses, tibia_poses = mirror_poses(femur_poses), mirror_poses(tibia_poses)
    F = femur_poses @ femur.frame
    T = tibia_poses @ tibia.frame
    e1 = F[:, :3, 0]
    e3 = T[:, :3, 2]
    e2 = np.cross(e3, e1)
    e2 /= np.linalg.norm(e2, axis=1, keepdims=True)
    flexion = -_angle(F[:, :3, 1], e2, e1)
    varus = np.degrees(np.arcsin(np.clip(np.einsum("ij,ij->i", e1, e3), -1.0, 1.0)))
    internal = _angle(e2, T[:, :3, 1], e3)
    offset = T[:, :3, 3] - F[:, :3, 3]
    translation = np.column_stack([np.einsum("ij,ij->i", offset, e) for e in (e1, e2, e3)])
    medial, anterior = tibia.plane_axes
    surface = None if tibia.surface_mm is None else PlateauSurface(tibia)
    distances, points, gaps = [], [], []
    for j, condyle in enumerate((femur.medial_condyle_mm, femur.lateral_condyle_mm)):
        homogeneous = np.hstack((condyle, np.ones((len(condyle), 1))))
        relative = np.linalg.inv(tibia_poses) @ femur_poses  # femur in the tibia's reference
        moved = np.einsum("fij,nj->fni", relative, homogeneous)[..., :3]
        signed = (moved - tibia.plateau_center_mm) @ tibia.plateau_normal
        lowest = np.argmin(signed, axis=1)
        d = signed[np.arange(len(frames)), lowest]
        p = moved[np.arange(len(frames)), lowest] - d[:, None] * tibia.plateau_normal
        rel = p - tibia.plateau_center_mm
        distances.append(d)
        points.append(np.column_stack((rel @ medial, rel @ anterior)))
        if surface is not None:
            rest = surface.gap_mm(condyle) if rest_gap_mm is None else rest_gap_mm[j]
            gaps.append(surface.gap_mm(moved) - rest)
    return KneeKinematics(
        side=side,
        frames=np.asarray(frames),
        flexion_deg=flexion,
        varus_deg=varus,
        internal_rotation_deg=internal,
        translation_mm=translation,
        medial_distance_mm=distances[0],
        lateral_distance_mm=distances[1],
        medial_point_mm=points[0],
        lateral_point_mm=points[1],
        medial_gap_mm=gaps[0] if gaps else None,
        lateral_gap_mm=gaps[1] if gaps else None,
        flag_mm=flag_mm,
    )
