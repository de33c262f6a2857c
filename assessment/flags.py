"""Medial-lateral difference (MLD) flags: runs of flagged frames and the sentences a surgeon reads.

A measured, loaded frame is flagged when |MLD| exceeds ``KneeKinematics.flag_mm`` (2 mm,
docs/system.md), and only when enough frames are measured (assessment.results). A flag is a cue
for review of alignment and ligament balance, not a diagnosis; the wording says so. The frames
left out (assessment.screening) are named, never measured.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from assessment.results import LOADED_GAP_MM, MIN_MEASURED_SHARE, KneeKinematics


@dataclass(frozen=True)
class FlagRun:
    """Consecutive flagged frames whose MLD has the same sign.

    Attributes:
        first_frame, last_frame: frame numbers (from ``kin.frames``) of the run's ends, inclusive.
        max_abs_mld_mm: largest |MLD| within the run, mm.
        sign: "medial" if MLD > 0 (medial gap larger), "lateral" otherwise.
        flexion_deg: flexion at the frame of that largest |MLD|, degrees (negative =
            hyperextension).
    """

    first_frame: int
    last_frame: int
    max_abs_mld_mm: float
    sign: Literal["medial", "lateral"]
    flexion_deg: float

    @property
    def frame_text(self) -> str:
        """ "frame 5" for a single frame, "frames 12–17" for a run."""
        if self.first_frame == self.last_frame:
            return f"frame {self.first_frame}"
        return f"frames {self.first_frame}–{self.last_frame}"


def flag_runs(kin: KneeKinematics) -> list[FlagRun]:
    """Group consecutive flagged frames into runs.

    Frames are consecutive when adjacent in the arrays (frame numbers may skip). A run also ends
    where the MLD changes sign, so each run has one direction (medial or lateral gap larger).

    Args:
        kin: per-frame knee metrics.

    Returns:
        The runs in frame order; empty if no frame is flagged.
    """
    mld = kin.mld_mm
    flagged = kin.flagged
    medial = mld > 0
    runs: list[FlagRun] = []
    start: int | None = None
    for i in range(len(mld)):
        if start is not None and not (flagged[i] and medial[i] == medial[start]):
            runs.append(_run(kin, start, i - 1))
            start = None
        if start is None and flagged[i]:
            start = i
    if start is not None:
        runs.append(_run(kin, start, len(mld) - 1))
    return runs


def _run(kin: KneeKinematics, first: int, last: int) -> FlagRun:
    """The FlagRun over array indices first..last inclusive."""
    abs_mld = np.abs(kin.mld_mm[first : last + 1])
    peak = first + int(np.argmax(abs_mld))
    return FlagRun(
        first_frame=int(kin.frames[first]),
        last_frame=int(kin.frames[last]),
        max_abs_mld_mm=float(abs_mld.max()),
        sign="medial" if kin.mld_mm[peak] > 0 else "lateral",
        flexion_deg=float(kin.flexion_deg[peak]),
    )


def frames_text(frames: list[int]) -> str:
    """Frame numbers in words, runs joined: "frame 5", "frames 7–11", "frames 3, 7–11".

    Args:
        frames: Frame numbers, ascending.

    Returns:
        The text ("" for none).
    """
    if not frames:
        return ""
    runs: list[list[int]] = []
    for frame in frames:
        if runs and frame == runs[-1][-1] + 1:
            runs[-1].append(frame)
        else:
            runs.append([frame])
    parts = [str(r[0]) if len(r) == 1 else f"{r[0]}–{r[-1]}" for r in runs]
    return ("frame " if len(frames) == 1 else "frames ") + ", ".join(parts)


def exclusion_sentences(kin: KneeKinematics) -> list[str]:
    """What was not measured, grouped by what went wrong: "tibial tray not tracked in frames
    7–11" (empty when every frame is measured).

    Args:
        kin: per-frame knee metrics.
    """
    grouped: dict[str, list[int]] = {}
    for frame, exclusion in zip(kin.frames, kin.excluded or (), strict=False):
        if exclusion is not None:
            grouped.setdefault(exclusion.what, []).append(int(frame))
    return [f"{what} in {frames_text(frames)}" for what, frames in grouped.items()]


def measured_text(kin: KneeKinematics) -> str:
    """Which frames the metrics come from: "tibial tray not tracked in frames 7–11: metrics
    from 7 of 12 frames", or "all 12 frames measured".

    Args:
        kin: per-frame knee metrics.
    """
    total, measured = len(kin.frames), int(kin.measured.sum())
    if measured == total:
        return f"all {total} frames measured"
    return "; ".join(exclusion_sentences(kin)) + f": metrics from {measured} of {total} frames"


def insufficient_text(kin: KneeKinematics) -> str:
    """The sentence that replaces every clinical flag when too few frames are measured."""
    return (
        f"Tracking insufficient: {measured_text(kin)} (a clinical flag needs at least "
        f"{MIN_MEASURED_SHARE:.0%} of them): repeat or correct the registration."
    )


def angle_text(flexion_deg: float) -> str:
    """A knee angle in words: "35° flexion", or "8° extension" for hyperextension (negative).

    Args:
        flexion_deg: flexion angle, degrees (negative = hyperextension).

    Returns:
        The angle rounded to whole degrees.
    """
    rounded = round(flexion_deg)
    if rounded < 0:
        return f"{-rounded}° extension"
    return f"{rounded}° flexion"


_DIRECTION = {
    "medial": "medial gap larger — suspect medial laxity / lateral tightness",
    "lateral": "lateral gap larger — suspect lateral laxity / medial tightness",
}


def describe_flags(kin: KneeKinematics) -> list[str]:
    """Sentences summarising the MLD flags and the DDV, for the report.

    One sentence per flag run, then one on the number of flagged frames and the DDV; or, if no
    frame is flagged, a single sentence with the largest |MLD| and the DDV.

    Args:
        kin: per-frame knee metrics.

    Returns:
        Plain-text sentences (Unicode dashes, degree and squared signs); when too few frames
        are measured, only :func:`insufficient_text`.
    """
    if not kin.sufficient:
        return [insufficient_text(kin)]
    limit = f"{kin.flag_mm:g} mm"
    runs = flag_runs(kin)
    ddv = f"{kin.ddv_mm2:.2f} mm²"
    left_out = [f"Not measured: {s}." for s in exclusion_sentences(kin)]
    unloaded = kin.over_limit & ~kin.loaded
    if unloaded.any():
        left_out.append(
            f"{frames_text([int(f) for f in kin.frames[unloaded]]).capitalize()}: |MLD| above "
            f"{limit} with neither condyle within {LOADED_GAP_MM:g} mm of the plateau (the knee "
            "bears no weight there): not flagged."
        )
    if not runs:
        max_abs = float(np.nanmax(np.abs(kin.mld_mm)))
        return [
            f"No medial–lateral difference above {limit} over the measured frames "
            f"(max |MLD| {max_abs:.1f} mm); DDV {ddv}.",
            *left_out,
        ]
    sentences = [
        f"Medial–lateral difference above {limit} in {run.frame_text} "
        f"(max {run.max_abs_mld_mm:.1f} mm at {angle_text(run.flexion_deg)}): "
        f"{_DIRECTION[run.sign]} (ligament imbalance) or malalignment; "
        "a flag for review, not a diagnosis."
        for run in runs
    ]
    n_flagged = int(np.count_nonzero(kin.flagged))
    sentences.append(
        f"{n_flagged} of {int(kin.measured.sum())} measured frames flagged; distance difference "
        f"variance (DDV) over them {ddv}."
    )
    return sentences + left_out
