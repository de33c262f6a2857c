"""BoneAxis-Reg: per-bone 6-DoF 2D-3D registration of a fluoroscopy sequence (docs/system.md).

Each bone is scored against a scene DRR: the soft tissue and the other bones at their current
estimates stay fixed while one bone moves, and the similarity is NCC of high-pass filtered
images over the bone's dilated silhouette (registration.similarity). Poses are searched as
6-vectors x = (t mm, r deg) about the bone's current centroid, in world axes:
``T(x) = [R(r), (I - R(r)) c + t] T0``.

a) first frame: the bone's principal axis (PCA of its voxels) orients a bounded box, searched
   by differential evolution (global initialisation, seeded);
b) kinematic priority module (KPM), from the third frame: the pose is predicted with constant
   velocity (the last frame-to-frame motion repeated) and searched first along that motion
   (T_n = T_{n-1} exp(lambda S), lambda scanned from -1.5 to 2.5, so a reversal is found; at a
   turning point, where the last motion nearly stops, S is the motion before it); the search
   widens (a small DE box) only when the similarity after refinement says the prediction
   failed;
c) refinement: on the first frame Powell then Nelder-Mead, coarse (binned panel) to fine, and
   a second pass that refines each bone against the others' new estimates; on later frames
   Levenberg-Marquardt on the residual whose half squared norm is 1 - NCC (plus the prior),
   its Jacobian by central differences, on the coarse level in a first pass over the bones
   and on the finest in a second, where each is scored and, if it failed, searched again
   (under 30 % of the renders of the derivative-free passes, which are kept for the tracker
   without the KPM and as a setting).

A single lateral view barely sees the patella's medial-lateral shift and its tilt and spin
(depth along the ray and rotations out of the image plane; measured on the quick demo: a
valley of nearly equal NCC runs 6 mm and 15 degrees away from the truth). The patella
therefore carries a patellofemoral prior: relative to the femur it may flex about the
femur's medial-lateral axis and slide in the femur's sagittal plane freely, while its
medial-lateral shift and its rotation about the other two axes, counted from the static scan,
cost ``prior_weight * ((shift / sigma_mm)^2 + (tilt / sigma_deg)^2)`` (patellofemoral_sigma).
The medial-lateral axis is the view's ray at the static scan (a lateral view looks along the
standing knee's medial-lateral axis), carried by the femur: the ray as seen from the moving
femur would count the patella's own flexion as tilt once the femur turns or leans (at 86
degrees of a squat, 4 degrees of tilt and 2.7 mm of shift that are not there).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, NonNegativeFloat, PositiveFloat, PositiveInt
from scipy.ndimage import (
    binary_dilation,
    distance_transform_edt,
    gaussian_filter,
    maximum_filter1d,
    minimum_filter1d,
)
from scipy.optimize import differential_evolution, least_squares, minimize, minimize_scalar
from scipy.spatial.transform import RigidTransform, Rotation
from threadpoolctl import threadpool_limits

from recon.geometry import View
from recon.project import JosephProjector
from registration.drr import BoneModel, SoftTissue, along_axis, scene
from registration.frames import blocks
from registration.implants import ImplantModel
from registration.similarity import BlurredHighpass, gradient_ncc, highpass, ncc, turned_gaussian

TRACK_ORDER = ("tibia_fibula", "femur", "patella")
"""Bones are registered in this order each frame (largest and slowest first)."""

LONG_BONES = ("tibia_fibula", "femur")

CARRIER = {"patella": "femur"}
"""Bones whose motion the KPM predicts relative to another bone, registered before them each
frame: the patella rides in the femur's trochlea, so it is carried by the femur's new pose
and extrapolated in the femur's frame."""

MAX_KPM_STEP = (25.0, 25.0)
"""A frame-to-frame motion beyond (mm, deg) is not extrapolated (it is a failure, not motion)."""

KPM_LAMBDA = np.arange(-1.5, 2.51, 0.25)
"""The KPM's scan along the kinematic direction, in steps of the last motion: from reversing
it one and a half times to repeating it two and a half times (then Brent about the best)."""


MIN_SILHOUETTE_PX = 20
"""A bone casting fewer pixels (at a pyramid level) than this is out of the field of view."""


EDGE_ON_DEG = 45.0
"""A face of the static scan's box cuts the leg with a step in the DRR where the rays graze it
within this angle (registration.drr.cut_outlines); seen more face-on, what it leaves out
thins out to nothing at its outline."""

DEFORMATION_REUSE_MM = 1.0
DEFORMATION_CARRY_MM = 5.0
DEFORMATION_REUSE_REACH_MM = 60.0
"""The soft tissue deformed by a pair of femur and tibia poses is reused for poses that move
no corner of the cube of this half-width about the joint centre by more than
DEFORMATION_REUSE_MM (its lattice is ~2 mm), or DEFORMATION_CARRY_MM for the bone registered,
which carries its share of the tissue from its pose in the deformation (to first order)."""

FRAME_BLUR_MM = np.arange(0.0, 3.01, 0.5)
"""Candidate blurs of the frames along each panel axis (Gaussian sigma, mm) for resolution
matching."""
MODEL_BLUR_MM = np.arange(0.0, 1.21, 0.15)
"""Candidate blurs of a mesh's sharp render (Gaussian sigma at the panel, mm): the imaging
chain's (focal spot, panel, video) that the frames carry."""


class OutOfView(ValueError):
    """The bone's projection (nearly) misses the detector: its frame is flagged, not guessed."""


