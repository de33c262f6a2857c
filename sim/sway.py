"""A standing patient's sway during the static scan: per-body rigid poses over time.

A standing person is an inverted pendulum over the ankles. Two bodies move:

- the shank (tibia, fibula and the soft tissue below the joint line) tilts about the ankle
  centre, anterior-posterior (about world x) and medial-lateral (about world y), and twists a
  little about its long axis (world z through the ankle);
- the thigh (femur, patella and the soft tissue above the joint line) rides on the shank and
  adds a knee-flexion wobble about the transepicondylar axis (TEA, through the knee centre)
  and a rotation about the long axis, so the two move differently.

Each angle is a slow drift (three sinusoids of 0.05-0.3 Hz) plus a tremor (two of 1-4 Hz, at
``tremor_share`` of the drift's amplitude), with random phases and weights drawn per seed, and
zero mean over the scan: the reference pose (where the phantom is built) is the patient's
average pose, which is also the pose a motion-compensated reconstruction shows. The angles are
then scaled so that the largest displacement of the knee's points (knee centre, patella
centre, tibial plateau centre, and the femoral and tibial shafts 60 mm from the joint line)
over the scan equals ``peak_mm``: "standing" is ~1-2 mm, "semi-flexed" ~3-5 mm.

Poses are ``T_world_body`` (4x4, mm) from the reference pose, as registration reports them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.spatial.transform import Rotation

from recon.geometry import View
from recon.motion import BodyMotion
from recon.project import JosephProjector
from recon.volume import Volume
from registration.labels import LABELS
from sim.phantoms.knee import KneePhantomSpec, knee_bone_poses, knee_landmarks

BODIES: tuple[str, ...] = ("thigh", "shank")
"""The bodies that move apart: above and below the joint line."""

BODY_BONES: dict[str, tuple[str, ...]] = {
    "thigh": ("femur", "patella"),
    "shank": ("tibia", "fibula"),
}
"""The bones each body carries."""

DRIFT_HZ = (0.05, 0.3)
TREMOR_HZ = (1.0, 4.0)
SHAFT_MM = 60.0
"""Distance of the shaft points from the joint line that size the sway, mm."""

SOFT_TISSUE_BLEND_MM = 10.0
"""Soft tissue hands over from the shank to the thigh over this height about the joint line."""

# relative amplitudes of the five angles before scaling (degrees): the shank's tilts dominate
_UNIT_DEG = {"ap": 1.0, "ml": 0.7, "twist": 0.4, "flex": 0.8, "rotation": 0.4}


class SwaySpec(BaseModel):
    """How much a simulated patient sways during a scan (0 mm: perfectly still)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    peak_mm: float = Field(
        0.0,
        ge=0.0,
        le=20.0,
        description="largest displacement at the knee over the scan, mm (standing ~1-2, "
        "semi-flexed ~3-5; 0: still)",
    )
    tremor_share: float = Field(
        0.1, ge=0.0, le=0.5, description="tremor amplitude as a share of the drift's"
    )
    seed: int = Field(0, description="the sway pattern (repeats per seed)")


def _waves(rng: np.random.Generator, band: tuple[float, float], count: int) -> np.ndarray:
    """(count, 3) rows of (frequency Hz, amplitude, phase rad), amplitudes summing to 1."""
    freq = rng.uniform(*band, count)
    amp = rng.uniform(0.5, 1.0, count)
    return np.column_stack((freq, amp / amp.sum(), rng.uniform(0, 2 * np.pi, count)))


