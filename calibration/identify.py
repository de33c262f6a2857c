"""Which ball is which, from one view alone (no knowledge of the view's geometry).

1. Sizes: the blobs' masses split into two clusters (the code has both sizes in every view);
   blobs far above the large cluster are merged balls, far below the small one are noise, and
   elongated blobs are overlaps; all are dropped.
2. Order: consecutive balls on the helix differ little in depth, so their shadows keep the
   helix's order along the rows (v). Each gap, divided by the local ball step (which drifts
   once per turn with the magnification, and is fitted as such), rounds to a whole number of
   steps, so a missing ball shows as a double step.
3. Offset: the sizes of the ordered balls, placed at their relative steps, are slid along the
   code; the offset where every size matches, and no other offset does, names every ball
   (the code's windows of :data:`~calibration.phantom.CODE_WINDOW` balls are unique).

Views where this is ambiguous identify nothing rather than guess.
"""

from __future__ import annotations

import numpy as np

from calibration.detect import Detections
from calibration.phantom import CODE_WINDOW

MAX_ELONGATION = 1.6
"""Blobs more elongated than this are overlapping balls."""

MAX_STEP_ERROR = 0.3
"""A gap must be within this fraction of a whole number of ball steps."""


def identify(detections: Detections, code: str, balls_per_turn: float) -> np.ndarray:
    """Ball index (into ``code``) of each detection, or -1 where unidentified (K,).

    ``balls_per_turn`` (360 / the helix's angle step) sets the period of the step's drift.
    """
    ids = np.full(len(detections), -1)
    keep = np.flatnonzero(detections.elongation <= MAX_ELONGATION)
    if len(keep) < CODE_WINDOW:
        return ids
    log_mass = np.log(detections.mass[keep])
    small, large = _two_clusters(log_mass)
    if large - small < np.log(1.8):  # sizes differ by (3/2)^3 = 3.4 in mass
        return ids
    split = 0.5 * (small + large)
    plausible = (log_mass > small - 0.5) & (log_mass < large + 0.5)
    keep = keep[plausible]
    is_large = (np.log(detections.mass[keep]) > split).astype(int)
    order = np.argsort(detections.uv[keep, 1])
    keep, is_large = keep[order], is_large[order]
    gaps = np.diff(detections.uv[keep, 1])
    if len(gaps) < CODE_WINDOW - 1:
        return ids
    steps, whole = _ball_steps(gaps, balls_per_turn)
    if np.any(whole < 1) or np.any(np.abs(steps - whole) > MAX_STEP_ERROR * whole):
        return ids
    relative = np.concatenate(([0], np.cumsum(whole).astype(int)))
    pattern = np.array([int(c) for c in code])
    offsets = [
        o
        for o in range(-relative[-1], len(code))
        if o + relative[0] >= 0
        and o + relative[-1] < len(code)
        and np.array_equal(pattern[o + relative], is_large)
    ]
    if len(offsets) == 1:
        ids[keep] = offsets[0] + relative
    return ids


def _ball_steps(gaps: np.ndarray, balls_per_turn: float) -> tuple[np.ndarray, np.ndarray]:
    """Each gap in units of the local ball step, and its nearest whole number of steps.

    The step drifts along the helix as the balls' depth (magnification) changes once per
    turn: it is modelled as a + b i + c sin(2 pi i / P) + d cos(2 pi i / P) in the ball index
    i, fitted to the gaps divided by their whole step counts, a few rounds from the median.
    """
    unit = np.full(len(gaps), np.median(gaps))
    for _ in range(5):
        whole = np.maximum(np.rint(gaps / unit), 1.0)
        index = np.cumsum(whole) - 0.5 * whole
        phase = 2 * np.pi * index / balls_per_turn
        design = np.column_stack((np.ones_like(index), index, np.sin(phase), np.cos(phase)))
        weight = np.sqrt(whole)
        coef, *_ = np.linalg.lstsq(design * weight[:, None], gaps / whole * weight, rcond=None)
        unit = design @ coef
        if np.any(unit <= 0):
            return np.full(len(gaps), np.inf), np.zeros(len(gaps))
    return gaps / unit, np.rint(gaps / unit)


def _two_clusters(values: np.ndarray) -> tuple[float, float]:
    """Centres of a 1-D two-means clustering (low, high)."""
    low, high = np.percentile(values, 10), np.percentile(values, 90)
    for _ in range(20):
        split = 0.5 * (low + high)
        a, b = values[values <= split], values[values > split]
        if len(a) == 0 or len(b) == 0:
            break
        low, high = float(a.mean()), float(b.mean())
    return low, high
