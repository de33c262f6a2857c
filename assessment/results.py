"""The per-frame knee metrics every part of the assessment reads and writes."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

MLD_FLAG_MM = 2.0
"""Medial-lateral distance difference above which a frame is flagged (docs/system.md)."""


@dataclass(frozen=True)
class KneeKinematics:
    """Knee metrics per frame of a motion.

    Angles follow the Grood-Suntay joint coordinate system with the same sign convention for
    both sides (a left knee is mirrored into a right knee's frame first): flexion positive,
    varus (adduction of the tibia) positive, internal rotation of the tibia positive.
    Distances are from the femoral condyles' lowest points to the tibial plateau (TP) plane.

    Attributes:
        side: "right" or "left".
        frames: frame numbers (F,).
        flexion_deg, varus_deg, internal_rotation_deg: joint angles (F,).
        translation_mm: tibia relative to femur along the JCS axes (F, 3):
            medial-lateral shift, anterior drawer, distraction.
        medial_distance_mm, lateral_distance_mm: lowest medial / lateral condyle point to the
            TP plane, positive above it (F,).
        medial_point_mm, lateral_point_mm: those points projected on the TP plane, in the
            plane's 2-D frame (medial-lateral, anterior-posterior) mm (F, 2).
        flag_mm: MLD threshold for flags.
    """

    side: Literal["right", "left"]
    frames: np.ndarray
    flexion_deg: np.ndarray
    varus_deg: np.ndarray
    internal_rotation_deg: np.ndarray
    translation_mm: np.ndarray
    medial_distance_mm: np.ndarray
    lateral_distance_mm: np.ndarray
    medial_point_mm: np.ndarray
    lateral_point_mm: np.ndarray
    flag_mm: float = MLD_FLAG_MM

    @property
    def mld_mm(self) -> np.ndarray:
        """Medial minus lateral distance per frame (MLD), mm."""
        return self.medial_distance_mm - self.lateral_distance_mm

    @property
    def ddv_mm2(self) -> float:
        """Distance difference variance: the variance of the MLD over the motion, mm^2."""
        return float(np.var(self.mld_mm))

    @property
    def flagged(self) -> np.ndarray:
        """Frames whose |MLD| exceeds the threshold (boolean per frame)."""
        return np.abs(self.mld_mm) > self.flag_mm
