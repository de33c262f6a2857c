"""Clearance along motions, with a sampling that cannot step over an obstacle.

Between two samples of a motion, no point of any moving body travels farther than

    bound = |d lift| + sum_j R_j * arc_j,    arc_j <= |d q_j| + a_max,j * dt^2 / 4,

where ``R_j`` bounds the distance from joint j's axis to anything it carries (the sum of the
link lengths, tool offset and shape sizes downstream: true in every configuration) and
``arc_j`` bounds the joint's travel over the interval even if it turns back within it. Samples
are added until every interval's bound is at most :data:`RESOLUTION_M`; two bodies then come
at most that much closer than at the nearer sample, so the clearance along the whole motion
is at least the smallest sampled clearance minus the resolution.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from trajectories.arms import ARMS
from trajectories.model import ScannerModel
from trajectories.timing import TimedPath

RESOLUTION_M = 0.005
"""Largest travel of any body point between checked samples, metres."""


@dataclass(frozen=True)
class Clearance:
    """The closest approach along a motion.

    Attributes:
        distance_m: smallest sampled clearance (negative: penetration).
        time_s: when (on the motion's own clock).
        pair: the two collision objects involved.
        samples: how many configurations were checked.
    """

    distance_m: float
    time_s: float
    pair: tuple[str, str]
    samples: int


def reach_bounds(model: ScannerModel) -> np.ndarray:
    """``R_j`` per joint (metres; the lift's entry is 1, a pure translation factor)."""
    config = model.config
    bounds = np.zeros(model.model.nv)
    bounds[model.index["lift"]] = 1.0
    farthest = 0.0
    for role, arm in model.arms():
        spec = ARMS[arm.model]
        links = [np.hypot(spec.d_m[k], spec.a_m[k]) for k in range(6)]
        tool = np.linalg.norm(np.asarray(arm.tool.xyz_mm)) / 1000.0
        extent = _tool_extent_m(model, role)
        for k, name in enumerate(
            ("shoulder_pan", "shoulder_lift", "elbow", "wrist_1", "wrist_2", "wrist_3")
        ):
            bounds[model.index[f"{role}_{name}"]] = sum(links[k:]) + tool + extent
        mount = np.asarray(arm.mount.xyz_mm) / 1000.0
        farthest = max(farthest, np.hypot(mount[0], mount[1]) + sum(links) + tool + extent)
    column = config.obstacles.column
    cx, cy, _ = (c / 1000.0 for c in column.center_mm)
    sx, sy, _ = (s / 2000.0 for s in column.size_mm)
    farthest = max(farthest, np.hypot(abs(cx) + sx, abs(cy) + sy))
    bounds[model.index["rotary"]] = farthest
    return bounds


def _tool_extent_m(model: ScannerModel, role: str) -> float:
    """Half-diagonal of the tool's collision box plus the thickest link radius, metres."""
    config = model.config
    if role == "source":
        size = np.asarray(config.tube.housing.size_mm) / 1000.0
        offset = np.linalg.norm(config.tube.housing.center_mm) / 1000.0
    else:
        panel = config.panel
        size = (
            np.array([panel.pixels.width_mm, panel.pixels.height_mm, panel.housing_thickness_mm])
            / 1000.0
            + 2 * panel.housing_border_mm / 1000
        )
        offset = panel.housing_thickness_mm / 2000.0
    arm = config.source_arm if role == "source" else config.detector_arm
    return float(0.5 * np.linalg.norm(size) + offset + max(ARMS[arm.model].link_radius_m))


def motion_clearance(model: ScannerModel, path: TimedPath, evaluate) -> Clearance:
    """Smallest clearance along ``path``, refining its samples to :data:`RESOLUTION_M`.

    ``evaluate(t)`` returns the configurations at the times ``t`` (len(t), nq) (the path's own
    trajectory); new samples go into every interval whose travel bound exceeds the resolution
    until none does.
    """
    bounds = reach_bounds(model)
    amax = model.limits.acceleration
    times = np.asarray(path.t_s, dtype=np.float64)
    qs = np.asarray(path.q, dtype=np.float64)
    while True:
        dt = np.diff(times)
        arcs = np.abs(np.diff(qs, axis=0)) + amax * (dt[:, None] ** 2) / 4.0
        travel = arcs @ bounds
        split = np.flatnonzero(travel > RESOLUTION_M)
        if split.size == 0:
            break
        new_t = np.concatenate(
            [
                np.linspace(times[i], times[i + 1], int(np.ceil(travel[i] / RESOLUTION_M)) + 1)[
                    1:-1
                ]
                for i in split
            ]
        )
        new_q = np.atleast_2d(evaluate(new_t))
        order = np.argsort(np.concatenate((times, new_t)), kind="stable")
        times = np.concatenate((times, new_t))[order]
        qs = np.concatenate((qs, new_q))[order]
    best = (np.inf, 0.0, ("", ""))
    for t, q in zip(times, qs, strict=True):
        distance, a, b = model.clearance(q)
        if distance < best[0]:
            best = (distance, float(t), (a, b))
    return Clearance(best[0], best[1], best[2], len(times))
