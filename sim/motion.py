"""Ground-truth knee motions of the phantom: per-frame bone poses relative to the static scan.

Poses are ``T_world_body`` (4x4, mm) moving each bone from its reference pose (where the static
scan, ``spec``, saw it) to the frame, as registration reports them. Every motion gives poses
for "femur", "tibia", "fibula", "patella" and "tibia_fibula" (the tibia and fibula move as one
body, so its pose is the tibia's), and the true knee flexion per frame: the angle between the
femoral and tibial long axes (bone-local z) about the transepicondylar axis (TEA, femoral local
x), positive when the femoral shaft swings posteriorly relative to the tibia.

- :func:`flexion_extension`: the tibia stands still (weight-bearing) and the femur and patella
  roll as the phantom's flexion model moves them, plus an optional varus tilt of the femur about
  the tibia's anterior-posterior axis through the knee centre in chosen frames (a
  medial-lateral imbalance of known size).
- :func:`squat_motion`: a squat (knee bend) with the whole leg moving in the world and the
  coupled motions of a healthy knee: femoral rollback, tibial internal rotation with flexion,
  the patella tracking the trochlea. See its docstring for the conventions and sizes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from sim.phantoms.knee import KneePhantomSpec, knee_bone_poses, knee_landmarks

BONES = ("femur", "tibia", "fibula", "patella")
"""The phantom's bones; every motion also carries ``"tibia_fibula"`` (= the tibia's pose)."""

_MAX_FLEXION_DEG = 90.0  # the phantom's flexion model holds from -10 to 90 degrees
_MAX_HYPEREXTENSION_DEG = 10.0
_SEED_FLEXION_RANGE = (0.9, 1.0)  # factor on max_flexion_deg drawn per seed
_SEED_COUPLING_RANGE = (0.8, 1.2)  # factor on rollback, rotation, lean, hyperextension
_SEED_PEAK_RANGE = (0.4, 0.6)  # share of the sequence at which flexion peaks


@dataclass(frozen=True)
class KneeMotion:
    """A knee motion and its ground truth.

    Attributes:
        frames: frame numbers (F,).
        flexion_deg: knee flexion per frame, degrees (F,); negative = hyperextension.
        varus_deg: varus tilt of the femur per frame, degrees (F,).
        poses: bone -> ``T_world_body`` (F, 4, 4) from the reference pose, mm.
        rollback_mm: posterior translation of the femur (its TEA midpoint) on the tibia along
            the tibia's posterior axis, relative to the phantom's flexion model, mm (F,).
        tibial_rotation_deg: internal rotation of the tibia relative to the femur about the
            tibia's long axis, relative to the phantom's flexion model, degrees (F,).
        knee_center_mm: world position of the TEA midpoint per frame, mm (F, 3).
    """

    frames: np.ndarray
    flexion_deg: np.ndarray
    varus_deg: np.ndarray
    poses: dict[str, np.ndarray]
    rollback_mm: np.ndarray
    tibial_rotation_deg: np.ndarray
    knee_center_mm: np.ndarray


def _rotation_about(axis: str, angle_deg: float, point_mm: np.ndarray) -> np.ndarray:
    """4x4 rotation by ``angle_deg`` about a line parallel to world ``axis`` through a point."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler(axis, angle_deg, degrees=True).as_matrix()
    T[:3, 3] = point_mm - T[:3, :3] @ point_mm
    return T


def _check_frames(frames: int) -> None:
    if int(frames) != frames or frames < 2:
        raise ValueError(f"frames must be an integer >= 2, got {frames!r}")


