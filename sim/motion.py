"""Ground-truth knee motions of the phantom: per-frame bone poses relative to the static scan.

A motion is flexion from 0 to ``max_flexion_deg`` and back over ``frames`` frames, the tibia
standing still (weight-bearing) and the femur, patella rolling as the phantom's flexion model
moves them, plus an optional varus tilt of the femur about the tibia's anterior-posterior axis
through the knee centre in chosen frames (a medial-lateral imbalance of known size).
Poses are ``T_world_bone`` from the reference (flexion 0) pose, as registration reports them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from sim.phantoms.knee import KneePhantomSpec, knee_bone_poses, knee_landmarks

BONES = ("femur", "tibia", "fibula", "patella")


@dataclass(frozen=True)
class KneeMotion:
    """Frames, the true flexion and varus per frame, and each bone's poses (F, 4, 4)."""

    frames: np.ndarray
    flexion_deg: np.ndarray
    varus_deg: np.ndarray
    poses: dict[str, np.ndarray]


def flexion_extension(
    spec: KneePhantomSpec,
    frames: int = 30,
    max_flexion_deg: float = 90.0,
    varus_deg: float = 0.0,
    varus_frames: tuple[int, int] | None = None,
) -> KneeMotion:
    """Flexion 0 -> max -> 0 (cosine profile) with ``varus_deg`` in frames
    ``varus_frames`` = (first, last) inclusive (all frames when None)."""
    if frames < 2:
        raise ValueError(f"frames must be >= 2, got {frames}")
    phase = np.linspace(0.0, 2.0 * np.pi, frames)
    flexion = 0.5 * max_flexion_deg * (1.0 - np.cos(phase))
    varus = np.zeros(frames)
    first, last = (0, frames - 1) if varus_frames is None else varus_frames
    varus[first : last + 1] = varus_deg
    sign = 1.0 if spec.side == "right" else -1.0  # medial is +x for a right knee
    reference = knee_bone_poses(spec)
    inverse = {b: np.linalg.inv(reference[b]) for b in BONES}
    poses = {b: np.empty((frames, 4, 4)) for b in BONES}
    for k, (angle, tilt) in enumerate(zip(flexion, varus, strict=True)):
        flexed = spec.model_copy(update={"flexion_deg": float(angle)})
        world = knee_bone_poses(flexed)
        center = knee_landmarks(flexed)["knee_center"]
        # varus: the medial condyle drops, rotating about the tibia's AP axis (world y here)
        tilt_T = np.eye(4)
        tilt_T[:3, :3] = Rotation.from_euler("y", sign * tilt, degrees=True).as_matrix()
        tilt_T[:3, 3] = center - tilt_T[:3, :3] @ center
        for bone in BONES:
            moved = world[bone] @ inverse[bone]
            poses[bone][k] = tilt_T @ moved if bone in ("femur", "patella") else moved
    return KneeMotion(np.arange(frames), flexion, varus, poses)
