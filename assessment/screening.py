"""Which frames of a motion the assessment measures: none that the tracker marked failed, none
whose poses cannot be.

A frame is left out of every metric, plot line and flag, and named in the report, when

- the tracker marked the femur's or the tibia's body failed in it (registration.poses);
- a femoral condyle stands more than :data:`INSIDE_MM` inside the plateau's surface beyond its
  rest (a component sunk into its insert; a bone into the joint space the standing scan
  showed, which cartilage under a person's weight does not give);
- both condyles stand more than :data:`LIFTED_MM` above their rest (the femur off the tibia:
  a knee that bears no weight opens by a few millimetres at most);
- a condyle stands over no part of the plateau (the femur off the tibia's top);
- the joint's translation (the tibia against the femur) leaves both neighbouring frames' by
  more than :data:`JUMP_MM` and comes back (a jump faster than a knee moves: whatever the
  frame rate, the condyles roll and slide on the plateau).

docs/guide/assessment.md states the thresholds and their reasons.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from assessment.results import Exclusion, KneeKinematics
from registration.poses import BodyPose

INSIDE_MM = 2.0
"""A condyle deeper than this inside the plateau's surface (beyond its rest) is implausible:
the registrations' depth errors are a few tenths of a millimetre, a component's insert and a
knee's cartilage give less under load."""
LIFTED_MM = 5.0
"""Both condyles higher than this above their rest is implausible: the femur off the tibia."""
JUMP_MM = 10.0
"""A frame's joint translation this far from both neighbours' and from their midpoint is a
jump: over a whole motion the tibia shifts against the femur by 10-15 mm (rollback)."""


def screen(
    kin: KneeKinematics,
    poses: Sequence[BodyPose],
    bodies: dict[str, str],
    surface: str,
) -> KneeKinematics:
    """``kin`` with the frames it must not measure excluded: NaN in every metric, the reason
    in ``excluded``.

    Args:
        kin: The kinematics of every frame (with the condyles' gaps where there are any).
        poses: The registered poses (their ``failed`` and ``reason``).
        bodies: The femur's and the tibia's body, in that order: pose name -> the name a
            report gives it (e.g. "tibia_fibula" -> "tibial tray").
        surface: What the condyles rest on, in words ("the insert").

    Returns:
        The screened kinematics.
    """
    index = {int(f): k for k, f in enumerate(kin.frames)}
    reasons: list[Exclusion | None] = [None] * len(kin.frames)
    for name, shown in bodies.items():
        for pose in sorted((p for p in poses if p.body == name), key=lambda p: p.frame):
            k = index.get(pose.frame)
            if k is not None and pose.failed and reasons[k] is None:
                reasons[k] = Exclusion(f"{shown} not tracked", pose.reason or "marked failed")
    femur, tibia = bodies.values()
    _contact(kin, reasons, femur, surface)
    _jumps(kin, reasons, tibia)
    return excluding(kin, tuple(reasons))


def _contact(
    kin: KneeKinematics, reasons: list[Exclusion | None], femur: str, surface: str
) -> None:
    """Mark the frames whose condyles are inside the surface, both lifted off it, or over no
    part of it."""
    if kin.medial_gap_mm is None or kin.lateral_gap_mm is None:
        return
    gaps = np.column_stack((kin.medial_gap_mm, kin.lateral_gap_mm))
    for k, (medial, lateral) in enumerate(gaps):
        if reasons[k] is not None:
            continue
        if not np.isfinite([medial, lateral]).all():
            off = "medial" if not np.isfinite(medial) else "lateral"
            reasons[k] = Exclusion(f"{femur} off {surface}", f"{off} condyle over no part of it")
            continue
        deepest = min(medial, lateral)
        if deepest < -INSIDE_MM:
            side = "medial" if medial <= lateral else "lateral"
            reasons[k] = Exclusion(
                f"{femur} inside {surface}",
                f"{side} condyle {-deepest:.1f} mm beyond its rest; limit {INSIDE_MM:g} mm",
            )
        elif medial > LIFTED_MM and lateral > LIFTED_MM:
            reasons[k] = Exclusion(
                f"{femur} lifted off {surface}",
                f"medial {medial:.1f} mm, lateral {lateral:.1f} mm above their rest; limit "
                f"{LIFTED_MM:g} mm",
            )


def _jumps(kin: KneeKinematics, reasons: list[Exclusion | None], tibia: str) -> None:
    """Mark the frames whose joint translation (the tibia against the femur) leaves both
    neighbours' by more than :data:`JUMP_MM` and comes back: the condyles roll and slide on
    the plateau, they do not leap there and back in a frame."""
    shift = np.asarray(kin.translation_mm, dtype=np.float64)
    for k in range(1, len(shift) - 1):
        if any(reasons[j] is not None for j in (k - 1, k, k + 1)):
            continue
        away = [float(np.linalg.norm(shift[k] - shift[j])) for j in (k - 1, k + 1)]
        between = float(np.linalg.norm(shift[k] - 0.5 * (shift[k - 1] + shift[k + 1])))
        if min(away) > JUMP_MM and between > JUMP_MM:
            reasons[k] = Exclusion(
                f"{tibia} jumped against the femur",
                f"{min(away):.1f} mm from both neighbouring frames and back; limit {JUMP_MM:g} mm",
            )


def excluding(kin: KneeKinematics, excluded: tuple[Exclusion | None, ...]) -> KneeKinematics:
    """``kin`` with NaN in every metric of the frames ``excluded`` names (and their reasons).

    Args:
        kin: Per-frame knee metrics.
        excluded: Per frame, why it is not measured; None when it is.

    Returns:
        The kinematics of the measured frames, the others NaN.
    """
    if len(excluded) != len(kin.frames):
        raise ValueError(f"{len(excluded)} exclusions for {len(kin.frames)} frames")
    out = np.array([e is not None for e in excluded], dtype=bool)

    def blank(values: np.ndarray | None) -> np.ndarray | None:
        if values is None:
            return None
        values = np.array(values, dtype=np.float64)
        values[out] = np.nan
        return values

    return replace(
        kin,
        flexion_deg=blank(kin.flexion_deg),
        varus_deg=blank(kin.varus_deg),
        internal_rotation_deg=blank(kin.internal_rotation_deg),
        translation_mm=blank(kin.translation_mm),
        medial_distance_mm=blank(kin.medial_distance_mm),
        lateral_distance_mm=blank(kin.lateral_distance_mm),
        medial_point_mm=blank(kin.medial_point_mm),
        lateral_point_mm=blank(kin.lateral_point_mm),
        medial_gap_mm=blank(kin.medial_gap_mm),
        lateral_gap_mm=blank(kin.lateral_gap_mm),
        excluded=excluded,
    )