def flexion_extension(
    spec: KneePhantomSpec,
    frames: int = 30,
    max_flexion_deg: float = 90.0,
    varus_deg: float = 0.0,
    varus_frames: tuple[int, int] | None = None,
) -> KneeMotion:
    """Flexion 0 -> max -> 0 (cosine profile) with ``varus_deg`` in frames
    ``varus_frames`` = (first, last) inclusive (all frames when None): the femur turned about
    its medial condyle's contact, the lateral condyle lifted off; the tibia stands still.
    """
    _check_frames(frames)
    phase = np.linspace(0.0, 2.0 * np.pi, frames)
    flexion = 0.5 * max_flexion_deg * (1.0 - np.cos(phase))
    varus = np.zeros(frames)
    first, last = (0, frames - 1) if varus_frames is None else varus_frames
    varus[first : last + 1] = varus_deg
    sign = 1.0 if spec.side == "right" else -1.0  # medial is +x for a right knee
    reference = knee_bone_poses(spec)
    inverse = {b: np.linalg.inv(reference[b]) for b in BONES}
    poses = {b: np.empty((frames, 4, 4)) for b in BONES}
    centers = np.empty((frames, 3))
    for k, (angle, tilt) in enumerate(zip(flexion, varus, strict=True)):
        flexed = spec.model_copy(update={"flexion_deg": float(angle)})
        world = knee_bone_poses(flexed)
        landmarks = knee_landmarks(flexed)
        centers[k] = landmarks["knee_center"]
        # varus: the femur turns about the tibia's AP axis (world y here) through its medial
        # condyle's contact, which stays on the plateau while the lateral compartment opens
        # (a knee under load pivots on the compartment it bears on)
        tilt_T = _rotation_about("y", sign * tilt, landmarks["medial_condyle_lowest"])
        centers[k] = tilt_T[:3, :3] @ centers[k] + tilt_T[:3, 3]  # the TEA's midpoint, tilted
        for bone in BONES:
            moved = world[bone] @ inverse[bone]
            poses[bone][k] = tilt_T @ moved if bone in ("femur", "patella") else moved
    poses["tibia_fibula"] = poses["tibia"].copy()
    zeros = np.zeros(frames)
    return KneeMotion(np.arange(frames), flexion, varus, poses, zeros, zeros.copy(), centers)


@dataclass(frozen=True)
class _SquatAmplitudes:
    max_flexion_deg: float
    hyperextension_deg: float
    rollback_mm_per_deg: float
    tibial_rotation_deg: float
    shank_lean: float
    peak: float  # share of the sequence at which flexion peaks


def _squat_amplitudes(nominal: _SquatAmplitudes, seed: int | None) -> _SquatAmplitudes:
    if seed is None:
        return nominal
    rng = np.random.default_rng(seed)
    lo, hi = _SEED_COUPLING_RANGE
    return _SquatAmplitudes(
        max_flexion_deg=nominal.max_flexion_deg * rng.uniform(*_SEED_FLEXION_RANGE),
        hyperextension_deg=min(
            nominal.hyperextension_deg * rng.uniform(lo, hi), _MAX_HYPEREXTENSION_DEG
        ),
        rollback_mm_per_deg=nominal.rollback_mm_per_deg * rng.uniform(lo, hi),
        tibial_rotation_deg=nominal.tibial_rotation_deg * rng.uniform(lo, hi),
        shank_lean=nominal.shank_lean * rng.uniform(lo, hi),
        peak=rng.uniform(*_SEED_PEAK_RANGE),
    )


def _squat_profile(frames: int, a: _SquatAmplitudes) -> np.ndarray:
    """Flexion (F,) deg: -hyperextension -> max (at share ``peak``) -> -hyperextension, each
    half a half-cosine, so the angular velocity is zero at both ends and at the peak."""
    s = np.linspace(0.0, 1.0, frames)
    rise = np.where(s <= a.peak, s / a.peak, (1.0 - s) / (1.0 - a.peak))
    low = -a.hyperextension_deg
    return low + (a.max_flexion_deg - low) * 0.5 * (1.0 - np.cos(np.pi * rise))