def _rotation_about(rotvec_rad: np.ndarray, point_mm: np.ndarray) -> np.ndarray:
    """(N, 4, 4) rotations by the rotation vectors (N, 3) about lines through ``point_mm``."""
    T = np.tile(np.eye(4), (len(rotvec_rad), 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(rotvec_rad).as_matrix()
    T[:, :3, 3] = point_mm - T[:, :3, :3] @ point_mm
    return T


@dataclass(frozen=True)
class SwayPivots:
    """Where a leg sways about, and the points that size the sway (world mm, reference pose).

    Attributes:
        ankle_mm: the ankle's centre, the shank's tilts' pivot.
        knee_mm: the knee's centre, the thigh's wobble's pivot.
        tea: the transepicondylar axis (unit), the flexion wobble's axis.
        patella_mm: the patella's centre.
        plateau_mm: the tibial plateau's centre.
    """

    ankle_mm: np.ndarray
    knee_mm: np.ndarray
    tea: np.ndarray
    patella_mm: np.ndarray
    plateau_mm: np.ndarray

    @classmethod
    def of_knee(cls, phantom: KneePhantomSpec) -> SwayPivots:
        """The knee phantom's landmarks."""
        marks = knee_landmarks(phantom)
        return cls(
            marks["ankle_center"],
            marks["knee_center"],
            knee_bone_poses(phantom)["femur"][:3, 0],
            marks["patella_center"],
            marks["tibial_plateau_center"],
        )


@dataclass(frozen=True)
class Sway:
    """The sway of one scan of ``duration_s`` seconds: :meth:`poses` at any time in it.

    Args:
        spec: size and pattern.
        pivots: the leg's ankle, knee centre and axes.
        duration_s: the scan's length, s (the angles have zero mean over it).
    """

    spec: SwaySpec
    pivots: SwayPivots
    duration_s: float

    def __post_init__(self) -> None:
        if not self.duration_s > 0:
            raise ValueError(f"duration_s must be > 0 s, got {self.duration_s!r}")
        rng = np.random.default_rng([self.spec.seed, 5])
        waves = {name: (_waves(rng, DRIFT_HZ, 3), _waves(rng, TREMOR_HZ, 2)) for name in _UNIT_DEG}
        object.__setattr__(self, "_waves", waves)
        t = np.linspace(0.0, self.duration_s, 2001)
        mean = {k: float(v.mean()) for k, v in self._waved(t).items()}
        object.__setattr__(self, "_mean", mean)
        object.__setattr__(self, "_scale", 1.0)
        if self.spec.peak_mm > 0:
            for _ in range(3):  # displacement is nearly linear in the small angles
                moved = self.peak_displacement_mm(t)
                object.__setattr__(self, "_scale", self._scale * self.spec.peak_mm / moved)
        else:
            object.__setattr__(self, "_scale", 0.0)

    def _waved(self, t_s: np.ndarray) -> dict[str, np.ndarray]:
        """Unscaled angles (degrees) per time: the sums of their drift and tremor waves."""
        out = {}
        for name, (drift, tremor) in self._waves.items():
            rows = np.vstack((drift, tremor * np.array([1.0, self.spec.tremor_share, 1.0])))
            phase = 2 * np.pi * rows[:, 0, None] * t_s[None] + rows[:, 2, None]
            out[name] = _UNIT_DEG[name] * (rows[:, 1, None] * np.sin(phase)).sum(axis=0)
        return out

    def _angles(self, t_s: np.ndarray) -> dict[str, np.ndarray]:
        """Unscaled angles (degrees) per time, zero mean over the scan."""
        return {k: v - self._mean[k] for k, v in self._waved(t_s).items()}

    def angles_deg(self, t_s: np.ndarray) -> dict[str, np.ndarray]:
        """The five angles (degrees) at times ``t_s`` (s from the scan's start): the shank's
        ``ap``, ``ml`` tilts and ``twist``, the thigh's ``flex`` wobble and ``rotation``."""
        return {k: self._scale * v for k, v in self._angles(np.asarray(t_s, float)).items()}

    def poses(self, t_s: np.ndarray) -> dict[str, np.ndarray]:
        """``T_world_body`` (N, 4, 4) of "thigh" and "shank" at times ``t_s`` (N,), s."""
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        a = {k: np.radians(v) for k, v in self.angles_deg(t).items()}
        ankle, knee, tea = self.pivots.ankle_mm, self.pivots.knee_mm, self.pivots.tea
        zero = np.zeros_like(t)
        tilt = _rotation_about(np.column_stack((a["ap"], a["ml"], zero)), ankle)
        twist = _rotation_about(np.column_stack((zero, zero, a["twist"])), ankle)
        shank = tilt @ twist
        wobble = _rotation_about(a["flex"][:, None] * tea, knee) @ _rotation_about(
            np.column_stack((zero, zero, a["rotation"])), knee
        )
        return {"thigh": shank @ wobble, "shank": shank}

    def size_points(self) -> dict[str, np.ndarray]:
        """The points (world mm, reference pose) whose displacement sizes the sway, per body."""
        knee, plateau = self.pivots.knee_mm, self.pivots.plateau_mm
        up = np.array([0.0, 0.0, SHAFT_MM])
        return {
            "thigh": np.stack((knee, self.pivots.patella_mm, plateau + up)),
            "shank": np.stack((plateau, knee, plateau - up)),
        }

    def displacement_mm(self, t_s: np.ndarray) -> dict[str, np.ndarray]:
        """Largest displacement of each body's sizing points per time, mm (N,)."""
        poses = self.poses(t_s)
        motion = BodyMotion(BODIES, np.stack([poses[b] for b in BODIES], axis=1))
        moved = motion.displacement_mm(self.size_points())
        return {b: moved[:, k] for k, b in enumerate(BODIES)}

    def peak_displacement_mm(self, t_s: np.ndarray | None = None) -> float:
        """Largest displacement of any body's sizing points over ``t_s`` (default: the scan)."""
        t = np.linspace(0.0, self.duration_s, 2001) if t_s is None else np.asarray(t_s)
        return float(max(d.max() for d in self.displacement_mm(t).values()))


def body_volumes(mu: Volume, labels: Volume, joint_line_z_mm: float) -> dict[str, np.ndarray]:
    """The attenuation split between the thigh and the shank (their sum is ``mu``).

    Bones go whole to their body (:data:`BODY_BONES`, by label); soft tissue and air go to the
    thigh above the joint line and to the shank below it, handed over by a raised cosine over
    :data:`SOFT_TISSUE_BLEND_MM` (the skin stretches, it does not tear).
    """
    z = mu.grid.axes_mm()[2]
    s = np.clip((z - joint_line_z_mm) / SOFT_TISSUE_BLEND_MM + 0.5, 0.0, 1.0)
    upper = (np.sin(0.5 * np.pi * s) ** 2).astype(np.float32)[:, None, None]
    thigh = np.broadcast_to(upper, mu.data.shape).copy()
    for body, bones in BODY_BONES.items():
        inside = np.isin(labels.data, [LABELS[b] for b in bones])
        thigh[inside] = 1.0 if body == "thigh" else 0.0
    data = np.asarray(mu.data, dtype=np.float32)
    return {"thigh": data * thigh, "shank": data * (1.0 - thigh)}


class SwayingSubject:
    """What the simulated panel sees of a swaying patient: the bodies' poses at any clock time.

    Times are the clock's; the sway starts at the first pulse rendered (the scan's start).
    """

    def __init__(self, sway: Sway) -> None:
        self.sway = sway
        self.start_s: float | None = None

    def poses_at(self, t_s: float) -> dict[str, np.ndarray]:
        """``T_world_body`` (4x4) of each body at clock time ``t_s``."""
        if self.start_s is None:
            self.start_s = t_s
        poses = self.sway.poses(np.array([t_s - self.start_s]))
        return {b: poses[b][0] for b in BODIES}


class SwayingKnee(SwayingSubject):
    """The knee phantom while the patient sways: each body projected at its pose at the
    pulse's time, summed (line integrals add)."""

    def __init__(self, mu: Volume, labels: Volume, phantom: KneePhantomSpec, sway: Sway) -> None:
        super().__init__(sway)
        parts = body_volumes(mu, labels, phantom.joint_line_height_mm)
        self._projectors = {b: JosephProjector(parts[b], mu.grid) for b in BODIES}

    def __call__(self, view: View, t_s: float = 0.0) -> np.ndarray:
        poses = self.poses_at(t_s)
        return sum(self._projectors[b].project_moved(view, poses[b]) for b in BODIES)
