"""Resolution matching: the blur that makes a frame and a render alike. A DRR carries the
static scan's blur, the panel does not, and the mismatch biases depth; a mesh's render is
sharper than any frame, so its own blur is matched instead."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from registration.objective import Objective
from registration.similarity import ncc

FRAME_BLUR_MM = np.arange(0.0, 3.01, 0.5)
"""Candidate blurs of the frames along each panel axis (Gaussian sigma, mm) for resolution
matching."""
MODEL_BLUR_MM = np.arange(0.0, 1.21, 0.15)
"""Candidate blurs of a mesh's sharp render (Gaussian sigma at the panel, mm): the imaging
chain's (focal spot, panel, video) that the frames carry."""


def frame_blur(
    objective: Objective,
    T: np.ndarray,
    target: Callable[[tuple[float, float]], np.ndarray],
) -> tuple[float, float]:
    """The frames' blur along (u, v), panel mm, that maximises the body's NCC at pose ``T``
    (4x4 mm): the best pair on the :data:`FRAME_BLUR_MM` grid, each axis refined by a parabola
    through its neighbours. ``target`` gives the frame's high-passed target at a blur pair
    (the objective's level, uncropped)."""
    grid = FRAME_BLUR_MM
    pairs = [(float(u), float(v)) for u in grid for v in grid]
    image = objective.image(T)
    scores = np.array(
        [ncc(target(pair)[objective.crop], image, objective.mask) for pair in pairs]
    ).reshape(len(grid), len(grid))
    best = np.unravel_index(np.argmax(scores), scores.shape)
    return tuple(
        _parabola_peak(grid, np.take(scores, best[1 - axis], axis=1 - axis), best[axis])
        for axis in (0, 1)
    )


def model_blur(score: Callable[[float], float]) -> float:
    """A mesh's render blur (Gaussian sigma at the panel, mm) that maximises ``score`` (its
    NCC with the render blurred so): the best of :data:`MODEL_BLUR_MM`, refined by a
    parabola."""
    grid = MODEL_BLUR_MM
    scores = [score(float(blur)) for blur in grid]
    best = int(np.argmax(scores))
    return _parabola_peak(grid, np.array(scores), best)


def _parabola_peak(x: np.ndarray, y: np.ndarray, i: int) -> float:
    """The peak of the parabola through samples i-1, i, i+1 of y(x) (sample i at an end or
    without a peak between its neighbours: x[i])."""
    if i == 0 or i == len(x) - 1:
        return float(x[i])
    a, b, _ = np.polyfit(x[i - 1 : i + 2], y[i - 1 : i + 2], 2)
    return float(np.clip(-b / (2 * a), x[i - 1], x[i + 1])) if a < 0 else float(x[i])