def squat_motion(
    spec: KneePhantomSpec,
    frames: int = 30,
    max_flexion_deg: float = 90.0,
    hyperextension_deg: float = 0.0,
    rollback_mm_per_deg: float = 0.12,
    tibial_rotation_deg: float = 5.0,
    shank_lean: float = 0.1,
    seed: int | None = None,
) -> KneeMotion:
    """A weight-bearing squat: the knee bends and straightens while the whole leg moves.

    Flexion runs from ``-hyperextension_deg`` up to ``max_flexion_deg`` and back (half-cosine
    ramps, zero angular velocity at the ends and at the peak). At flexion ``f`` degrees:

    - the femur and patella take the phantom's flexion model relative to the tibia (the femur
      turns by ``f`` about its TEA; the patella slides along the trochlea and turns by 0.7 f);
    - femoral rollback: the femur and patella then translate by ``rollback_mm_per_deg * f`` mm
      along the tibia's posterior axis (local +y);
    - tibial internal rotation (the screw-home mechanism reversed): the tibia turns internally
      relative to the femur by ``tibial_rotation_deg * f / 90`` degrees about its long axis
      (local z through the plateau centre), i.e. the femur and patella turn externally about
      it; internal = the tibial tuberosity turns medially;
    - the shank leans forward: the tibia and fibula (with the knee) rotate about the ankle
      centre, about the world medial-lateral (x) axis, by ``shank_lean * f`` degrees, the knee
      moving anteriorly (-y); the femur completes the knee flexion, so it tilts posteriorly in
      the world by ``(1 - shank_lean) * f``.

    Rollback and rotation act about the tibia's long axis and along its plateau, so the knee
    flexion (femoral vs tibial long axis about the TEA) is exactly ``f``; hyperextension
    (``f < 0``) gives an anterior femur and tibial external rotation. At the defaults and
    90 degrees: rollback 10.8 mm, tibial internal rotation 5 degrees, shank lean 9 degrees
    (the knee centre moves ~57 mm anteriorly and ~5 mm down). Larger leans are deeper,
    heel-down squats, but the knee then travels ``~435 sin(shank_lean * f)`` mm: with 0.5 it
    leaves a lateral fluoroscope's ~200 mm field (0.3 mm x 1024 pixels at magnification 1.5).

    Args:
        spec: the phantom; its pose is the reference (the static scan).
        frames: number of frames, >= 2.
        max_flexion_deg: peak flexion, (0, 90] degrees.
        hyperextension_deg: flexion at the first and last frame is ``-hyperextension_deg``,
            [0, 10] degrees.
        rollback_mm_per_deg: femoral rollback per degree of flexion, mm/degree.
        tibial_rotation_deg: tibial internal rotation at 90 degrees of flexion, degrees.
        shank_lean: forward shank lean per degree of knee flexion, [0, 1].
        seed: None for the nominal motion; an integer draws a slightly different motion
            (peak flexion x U(0.9, 1.0), rollback, rotation, lean and hyperextension each
            x U(0.8, 1.2), peak at U(0.4, 0.6) of the sequence) for benchmark sequences.

    Returns:
        The motion; ``rollback_mm`` and ``tibial_rotation_deg`` hold the values applied.
    """
    _check_frames(frames)
    if not 0.0 < max_flexion_deg <= _MAX_FLEXION_DEG:
        raise ValueError(f"max_flexion_deg must be in (0, 90] degrees, got {max_flexion_deg!r}")
    if not 0.0 <= hyperextension_deg <= _MAX_HYPEREXTENSION_DEG:
        raise ValueError(
            f"hyperextension_deg must be in [0, 10] degrees, got {hyperextension_deg!r}"
        )
    if not 0.0 <= shank_lean <= 1.0:
        raise ValueError(f"shank_lean must be in [0, 1], got {shank_lean!r}")
    if not (math.isfinite(rollback_mm_per_deg) and math.isfinite(tibial_rotation_deg)):
        raise ValueError("rollback_mm_per_deg and tibial_rotation_deg must be finite")
    amp = _squat_amplitudes(
        _SquatAmplitudes(
            max_flexion_deg,
            hyperextension_deg,
            rollback_mm_per_deg,
            tibial_rotation_deg,
            shank_lean,
            0.5,
        ),
        seed,
    )
    flexion = _squat_profile(frames, amp)
    rollback = amp.rollback_mm_per_deg * flexion
    rotation = amp.tibial_rotation_deg * flexion / 90.0
    sign = 1.0 if spec.side == "right" else -1.0  # internal rotation turns anterior to medial
    reference = knee_bone_poses(spec)
    ankle = knee_landmarks(spec)["ankle_center"]
    poses = {b: np.empty((frames, 4, 4)) for b in BONES}
    centers = np.empty((frames, 3))
    for k, f in enumerate(flexion):
        world = knee_bone_poses(spec.model_copy(update={"flexion_deg": float(f)}))
        T_tibia = world["tibia"]
        # in the tibia's frame: rollback along +y after turning the femur externally about z
        coupled = _rotation_about("z", -sign * rotation[k], np.zeros(3))
        coupled[1, 3] = rollback[k]
        T_lean = _rotation_about("x", amp.shank_lean * f, ankle)
        leaned_tibia = T_lean @ T_tibia
        for bone in BONES:
            relative = np.linalg.inv(T_tibia) @ world[bone]
            if bone in ("femur", "patella"):
                relative = coupled @ relative
            moved = leaned_tibia @ relative
            poses[bone][k] = moved @ np.linalg.inv(reference[bone])
            if bone == "femur":
                centers[k] = moved[:3, 3]
    poses["tibia_fibula"] = poses["tibia"].copy()
    return KneeMotion(
        frames=np.arange(frames),
        flexion_deg=flexion,
        varus_deg=np.zeros(frames),
        poses=poses,
        rollback_mm=rollback,
        tibial_rotation_deg=rotation,
        knee_center_mm=centers,
    )
