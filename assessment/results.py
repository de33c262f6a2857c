"""The per-frame knee metrics every part of the assessment reads and writes."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

MLD_FLAG_MM = 2.0
"""Medial-lateral distance difference above which a frame is flagged (docs/system.md)."""
LOADED_GAP_MM = 1.5
"""A frame is loaded (its MLD can be flagged) when a condyle is within this of its rest on the
plateau's surface (assessment.screening; docs/guide/assessment.md)."""
MIN_MEASURED_SHARE = 0.5
"""Below this share of measured frames the report gives no clinical flag at all."""


@dataclass(frozen=True)
class Exclusion:
    """Why a frame is not measured.

    Attributes:
        what: What went wrong, the same words for every frame it hits, e.g. "tibial tray not
            tracked" (the report groups frames by it).
        detail: The frame's own figures, e.g. "NCC 0.308 below 0.5".
    """

    what: str
    detail: str

    def __str__(self) -> str:
        return f"{self.what} ({self.detail})"


@dataclass(frozen=True)
class KneeKinematics:
    """Knee metrics per frame of a motion.

    Angles follow the Grood-Suntay joint coordinate system with the same sign convention for
    both sides (a left knee is mirrored into a right knee's frame first): flexion positive,
    varus (adduction of the tibia) positive, internal rotation of the tibia positive.
    Distances are from the femoral condyles' lowest points to the tibial plateau (TP) plane.
    A frame the assessment does not measure (``excluded``: a failed or implausible
    registration, assessment.screening) holds NaN in every metric.

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
        medial_gap_mm, lateral_gap_mm: how far the medial / lateral condyle is above the
            plateau's surface beneath it, less its rest (the static scan's joint space for
            bones; contact for a component on its insert), mm; negative: inside it; NaN where
            there is no surface to measure against (F,).
        flag_mm: MLD threshold for flags.
        excluded: per frame, why it is not measured; None when it is.
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
    medial_gap_mm: np.ndarray | None = None
    lateral_gap_mm: np.ndarray | None = None
    flag_mm: float = MLD_FLAG_MM
    excluded: tuple[Exclusion | None, ...] | None = None

    @property
    def measured(self) -> np.ndarray:
        """Frames the metrics come from (boolean per frame)."""
        if self.excluded is None:
            return np.ones(len(self.frames), dtype=bool)
        return np.array([e is None for e in self.excluded], dtype=bool)

    @property
    def sufficient(self) -> bool:
        """Whether enough frames are measured for clinical flags (:data:`MIN_MEASURED_SHARE`)."""
        return bool(self.measured.mean() >= MIN_MEASURED_SHARE)

    @property
    def loaded(self) -> np.ndarray:
        """Frames where a condyle rests on the plateau (within :data:`LOADED_GAP_MM` of its
        rest), so that a medial-lateral difference is an imbalance, not the laxity of a
        joint that bears no weight; True where no surface measures it (boolean per frame)."""
        if self.medial_gap_mm is None or self.lateral_gap_mm is None:
            return np.ones(len(self.frames), dtype=bool)
        nearest = np.fmin(self.medial_gap_mm, self.lateral_gap_mm)
        return ~(nearest > LOADED_GAP_MM)

    @property
    def mld_mm(self) -> np.ndarray:
        """Medial minus lateral distance per frame (MLD), mm."""
        return self.medial_distance_mm - self.lateral_distance_mm

    @property
    def ddv_mm2(self) -> float:
        """Distance difference variance: the variance of the MLD over the measured frames,
        mm^2 (NaN when none is measured)."""
        mld = self.mld_mm[self.measured]
        return float(np.var(mld)) if mld.size else float("nan")

    @property
    def over_limit(self) -> np.ndarray:
        """Frames whose |MLD| exceeds the threshold, loaded or not; never a frame not
        measured (boolean per frame)."""
        with np.errstate(invalid="ignore"):
            return (np.abs(self.mld_mm) > self.flag_mm) & self.measured

    @property
    def flagged(self) -> np.ndarray:
        """Loaded frames over the limit (:attr:`over_limit`), when enough frames are measured
        (boolean per frame)."""
        if not self.sufficient:
            return np.zeros(len(self.frames), dtype=bool)
        return self.over_limit & self.loaded