class Settings(BaseModel):
    """Registration settings (mm and degrees); YAML files load with recon.config.load_config
    (``configs/registration.yaml`` holds the defaults)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    pyramid_mm: tuple[PositiveFloat, ...] = Field(
        (2.4, 1.2),
        min_length=1,
        description="pixel sizes of the resolution pyramid at the panel, coarse to fine, mm; "
        "each level bins the panel by the nearest whole factor (at least 1)",
    )
    highpass_mm: PositiveFloat = Field(3.0, description="high-pass Gaussian sigma, mm")
    frame_blur_mm: tuple[NonNegativeFloat, NonNegativeFloat] | None = Field(
        None,
        description="Gaussian sigmas (along the panel's u, v axes, mm) the frames are blurred "
        "by to match the DRRs' resolution (a CBCT is blurrier than a fluoroscopy panel, and "
        "blurrier across its axis than along it); None estimates them per bone on the first "
        "frame (the pair on the FRAME_BLUR_MM grid that maximises the bone's NCC)",
    )
    mask_dilation_mm: PositiveFloat = Field(4.0, description="2D mask dilation, mm")
    truncation_band_mm: NonNegativeFloat = Field(
        12.0,
        description="the mask leaves out pixels this close (panel mm) to where the static "
        "scan's box cuts the leg, projected at the current poses: the DRR ends there, the "
        "frame goes on (the edge and its high-pass reach, 3 sigma, plus a few mm of motion); "
        "0 keeps them",
    )
    de_translation_mm: PositiveFloat = Field(12.0, description="DE box half-width, mm")
    de_long_axis_deg: PositiveFloat = Field(15.0, description="DE box about the long axis, deg")
    de_other_axes_deg: PositiveFloat = Field(8.0, description="DE box about the others, deg")
    de_popsize: PositiveInt = 10
    de_maxiter: PositiveInt = 30
    powell_maxfev: PositiveInt = 400
    powell_xtol: PositiveFloat = Field(
        0.05,
        description="Powell's tolerance on the coarsest level, mm and deg (Nelder-Mead on the "
        "finer levels refines further)",
    )
    nelder_mead_maxfev: PositiveInt = 120
    refinement: Literal["least_squares", "powell_nelder_mead"] = Field(
        "least_squares",
        description="with the KPM, how a bone is refined once the KPM has placed it (every "
        "frame after the first): Levenberg-Marquardt on the residual whose half squared norm "
        "is 1 - NCC (Jacobian by central differences of ls_step), the coarse levels in a "
        "first pass over the bones and the finest in a second, whatever passes says; or "
        "powell_nelder_mead, the derivative-free passes of the first frame (where the DE's "
        "pose may be a few mm off, which Powell's box search recovers) and of the tracker "
        "without the KPM",
    )
    ls_step: tuple[PositiveFloat, PositiveFloat] = Field(
        (0.25, 0.25), description="least squares: central-difference steps, (mm, deg)"
    )
    ls_max_steps: tuple[PositiveInt, PositiveInt] = Field(
        (5, 5),
        description="least squares: residual evaluations as MINPACK counts them (each step "
        "also takes a Jacobian: 12 renders) on the coarse levels and on the finest",
    )
    passes: PositiveInt = Field(
        2,
        description="passes over the bones per frame; later passes refine each against the "
        "others' newest estimates (first frame: Powell in a box of 0.4 x refine_range, then "
        "Nelder-Mead; warm frames: Nelder-Mead on the finest level); a first frame that "
        "estimates the frames' blur takes at least two",
    )
    kpm: bool = True
    global_init: bool = True
    powell: bool = True
    fail_ncc: float = Field(0.5, ge=-1.0, le=1.0, description="flag a bone below this NCC")
    drop_ncc: float = Field(
        0.02,
        ge=0.0,
        description="a warm frame whose NCC falls this far below the bone's previous frame "
        "widens the search (DE in half the first frame's box) and keeps the better pose",
    )
    refine_range: tuple[PositiveFloat, PositiveFloat] = Field(
        (5.0, 5.0), description="Powell's box about the start, (mm, deg)"
    )
    patellofemoral_sigma: tuple[PositiveFloat, PositiveFloat] | None = Field(
        (3.0, 5.0),
        description="patellofemoral prior: (mm, deg) of the patella's medial-lateral shift and "
        "out-of-plane tilt relative to the femur since the static scan; None turns it off",
    )
    depth_step_sigma_mm: dict[str, PositiveFloat] = Field(
        default_factory=dict,
        description="depth prior, by body: sigma of its move along the view's axis (its depth) "
        "from the frame before, mm; a body not named has none (a lateral view's knee moves "
        "across the beam, and its depth is the least seen of its six degrees of freedom)",
    )
    prior_weight: float = Field(
        0.005, ge=0.0, description="prior cost in NCC units per sigma squared"
    )
    kpm_depth: Literal["extrapolate", "hold"] = Field(
        "extrapolate",
        description="what the KPM's prediction does with a bone's depth (its centroid's move "
        "along the view's ray): extrapolate it with the rest of the last motion, or hold it at "
        "the last frame's (one plane measures depth least well: an error in it, extrapolated, "
        "grows from frame to frame)",
    )
    seed: int = 0


@dataclass
class BoneResult:
    """One bone in one frame."""

    pose: np.ndarray
    ncc: float
    gradient_ncc: float
    seconds: float
    evaluations: int
    failed: bool
    reason: str = ""
    """Why the bone failed (empty when it did not)."""

    def scored(self, ncc: float, gradient_ncc: float, fail_ncc: float) -> None:
        """Set the similarity, and the failure flag against ``fail_ncc``.

        Args:
            ncc: Normalised cross-correlation of the frame and the DRR, in [-1, 1].
            gradient_ncc: The same of their gradients, in [-1, 1].
            fail_ncc: The NCC below which the body counts as failed.
        """
        self.ncc, self.gradient_ncc, self.failed = ncc, gradient_ncc, ncc < fail_ncc
        self.reason = f"NCC {ncc:.3f} below {fail_ncc}" if self.failed else ""


@dataclass
class FrameResult:
    frame: int
    bones: dict[str, BoneResult] = field(default_factory=dict)


def compose(x: np.ndarray, T0: np.ndarray, center_mm: np.ndarray) -> np.ndarray:
    """``T(x) = [R, (I - R) c + t] T0`` with c the moved centroid, x = (t mm, r deg)."""
    R = Rotation.from_rotvec(np.radians(x[3:6])).as_matrix()
    c = T0[:3, :3] @ center_mm + T0[:3, 3]
    M = np.eye(4)
    M[:3, :3] = R
    M[:3, 3] = c - R @ c + x[:3]
    return M @ T0


class _Objective:
    """-NCC of one bone at one pyramid level against a frame, the rest of the scene fixed.

    The soft tissue is deformed by the bones' estimates at the start; the bone carries its
    share of it (``carried``: its projector and the bone's pose in the deformation, rendered
    moved by the bone's motion from there). The
    similarity is taken over the bone's silhouette at the start pose (and at the ``reach``
    poses), dilated, less the ``excluded`` pixels (the frame's 2D mask), in a crop of the
    view around it; the fixed rest of the scene (``background``: its line integrals through a
    view) is rendered once, over the crop and the reach of the high-pass filter around it.
    """

    def __init__(
        self,
        view: View,
        target_hp: np.ndarray,
        background: Callable[[View], np.ndarray],
        bone: BoneModel,
        carried: tuple[JosephProjector, np.ndarray] | None,
        T0: np.ndarray,
        sigma_px: float,
        dilation_px: int,
        coarse: bool,
        prior: Callable[[np.ndarray], np.ndarray] | None = None,
        reach: tuple[np.ndarray, ...] = (),
        excluded: np.ndarray | None = None,
    ) -> None:
        silhouette = bone.render(view, T0, coarse) > 0.02
        for T in reach:  # poses the search will visit far from T0: the mask covers them too
            silhouette |= bone.render(view, T, coarse) > 0.02
        if silhouette.sum() < MIN_SILHOUETTE_PX:
            raise OutOfView(f"bone {bone.name} leaves the field of view")
        mask = binary_dilation(silhouette, iterations=max(1, dilation_px))
        if excluded is not None:
            mask &= ~excluded
            if mask.sum() < MIN_SILHOUETTE_PX:
                raise OutOfView(
                    f"bone {bone.name} lies where the frame tells nothing: the static scan's "
                    "box cuts it, or it is outside the exposed field"
                )
        rows, cols = np.nonzero(mask)
        margin = math.ceil(3 * sigma_px)
        r0, r1 = max(0, rows.min() - margin), min(view.rows, rows.max() + margin + 1)
        c0, c1 = max(0, cols.min() - margin), min(view.cols, cols.max() + margin + 1)
        self.view = view.cropped(r0, c0, r1 - r0, c1 - c0)
        self.crop = (slice(r0, r1), slice(c0, c1))
        self.mask = mask[self.crop]
        self.spans = _row_spans(self.mask, math.ceil(4 * sigma_px))
        self.target = target_hp[self.crop]
        halo = int(4 * sigma_px + 0.5) + 1  # scipy's Gaussian reaches 4 sigma: exact in the crop
        h0, g0 = max(0, r0 - halo), max(0, c0 - halo)
        outer = view.cropped(h0, g0, min(view.rows, r1 + halo) - h0, min(view.cols, c1 + halo) - g0)
        inner = (slice(r0 - h0, r1 - h0), slice(c0 - g0, c1 - g0))
        self.background = highpass(background(outer), sigma_px)[inner]
        self.bone, self.carried, self.T0 = bone, carried, T0
        self._deformed_inv = None if carried is None else np.linalg.inv(carried[1])
        self.sigma, self.coarse, self.prior = sigma_px, coarse, prior
        self._sharp = None  # a mesh's render: its blur and the high-pass in one filter
        if isinstance(bone, ImplantModel) and carried is None:
            blur_px = bone.blur_mm / self.view.pitch_u_mm
            self._sharp = BlurredHighpass(self.mask.shape, blur_px, sigma_px)
        self.evaluations = 0
        self._unit_target: np.ndarray | None = None

    def image(self, T: np.ndarray) -> np.ndarray:
        if self._sharp is not None:
            return self.background + self._sharp(self.bone.render(self.view, T, blurred=False))
        moving = self.bone.render(self.view, T, self.coarse, self.spans)
        if self.carried is not None:
            moving += self.carried[0].project_moved(self.view, T @ self._deformed_inv, self.spans)
        return self.background + highpass(moving, self.sigma)

    def __call__(self, x: np.ndarray) -> float:
        self.evaluations += 1
        return self.cost(compose(np.asarray(x, dtype=np.float64), self.T0, self.bone.centroid_mm))

    def residuals(self, x: np.ndarray) -> np.ndarray:
        """Target minus render over the mask, each zero-mean and of unit norm (half the
        squared norm is 1 - NCC), and the prior's terms times sqrt(2), at pose ``x``."""
        self.evaluations += 1
        T = compose(np.asarray(x, dtype=np.float64), self.T0, self.bone.centroid_mm)
        if self._unit_target is None:
            self._unit_target = _unit(self.target[self.mask])
        prior = () if self.prior is None else math.sqrt(2.0) * self.prior(T)
        try:
            image = _unit(self.image(T)[self.mask])
        except ValueError:  # no view renders the pose: the worst residual
            image = -self._unit_target
        return np.append(self._unit_target - image, prior)

    def scores(self, T: np.ndarray) -> tuple[float, float]:
        """NCC and gradient NCC at pose ``T`` (no prior)."""
        image = self.image(T)
        return ncc(self.target, image, self.mask), gradient_ncc(self.target, image, self.mask)

    def cost(self, T: np.ndarray) -> float:
        """-NCC at pose T plus the prior (if any); +1 (worst) for poses no view can render
        (e.g. behind the source)."""
        penalty = 0.0 if self.prior is None else float(np.sum(self.prior(T) ** 2))
        try:
            return penalty - ncc(self.target, self.image(T), self.mask)
        except ValueError:
            return 1.0 + penalty


def _unit(values: np.ndarray) -> np.ndarray:
    """``values`` less their mean, scaled to unit norm (float64; zeros when constant)."""
    centred = values.astype(np.float64) - values.mean(dtype=np.float64)
    norm = np.linalg.norm(centred)
    return centred / norm if norm > 0 else centred


def _either(a: np.ndarray | None, b: np.ndarray | None) -> np.ndarray | None:
    """The union of two optional pixel masks."""
    if a is None or b is None:
        return b if a is None else a
    return a | b


def _extend_into(image: np.ndarray, field: np.ndarray, sigma_px: float) -> np.ndarray:
    """``image`` with the pixels outside ``field`` replaced by a smooth extension of those
    inside (normalised convolution: Gaussian-weighted means of the field's pixels, sigma
    ``2 sigma_px``; the field's mean where none is near)."""
    weight = field.astype(np.float32)
    sigma = 2.0 * sigma_px
    num = gaussian_filter(np.where(field, image, 0.0).astype(np.float32), sigma, mode="nearest")
    den = gaussian_filter(weight, sigma, mode="nearest")
    fill = np.full_like(num, float(image[field].mean()))
    np.divide(num, den, out=fill, where=den > 1e-3)
    return np.where(field, image, fill).astype(np.float32)


def _row_spans(mask: np.ndarray, margin_px: int) -> np.ndarray:
    """Per row, the columns (start, stop) within ``margin_px`` (chessboard) of ``mask``: where
    the high-pass of a render reaches the mask (the Gaussian's truncation at 4 sigma)."""
    cols = mask.shape[1]
    index = np.arange(cols)
    size = 2 * margin_px + 1
    lo = minimum_filter1d(np.where(mask, index, cols).min(axis=1), size, mode="nearest")
    hi = maximum_filter1d(np.where(mask, index + 1, 0).max(axis=1), size, mode="nearest")
    empty = hi <= lo
    lo, hi = np.maximum(lo - margin_px, 0), np.minimum(hi + margin_px, cols)
    lo[empty] = hi[empty] = 0
    return np.column_stack((lo, hi)).astype(np.int64)


def patellofemoral_offsets(
    T_femur: np.ndarray, T_patella: np.ndarray, center_mm: np.ndarray, axis: np.ndarray
) -> np.ndarray:
    """:func:`patellofemoral_deviation` as a vector: the shift (mm), then the rotation vector
    less its component along ``axis`` (deg, 3; its norm is the tilt)."""
    M = np.linalg.inv(T_femur) @ T_patella
    shift = axis @ (M[:3, :3] @ center_mm + M[:3, 3] - center_mm)
    rotvec = Rotation.from_matrix(M[:3, :3]).as_rotvec(degrees=True)
    return np.append(shift, rotvec - (rotvec @ axis) * axis)


def patellofemoral_deviation(
    T_femur: np.ndarray, T_patella: np.ndarray, center_mm: np.ndarray, axis: np.ndarray
) -> tuple[float, float]:
    """The patella's out-of-plane motion relative to the femur since the static scan (both
    poses are identity there): the shift of its centroid ``center_mm`` along the femur's
    medial-lateral ``axis`` (a unit vector in the static scan, which the femur carries with
    it), mm, and its rotation about the two axes perpendicular to that, deg. Flexing about
    any medial-lateral line and sliding in the femur's sagittal plane count nothing."""
    offsets = patellofemoral_offsets(T_femur, T_patella, center_mm, axis)
    return float(offsets[0]), float(np.linalg.norm(offsets[1:]))


def _carried_pose(name: str, poses: dict[str, np.ndarray]) -> np.ndarray:
    """The pose of bone ``name`` in its carrier's frame (:data:`CARRIER`, when tracked), else in
    the world."""
    carrier = CARRIER.get(name)
    if carrier not in poses:
        return poses[name]
    return np.linalg.inv(poses[carrier]) @ poses[name]


def _carrier_pose(name: str, poses: dict[str, np.ndarray]) -> np.ndarray:
    """The pose of bone ``name``'s carrier (:data:`CARRIER`) in ``poses``, else the identity."""
    carrier = CARRIER.get(name)
    return poses[carrier] if carrier in poses else np.eye(4)


def _parabola_peak(x: np.ndarray, y: np.ndarray, i: int) -> float:
    """The peak of the parabola through samples i-1, i, i+1 of y(x) (sample i at an end or
    without a peak between its neighbours: x[i])."""
    if i == 0 or i == len(x) - 1:
        return float(x[i])
    a, b, _ = np.polyfit(x[i - 1 : i + 2], y[i - 1 : i + 2], 2)
    return float(np.clip(-b / (2 * a), x[i - 1], x[i + 1])) if a < 0 else float(x[i])


def principal_axes(points_mm: np.ndarray) -> np.ndarray:
    """Columns: the bone's principal axes (PCA), the longest first."""
    centered = points_mm - points_mm.mean(axis=0)
    _, _, vt = np.linalg.svd(centered[:: max(1, len(centered) // 20000)], full_matrices=False)
    return vt.T


def kinematic_twist(
    T_before: np.ndarray, T_last: np.ndarray, center_mm: np.ndarray
) -> np.ndarray | None:
    """The last frame-to-frame motion in the bone's frame as exponential coordinates
    ``(rotation vector rad, v mm)`` (``T_last = T_before exp(xi)``, scipy's RigidTransform),
    or None when it is too large to be motion (MAX_KPM_STEP, measured at the bone's reference
    centroid ``center_mm``)."""
    xi = RigidTransform.from_matrix(np.linalg.inv(T_before) @ T_last).as_exp_coords()
    c = np.append(center_mm, 1.0)
    step_mm = np.linalg.norm((T_last @ c - T_before @ c)[:3])
    if step_mm > MAX_KPM_STEP[0] or math.degrees(np.linalg.norm(xi[:3])) > MAX_KPM_STEP[1]:
        return None
    return xi


def _twist_size(xi: np.ndarray, center_mm: np.ndarray) -> float:
    """The larger of a twist's step at ``center_mm`` (mm, to first order) and its angle (deg)."""
    step_mm = np.linalg.norm(np.cross(xi[:3], center_mm) + xi[3:])
    return max(float(step_mm), math.degrees(np.linalg.norm(xi[:3])))


def _exp(xi: np.ndarray) -> np.ndarray:
    """``exp(xi)`` as 4x4 matrices, for exponential coordinates (..., 6)."""
    return RigidTransform.from_exp_coords(xi).as_matrix()


def predict(
    T_before: np.ndarray, T_last: np.ndarray, center_mm: np.ndarray, lam: float = 1.0
) -> np.ndarray:
    """The KPM prediction ``T_last exp(lam xi)``: constant velocity for ``lam = 1``."""
    xi = kinematic_twist(T_before, T_last, center_mm)
    return T_last if xi is None else T_last @ _exp(lam * xi)


class Tracker:
    """Registers every bone in every frame of a fluoroscopy sequence.

    Args:
        view: the fluoroscopy view at full resolution.
        frames: line integrals (F, rows, cols).
        bones: the tracked bodies by name (a subset of :data:`TRACK_ORDER`): bones
            (registration.drr.bone_models) or implant components
            (registration.implants.implant_model).
        settings: registration settings.
        soft_tissue: the soft tissue, deformed by the femur and the tibia
            (registration.drr.SoftTissue); None leaves it out.
        field: bool (rows, cols), the pixels the beam reaches (an image intensifier's round
            field, a collimator's shutters: registration.frames.Frames.field); the rest, and
            the band where the high-pass filter sees the field's edge, is left out of the
            similarity. None: every pixel.
    """

    def __init__(
        self,
        view: View,
        frames: np.ndarray,
        bones: dict[str, BoneModel],
        settings: Settings | None = None,
        soft_tissue: SoftTissue | None = None,
        field: np.ndarray | None = None,
    ) -> None:
        unknown = sorted(set(bones) - set(TRACK_ORDER))
        if unknown or not bones:
            raise ValueError(f"tracked bodies are named from {TRACK_ORDER}, got {sorted(bones)}")
        self.order = tuple(b for b in TRACK_ORDER if b in bones)
        """The tracked bodies in the order they are registered in a frame."""
        self.view = view
        self.frames = np.asarray(frames, dtype=np.float32)
        if field is not None and np.shape(field) != self.frames.shape[1:]:
            raise ValueError(
                f"field of {np.shape(field)} pixels for frames of {self.frames.shape[1:]}"
            )
        self.field = None if field is None or np.all(field) else np.asarray(field, dtype=bool)
        self.bones = dict(bones)  # a mesh body's matched blur stays this tracker's
        self.soft_tissue = soft_tissue
        self._knees: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        """The frame's (femur, tibia) pose pairs the soft tissue was deformed by."""
        self._deformed: dict[int, tuple] = {}
        """Per pose pair of :attr:`_knees`: the deformed soft tissue."""
        if soft_tissue is not None:
            reach = DEFORMATION_REUSE_REACH_MM * np.array([-1.0, 1.0])
            self._knee_corners = soft_tissue.joint_mm + np.array(
                [[x, y, z] for x in reach for y in reach for z in reach]
            )
        self._split: dict[tuple[int, str], tuple] = {}
        """Per pose pair and bone: what stays, what the bone carries."""
        self.settings = settings or Settings()
        self.levels = tuple(
            dict.fromkeys(max(1, round(mm / view.pitch_u_mm)) for mm in self.settings.pyramid_mm)
        )
        """Binning factors of the pyramid, coarse to fine."""
        self._views = {b: view.binned(b) for b in self.levels}
        self._targets: dict[tuple[int, int, tuple[float, float], int], np.ndarray] = {}
        """High-passed frames by (frame, level, blur_mm, turn_deg) (:meth:`_target`)."""
        self._blurred: dict[tuple[int, tuple[float, float], int], np.ndarray] = {}
        """The frames blurred, before binning, by (frame, blur_mm, turn_deg)."""
        blur = self.settings.frame_blur_mm or (0.0, 0.0)
        self.frame_blur_mm = {name: tuple(blur) for name in bones}
        """Per bone: the frames' matching blur along (u, v), panel mm (estimated on the first
        frame when the settings leave it open), at the bone's :attr:`_blur_rotation`."""
        self._blur_rotation = {name: np.eye(3) for name in bones}
        """Per bone: its rotation when its blur was estimated (the static scan's, identity,
        for a blur given in the settings). The blur is the CBCT's, so it turns with the bone."""
        self._last_ncc: dict[str, float] = {}
        self._before: dict[str, np.ndarray] = {}  # the frame before's poses (the depth prior)
        self._outside: dict[int, np.ndarray] = {}
        """Per pyramid level: the pixels outside the exposed field (:meth:`_outside_field`)."""
        self._extensions: dict[int, np.ndarray] = {}
        """The frame being registered, extended beyond the exposed field (:meth:`_extended`)."""

    def _sigma_px(self, level: int) -> float:
        return self.settings.highpass_mm / self._views[level].pitch_u_mm

    def _blur_turn_deg(self, name: str, T: np.ndarray) -> int:
        """How far bone ``name`` at pose ``T`` has turned in the panel's plane since its blur
        was estimated (the turn of the panel's u axis carried by the bone, projected), whole
        degrees."""
        turned = T[:3, :3] @ self._blur_rotation[name].T @ self.view.e_u
        return round(math.degrees(math.atan2(turned @ self.view.e_v, turned @ self.view.e_u)))

    def _target(
        self, frame: int, level: int, blur_mm: tuple[float, float], turn_deg: int = 0
    ) -> np.ndarray:
        """The frame blurred by ``blur_mm`` (Gaussian sigmas along u, v at the panel, mm; the
        axes turned by ``turn_deg`` towards +v), binned to ``level``, high-passed."""
        if blur_mm[0] == blur_mm[1]:
            turn_deg = 0  # a round blur does not turn
        key = (frame, level, blur_mm, turn_deg)
        if key not in self._targets:
            blurred = key[:1] + key[2:]
            if blurred not in self._blurred:  # shared by the levels
                image = self._extended(frame)
                sigma_px = (blur_mm[0] / self.view.pitch_u_mm, blur_mm[1] / self.view.pitch_v_mm)
                if turn_deg:
                    image = turned_gaussian(image, sigma_px, math.radians(turn_deg))
                elif any(blur_mm):
                    image = gaussian_filter(image, sigma_px[::-1], mode="nearest")
                self._blurred[blurred] = image
            image = self._blurred[blurred]
            if level > 1:
                image = blocks(image, level).mean(axis=(1, 3))
            self._targets[key] = highpass(image, self._sigma_px(level))
        return self._targets[key]

    def _extended(self, frame: int) -> np.ndarray:
        """The frame, extended smoothly beyond the exposed field (no step at the field's edge
        for the filters), once per frame."""
        if self.field is None:
            return self.frames[frame]
        if frame not in self._extensions:
            self._extensions.clear()  # one frame at a time
            sigma = self.settings.highpass_mm / self.view.pitch_u_mm
            self._extensions[frame] = _extend_into(self.frames[frame], self.field, sigma)
        return self._extensions[frame]

    def _coarse(self, level: int, name: str) -> bool:
        """Render with the pooled volumes when a pixel spans two voxels at the bone."""
        view, bone = self._views[level], self.bones[name]
        pixel_at_bone = view.pitch_u_mm * float(view.depth(bone.centroid_mm)[0])
        return pixel_at_bone >= 2.0 * bone.voxel_mm()

    def _objective(
        self,
        frame: int,
        level: int,
        name: str,
        poses: dict[str, np.ndarray],
        lone: bool = False,
        reach: tuple[np.ndarray, ...] = (),
        beside: tuple[str, ...] = (),
    ):
        """The objective of bone ``name``, the others at ``poses`` (``lone``: bone alone but
        for those ``beside`` it, no prior, no soft tissue), masked to its silhouettes at
        ``poses`` and ``reach``."""
        view = self._views[level]
        others = {b: m for b, m in self.bones.items() if b != name and (not lone or b in beside)}
        stays = carried = None
        if not lone and self.soft_tissue is not None:
            stays, carried = self._soft_tissue(name, poses)

        def background(part: View) -> np.ndarray:
            image = scene(part, others, poses)
            if stays is not None:
                image += stays.project_moved(part, np.eye(4))
            return image

        return _Objective(
            view,
            self._target(
                frame, level, self.frame_blur_mm[name], self._blur_turn_deg(name, poses[name])
            ),
            background,
            self.bones[name],
            carried,
            poses[name],
            self._sigma_px(level),
            round(self.settings.mask_dilation_mm / view.pitch_u_mm),
            self._coarse(level, name),
            None if lone else self._prior(name, poses),
            reach,
            _either(self._truncation(level, name, poses, reach), self._outside_field(level)),
        )

    def _outside_field(self, level: int) -> np.ndarray | None:
        """The pixels of ``level``'s view outside the exposed field, or within two high-pass
        sigmas of it (where the filtered frame still sees the field's edge); None: no field."""
        if self.field is None:
            return None
        if level not in self._outside:
            outside = blocks(~self.field, level).any(axis=(1, 3))
            band = math.ceil(2 * self._sigma_px(level))
            self._outside[level] = binary_dilation(outside, iterations=band)
        return self._outside[level]

    def _truncation(
        self, level: int, name: str, poses: dict[str, np.ndarray], reach: tuple[np.ndarray, ...]
    ) -> np.ndarray | None:
        """The pixels of ``level``'s view within ``truncation_band_mm`` of the static scan's
        cuts (registration.drr.SoftTissue.cuts) seen within :data:`EDGE_ON_DEG` of edge-on,
        carried by the femur and the tibia at ``poses`` (bone ``name``'s also at ``reach``);
        None when nothing is cut nearby."""
        band_mm = self.settings.truncation_band_mm
        if self.soft_tissue is None or band_mm == 0:
            return None
        view = self._views[level]
        pad = math.ceil(band_mm / view.pitch_u_mm)  # cuts just off the panel reach onto it
        hit = np.zeros((view.rows + 2 * pad, view.cols + 2 * pad), dtype=bool)
        for carrier, (points, normals) in self.soft_tissue.cuts.items():
            for T in (poses[carrier], *(reach if carrier == name else ())):
                moved = points @ T[:3, :3].T + T[:3, 3]
                rays = moved - view.source_mm
                facing = np.abs(np.sum(rays * (normals @ T[:3, :3].T), axis=1))
                edge_on = facing < math.sin(math.radians(EDGE_ON_DEG)) * np.linalg.norm(
                    rays, axis=1
                )
                u, v = np.rint(view.project(moved[edge_on]) + pad).T
                on = (u >= 0) & (u < hit.shape[1]) & (v >= 0) & (v < hit.shape[0])
                hit[v[on].astype(int), u[on].astype(int)] = True
        if not hit.any():
            return None
        near = distance_transform_edt(~hit, sampling=(view.pitch_v_mm, view.pitch_u_mm))
        return (near <= band_mm)[pad:-pad, pad:-pad]

    def _near(self, name: str, knee: tuple[np.ndarray, np.ndarray], poses) -> bool:
        """Whether the (femur, tibia) poses ``knee`` and those in ``poses`` move no corner of
        the knee's cube (:data:`DEFORMATION_REUSE_REACH_MM`) further apart than
        :data:`DEFORMATION_REUSE_MM` (:data:`DEFORMATION_CARRY_MM` for bone ``name``, which
        carries its share of the tissue)."""
        corners = self._knee_corners
        return all(
            np.abs(corners @ (A[:3, :3] - B[:3, :3]).T + (A[:3, 3] - B[:3, 3])).max()
            <= (DEFORMATION_CARRY_MM if bone == name else DEFORMATION_REUSE_MM)
            for bone, A, B in zip(
                ("femur", "tibia_fibula"),
                knee,
                (poses["femur"], poses["tibia_fibula"]),
                strict=True,
            )
        )

    def _soft_tissue(
        self, name: str, poses: dict[str, np.ndarray]
    ) -> tuple[JosephProjector, tuple[JosephProjector, np.ndarray] | None]:
        """The soft tissue deformed by ``poses``: what stays when bone ``name`` moves, and
        what it carries (registration.drr.SoftTissue.carried, averaged over pairs of slices
        along the rays: rendered every evaluation) with the bone's pose in the deformation;
        kept for the frame being registered and reused for poses nearby (:meth:`_near`)."""
        knee = next((k for k, pair in self._knees.items() if self._near(name, pair, poses)), None)
        if knee is None:
            knee = len(self._knees)
            self._knees[knee] = (poses["femur"], poses["tibia_fibula"])
            self._deformed[knee] = self.soft_tissue.deformed(*self._knees[knee], self.view)
        if (knee, name) not in self._split:
            deformed = self._deformed[knee]
            stays, carried = self.soft_tissue.carried(deformed, name)
            axis = int(np.argmax(np.abs(self.view.normal)))  # the rays' main axis
            moving = None
            if carried is not None:
                pose = self._knees[knee][name != "femur"]
                moving = (along_axis(carried, deformed[2], axis), pose)
            self._split[knee, name] = (JosephProjector(stays, deformed[2]), moving)
        return self._split[knee, name]

    def _prior(self, name: str, poses: dict[str, np.ndarray]) -> Callable | None:
        """The priors of bone ``name`` as a function of its pose whose squared norm is their
        cost (each term scaled, so a least-squares residual stays smooth at zero), or None:
        the patellofemoral prior of a carried bone (the patella, :data:`CARRIER`) against its
        carrier's estimate (the femur), and the depth prior against the frame before."""
        terms = [t for t in (self._patellofemoral(name, poses), self._depth(name)) if t]
        if not terms:
            return None
        if len(terms) == 1:
            return terms[0]
        return lambda T: np.concatenate([term(T) for term in terms])

    def _patellofemoral(self, name: str, poses: dict[str, np.ndarray]) -> Callable | None:
        """The patellofemoral prior's terms: the patella's shift and the three components of
        its tilt relative to the femur's estimate; None for other bones."""
        s = self.settings
        carrier = CARRIER.get(name)
        if carrier not in poses or s.patellofemoral_sigma is None:
            return None
        sigma_mm, sigma_deg = s.patellofemoral_sigma
        T_femur, center = poses[carrier], self.bones[name].centroid_mm
        axis = self.view.normal  # a lateral view looks along the static scan's ML axis

        scale = math.sqrt(s.prior_weight) / np.array([sigma_mm, sigma_deg, sigma_deg, sigma_deg])

        def prior(T: np.ndarray) -> np.ndarray:
            return scale * patellofemoral_offsets(T_femur, T, center, axis)

        return prior

    def _depth(self, name: str) -> Callable | None:
        """The depth prior's term: the move of the bone's centroid along the view's axis from
        the frame before, over its ``depth_step_sigma_mm``; None on the first frame or for a
        bone without one."""
        s = self.settings
        sigma_mm = s.depth_step_sigma_mm.get(name)
        if sigma_mm is None or name not in self._before:
            return None
        view, center = self.view, np.append(self.bones[name].centroid_mm, 1.0)
        scale = math.sqrt(s.prior_weight) / sigma_mm

        def depth_mm(T: np.ndarray) -> float:
            return float(view.depth((T @ center)[:3])[0]) * view.sdd_mm

        before = depth_mm(self._before[name])
        return lambda T: np.array([scale * (depth_mm(T) - before)])

    def _refine(
        self,
        frame: int,
        name: str,
        poses: dict[str, np.ndarray],
        scale: float = 1.0,
        polish: bool = False,
    ) -> tuple[np.ndarray, int]:
        """Coarse to fine: Powell (bounded about the start by ``scale`` x refine_range) on the
        coarsest level, Nelder-Mead on the finer ones (on every level without Powell);
        ``polish``: Nelder-Mead on the finest level only."""
        s = self.settings
        t_max, r_max = scale * s.refine_range[0], scale * s.refine_range[1]
        evaluations = 0
        levels = self.levels[-1:] if polish and s.powell else self.levels
        for i, level in enumerate(levels, start=len(self.levels) - len(levels)):
            objective = self._objective(frame, level, name, poses)
            fine = i == len(self.levels) - 1
            if s.powell and i == 0:
                x = minimize(
                    objective,
                    np.zeros(6),
                    method="Powell",
                    bounds=[(-t_max, t_max)] * 3 + [(-r_max, r_max)] * 3,
                    options={"maxfev": s.powell_maxfev, "xtol": s.powell_xtol, "ftol": 1e-5},
                ).x
            if not (s.powell and i == 0) or len(self.levels) == 1:
                x0 = np.zeros(6) if not (s.powell and i == 0) else x
                step = 0.3 if fine and i > 0 else 1.0
                x = minimize(
                    objective,
                    x0,
                    method="Nelder-Mead",
                    options={
                        "maxfev": s.nelder_mead_maxfev,
                        "initial_simplex": np.vstack((x0, x0 + step * np.eye(6))),
                        "xatol": 1e-2,
                        "fatol": 1e-6,
                    },
                ).x
            poses = {**poses, name: compose(x, poses[name], self.bones[name].centroid_mm)}
            evaluations += objective.evaluations
        return poses[name], evaluations

    def _least_squares(
        self, frame: int, name: str, poses: dict[str, np.ndarray], levels: tuple[int, ...]
    ) -> tuple[np.ndarray, int, _Objective]:
        """Levenberg-Marquardt (scipy's MINPACK) on :meth:`_Objective.residuals` on each of
        ``levels`` in turn, at most ``ls_max_steps`` steps each (coarse, finest), the Jacobian
        by central differences of ``ls_step`` (12 renders). Returns the pose, the evaluations
        and the last level's objective."""
        s = self.settings
        steps = np.repeat(np.asarray(s.ls_step, dtype=np.float64), 3)
        evaluations = 0
        for level in levels:
            objective = self._objective(frame, level, name, poses)

            def jacobian(x: np.ndarray, objective=objective) -> np.ndarray:
                return np.column_stack(
                    [
                        (objective.residuals(x + d) - objective.residuals(x - d)) / (2 * h)
                        for d, h in zip(np.diag(steps), steps, strict=True)
                    ]
                )

            x = least_squares(
                objective.residuals,
                np.zeros(6),
                jac=jacobian,
                method="lm",
                x_scale=steps,
                xtol=1e-4,
                ftol=1e-8,
                max_nfev=s.ls_max_steps[int(level == self.levels[-1])],
            ).x
            poses = {**poses, name: compose(x, poses[name], self.bones[name].centroid_mm)}
            evaluations += objective.evaluations
        return poses[name], evaluations, objective

    def _global(
        self,
        frame: int,
        name: str,
        poses: dict[str, np.ndarray],
        scale: float = 1.0,
        lone: bool = False,
        beside: tuple[str, ...] = (),
    ) -> tuple[np.ndarray, int]:
        """Differential evolution in a box aligned with the bone's principal axes."""
        s = self.settings
        level = self.levels[0]
        objective = self._objective(frame, level, name, poses, lone, beside=beside)
        axes = principal_axes(self.bones[name].points_mm)
        R_pose = poses[name][:3, :3]
        axes = R_pose @ axes  # the principal axes at the current pose

        def in_axes(y):
            x = np.empty(6)
            x[:3] = y[:3]
            x[3:] = axes @ y[3:]  # rotation vector (deg) about the principal axes
            return x

        t, rl, ro = (
            s.de_translation_mm * scale,
            s.de_long_axis_deg * scale,
            s.de_other_axes_deg * scale,
        )
        bounds = [(-t, t)] * 3 + [(-rl, rl), (-ro, ro), (-ro, ro)]
        result = differential_evolution(
            lambda y: objective(in_axes(y)),
            bounds,
            seed=s.seed,
            popsize=s.de_popsize,
            maxiter=s.de_maxiter,
            tol=1e-6,
            polish=False,
            init="sobol",
        )
        pose = compose(in_axes(result.x), poses[name], self.bones[name].centroid_mm)
        return pose, objective.evaluations

    def best_start(
        self, frame: int, name: str, candidates: list[np.ndarray], placed: dict[str, np.ndarray]
    ) -> np.ndarray:
        """Body ``name``'s best start in ``frame`` among its candidate poses.

        Differential evolution in twice the first frame's box about each candidate, the
        bodies already placed in the scene, scored by its NCC on the coarsest level
        (registration.autostart).

        Args:
            frame: Index of the frame.
            name: The body.
            candidates: Candidate poses, each 4x4 (mm).
            placed: Poses (4x4, mm) of the bodies already placed, by name.

        Returns:
            The best pose, 4x4 (mm).
        """
        if not candidates:
            raise ValueError(f"no candidate start for {name}: is it in the frame?")
        beside = tuple(placed)
        best, best_score = None, -math.inf
        for T in candidates:
            trial = {**{b: T for b in self.order}, **placed, name: T}
            try:
                pose, _ = self._global(frame, name, trial, 2.0, True, beside)
                objective = self._objective(
                    frame, self.levels[0], name, trial | {name: pose}, True, beside=beside
                )
                score = objective.scores(pose)[0]
            except OutOfView:
                continue
            if score > best_score:
                best, best_score = pose, score
        if best is None:
            raise ValueError(f"no candidate start of {name} stays in the view")
        return best

    def _penalty(self, name: str, poses: dict[str, np.ndarray]) -> float:
        """The prior's cost of bone ``name`` at ``poses`` (0 without a prior)."""
        prior = self._prior(name, poses)
        return 0.0 if prior is None else float(np.sum(prior(poses[name]) ** 2))

    def _score(self, frame: int, name: str, poses: dict[str, np.ndarray]) -> tuple[float, float]:
        return self._objective(frame, self.levels[-1], name, poses).scores(poses[name])

    def _held(self, name: str, T: np.ndarray, T_last: np.ndarray) -> np.ndarray:
        """Predictions ``T`` (..., 4, 4) of bone ``name``, their depth held at ``T_last``'s when
        the settings say so (:attr:`Settings.kpm_depth`): each moved along the ray through its
        centroid (which therefore projects where it did) until the centroid is as far from the
        source as at ``T_last``."""
        if self.settings.kpm_depth == "extrapolate":
            return T
        center = np.append(self.bones[name].centroid_mm, 1.0)
        source = self.view.source_mm
        rays = (T @ center)[..., :3] - source
        distance = np.linalg.norm((T_last @ center)[:3] - source)
        held = T.copy()
        held[..., :3, 3] += (distance / np.linalg.norm(rays, axis=-1, keepdims=True) - 1.0) * rays
        return held

    def _kpm(self, frame: int, name: str, poses, history) -> tuple[np.ndarray, int]:
        """Line search along the kinematic direction: the last frame-to-frame motion, or at a
        turning point (the last motion under half the one before it) the one before; a scan
        of :data:`KPM_LAMBDA` steps, then Brent between the best one's neighbours. A carried
        bone (:data:`CARRIER`) moves along its motion relative to its carrier, from the
        carrier's pose in this frame."""
        base = _carrier_pose(name, poses)
        center = self.bones[name].centroid_mm
        carried = [_carried_pose(name, h) for h in history[-3:]]
        xi = kinematic_twist(carried[-2], carried[-1], center)
        if xi is None:
            return base @ carried[-1], 0
        before = kinematic_twist(carried[0], carried[1], center) if len(carried) == 3 else None
        if before is not None and _twist_size(xi, center) < 0.5 * _twist_size(before, center):
            xi = before
        start = base @ carried[-1]

        def at(lam: float) -> np.ndarray:
            return self._held(name, start @ _exp(lam * xi), start)

        line = self._held(name, start @ _exp(KPM_LAMBDA[:, None] * xi), start)
        # about the frame's prediction: the soft tissue deformed as the other bones' objectives
        objective = self._objective(frame, self.levels[0], name, poses, reach=(line[0], line[-1]))
        costs = [objective.cost(T) for T in line]
        k = int(np.argmin(costs))
        lo, hi = KPM_LAMBDA[max(k - 1, 0)], KPM_LAMBDA[min(k + 1, len(KPM_LAMBDA) - 1)]
        best = minimize_scalar(
            lambda lam: objective.cost(at(lam)),
            bounds=(lo, hi),
            method="bounded",
            options={"xatol": 0.02, "maxiter": 15},
        )
        return (at(best.x) if best.fun < costs[k] else line[k]), len(costs) + best.nfev

    def register(
        self, frame: int, poses: dict[str, np.ndarray], history: list[dict[str, np.ndarray]]
    ) -> FrameResult:
        """Register every bone in ``frame`` starting from ``poses`` (previous estimates).

        Warm frames with the KPM start every bone at its constant-velocity prediction, so each
        bone is scored against the others' predictions rather than their previous poses.
        Cold frames (no history) with global initialisation run differential evolution on
        every bone first: the long bones alone (the rest of the scene is still at its wrong
        starting estimate), the patella, small and overlapped by the femoral condyles, against
        the long bones' new estimates; then every bone is refined against the others' global
        estimates (bone by bone alternation).

        BLAS runs single-threaded meanwhile: the similarity's dot products over ~10^4 pixels
        woke OpenBLAS's threads, which then fought numba's renderer threads for the two cores
        (a femur evaluation at 256^2 took 8 ms instead of 1.5).

        Args:
            frame: Index of the frame.
            poses: Starting poses (4x4, mm) by body: the previous frame's estimates.
            history: The poses of the frames registered so far, oldest first.
        """
        with threadpool_limits(limits=1, user_api="blas"):
            return self._register(frame, poses, history)

    def _register(
        self, frame: int, poses: dict[str, np.ndarray], history: list[dict[str, np.ndarray]]
    ) -> FrameResult:
        s = self.settings
        result = FrameResult(frame)
        poses = dict(poses)
        self._knees.clear()
        self._deformed.clear()
        self._split.clear()
        self._targets = {k: t for k, t in self._targets.items() if k[0] == frame}
        self._blurred = {k: b for k, b in self._blurred.items() if k[0] == frame}
        self._before = history[-1] if history else {}
        if s.kpm and len(history) >= 2:  # every bone at its constant-velocity prediction first
            poses = {
                b: self._held(
                    b,
                    predict(history[-2][b], history[-1][b], self.bones[b].centroid_mm),
                    history[-1][b],
                )
                for b in self.order
            }
        if history and self._by_least_squares():
            return self._register_warm(frame, poses, history)
        spent = {name: (0.0, 0) for name in self.order}
        if not history and s.global_init:
            for name in self.order:
                start = time.perf_counter()
                lone = name in LONG_BONES
                poses[name], n = self._global(frame, name, poses, lone=lone)
                spent[name] = (time.perf_counter() - start, n)
        for name in self.order:
            start = time.perf_counter()
            try:
                result.bones[name] = self._track_bone(frame, name, poses, history)
            except OutOfView as err:
                result.bones[name] = BoneResult(
                    poses[name], math.nan, math.nan, 0.0, 0, True, str(err)
                )
            bone = result.bones[name]
            bone.seconds += spent[name][0] + time.perf_counter() - start
            bone.evaluations += spent[name][1]
            poses[name] = bone.pose
        matching = not history and s.frame_blur_mm is None
        if matching:  # then at least one more pass, against the matched frames
            self._match_resolution(frame, poses, result)
        for _ in range(max(s.passes - 1, int(matching))):  # each against the others' new poses
            for name, bone in result.bones.items():
                if math.isnan(bone.ncc):
                    continue
                start = time.perf_counter()
                try:
                    pose, n = self._refine(frame, name, poses, 0.4, polish=bool(history))
                    score, grad = self._score(frame, name, {**poses, name: pose})
                except OutOfView:  # the refinement walked off the panel: keep the first pass
                    pose, n, score, grad = bone.pose, 0, -math.inf, math.nan
                before = bone.ncc - self._penalty(name, poses)
                if score - self._penalty(name, {**poses, name: pose}) > before:
                    bone.pose = poses[name] = pose
                    bone.scored(score, grad, s.fail_ncc)
                bone.seconds += time.perf_counter() - start
                bone.evaluations += n
        return result

    def _register_warm(
        self, frame: int, poses: dict[str, np.ndarray], history: list[dict[str, np.ndarray]]
    ) -> FrameResult:
        """A frame after the first, refined by least squares: each bone placed by the
        KPM (the second frame's at its last pose, carried) and refined on the coarse levels,
        then each on the finest level against the others' new estimates and scored there;
        a bone whose score fails or drops (``fail_ncc``, ``drop_ncc``) is searched again about
        its last frame's pose (differential evolution in half the first frame's box, then the
        least squares on every level), keeping the better."""
        s = self.settings
        result = FrameResult(frame)
        coarse, finest = self.levels[:-1] or self.levels, self.levels[-1:]
        for name in self.order:  # first pass: the KPM and the coarse levels
            start, n = time.perf_counter(), 0
            try:
                poses[name], n = self._place(frame, name, poses, history)
                poses[name], m, _ = self._least_squares(frame, name, poses, coarse)
                bone = BoneResult(poses[name], math.nan, math.nan, 0.0, n + m, False)
            except OutOfView as err:
                bone = BoneResult(poses[name], math.nan, math.nan, 0.0, n, True, str(err))
            bone.seconds = time.perf_counter() - start
            result.bones[name] = bone
        for name, bone in result.bones.items():  # second pass: the finest level, the check
            if bone.failed:
                continue
            start = time.perf_counter()
            try:
                pose, n, objective = self._least_squares(frame, name, poses, finest)
                bone.pose = poses[name] = pose
                score, grad = objective.scores(pose)
            except OutOfView as err:
                bone.failed, bone.reason = True, str(err)
                continue
            previous = self._last_ncc.get(name, score)
            if score < s.fail_ncc or score < previous - s.drop_ncc:
                wide = {
                    **poses,
                    name: _carrier_pose(name, poses) @ _carried_pose(name, history[-1]),
                }
                wide[name], m = self._global(frame, name, wide, scale=0.5)
                wide[name], k, objective = self._least_squares(frame, name, wide, self.levels)
                wide_score, wide_grad = objective.scores(wide[name])
                n += m + k
                if wide_score - self._penalty(name, wide) > score - self._penalty(name, poses):
                    bone.pose = poses[name] = wide[name]
                    score, grad = wide_score, wide_grad
            self._last_ncc[name] = score
            bone.scored(score, grad, s.fail_ncc)
            bone.seconds += time.perf_counter() - start
            bone.evaluations += n
        return result

    def _by_least_squares(self) -> bool:
        """Whether bones are refined by least squares (:attr:`Settings.refinement`)."""
        return self.settings.kpm and self.settings.refinement == "least_squares"

    def _match_resolution(
        self, frame: int, poses: dict[str, np.ndarray], result: FrameResult
    ) -> None:
        """Per bone, the blur of the frames along (u, v) that maximises its NCC at ``poses``:
        the best pair on the :data:`FRAME_BLUR_MM` grid, each axis refined by a parabola
        through its neighbours. The DRRs carry the CBCT's blur, the panel does not, and the
        mismatch biases depth. A mesh's render is sharper than any frame: its own blur is
        matched instead (:meth:`_match_model_blur`). Re-scores ``result``."""
        level, grid = self.levels[-1], FRAME_BLUR_MM
        pairs = [(float(u), float(v)) for u in grid for v in grid]
        for name, bone in result.bones.items():
            if math.isnan(bone.ncc):
                continue
            if isinstance(self.bones[name], ImplantModel):
                self._match_model_blur(frame, name, poses, bone)
                continue
            objective = self._objective(frame, level, name, poses)
            image = objective.image(poses[name])
            scores = np.array(
                [
                    ncc(self._target(frame, level, pair)[objective.crop], image, objective.mask)
                    for pair in pairs
                ]
            ).reshape(len(grid), len(grid))
            best = np.unravel_index(np.argmax(scores), scores.shape)
            self._blur_rotation[name] = poses[name][:3, :3].copy()
            self.frame_blur_mm[name] = tuple(
                _parabola_peak(grid, np.take(scores, best[1 - axis], axis=1 - axis), best[axis])
                for axis in (0, 1)
            )
            bone.scored(*self._score(frame, name, poses), self.settings.fail_ncc)
            self._last_ncc[name] = bone.ncc
        chosen = set(self.frame_blur_mm.values())
        self._targets = {k: t for k, t in self._targets.items() if k[2] in chosen}
        self._blurred = {k: b for k, b in self._blurred.items() if k[1] in chosen}

    def _match_model_blur(
        self, frame: int, name: str, poses: dict[str, np.ndarray], bone: BoneResult
    ) -> None:
        """A mesh body's render blur (:data:`MODEL_BLUR_MM`, refined by a parabola) that
        maximises its NCC at ``poses`` against the unblurred frame; re-scores ``bone``."""
        level, grid = self.levels[-1], MODEL_BLUR_MM
        body = self.bones[name]
        scores = []
        for blur in grid:
            self.bones[name] = replace(body, blur_mm=float(blur))
            objective = self._objective(frame, level, name, poses)
            scores.append(objective.scores(poses[name])[0])
        best = int(np.argmax(scores))
        self.bones[name] = replace(body, blur_mm=_parabola_peak(grid, np.array(scores), best))
        bone.scored(*self._score(frame, name, poses), self.settings.fail_ncc)
        self._last_ncc[name] = bone.ncc

    def _place(
        self, frame: int, name: str, poses: dict[str, np.ndarray], history
    ) -> tuple[np.ndarray, int]:
        """Bone ``name``'s start in ``frame`` with the KPM, and the evaluations it took: its
        line search from the third frame; on the second, a carried bone at its last pose
        relative to its carrier; else ``poses[name]`` as it is."""
        if len(history) >= 2:
            return self._kpm(frame, name, poses, history)
        if history and name in CARRIER:  # carried at its last relative pose
            return _carrier_pose(name, poses) @ _carried_pose(name, history[-1]), 0
        return poses[name], 0

    def _track_bone(self, frame: int, name: str, poses: dict[str, np.ndarray], history):
        """KPM prediction (warm frames), refinement, and a wider search if the score fails."""
        s = self.settings
        evaluations = 0
        poses = dict(poses)
        if s.kpm:
            poses[name], evaluations = self._place(frame, name, poses, history)
        poses[name], n = self._refine(frame, name, poses)
        score, grad = self._score(frame, name, poses)
        evaluations += n
        previous = self._last_ncc.get(name, score)
        if s.kpm and history and (score < s.fail_ncc or score < previous - s.drop_ncc):
            # the prediction failed: widen the search about the last frame's pose (carried by
            # the carrier's new pose), keep the better of the two
            wide = dict(poses)
            wide[name] = _carrier_pose(name, poses) @ _carried_pose(name, history[-1])
            wide[name], n = self._global(frame, name, wide, scale=0.5)
            wide[name], m = self._refine(frame, name, wide)
            evaluations += n + m
            wide_score, wide_grad = self._score(frame, name, wide)
            if wide_score - self._penalty(name, wide) > score - self._penalty(name, poses):
                poses, score, grad = wide, wide_score, wide_grad
        self._last_ncc[name] = score
        result = BoneResult(poses[name], score, grad, 0.0, evaluations, False)
        result.scored(score, grad, s.fail_ncc)
        return result

    def track(
        self,
        initial: dict[str, np.ndarray],
        progress: Callable[[int, int], None] | None = None,
    ) -> list[FrameResult]:
        """Register every frame in order.

        Args:
            initial: The first frame's starting poses (4x4, mm) by body.
            progress: Called with (frames done, frames in all) after each frame.
        """
        results, history = [], []
        poses = dict(initial)
        for frame in range(len(self.frames)):
            result = self.register(frame, poses, history)
            poses = {name: r.pose for name, r in result.bones.items()}
            history.append(poses)
            results.append(result)
            if progress is not None:
                progress(frame + 1, len(self.frames))
        return results
