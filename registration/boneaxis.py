"""BoneAxis-Reg: per-bone 6-DoF 2D-3D registration of a fluoroscopy sequence (SYSTEM.md).

Each bone is scored against a scene DRR: the soft tissue and the other bones at their current
estimates stay fixed while one bone moves, and the similarity is NCC of high-pass filtered
images over the bone's dilated silhouette (registration.similarity). Poses are searched as
6-vectors x = (t mm, r deg) about the bone's current centroid, in world axes:
``T(x) = [R(r), (I - R(r)) c + t] T0``.

a) first frame: the bone's principal axis (PCA of its voxels) orients a bounded box, searched
   by differential evolution (global initialisation, seeded);
b) kinematic priority module (KPM), from the third frame: the pose is predicted with constant
   velocity (the last frame-to-frame motion repeated) and searched first along that motion
   (T_n = T_{n-1} exp(lambda S)); the search widens (a small DE box) only when the similarity
   after refinement says the prediction failed;
c) refinement: Powell then Nelder-Mead, coarse (binned panel) to fine.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import expm, logm
from scipy.ndimage import binary_dilation
from scipy.optimize import differential_evolution, minimize, minimize_scalar
from scipy.spatial.transform import Rotation

from recon.geometry import View
from registration.drr import BoneModel
from registration.similarity import gradient_ncc, highpass, ncc

TRACK_ORDER = ("tibia_fibula", "femur", "patella")
"""Bones are registered in this order each frame (largest and slowest first)."""


@dataclass(frozen=True)
class Settings:
    """Registration settings (mm and degrees)."""

    levels: tuple[int, ...] = (4, 2)
    """Panel binning factors, coarse to fine."""
    highpass_mm: float = 3.0
    mask_dilation_mm: float = 4.0
    de_translation_mm: float = 12.0
    de_long_axis_deg: float = 15.0
    de_other_axes_deg: float = 8.0
    de_popsize: int = 10
    de_maxiter: int = 30
    powell_maxfev: int = 400
    nelder_mead_maxfev: int = 300
    kpm: bool = True
    global_init: bool = True
    powell: bool = True
    fail_ncc: float = 0.5
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
    """-NCC of one bone at one binning level against a frame, the rest of the scene fixed."""

    def __init__(
        self,
        view: View,
        target_hp: np.ndarray,
        background_hp: np.ndarray,
        bone: BoneModel,
        T0: np.ndarray,
        sigma_px: float,
        dilation_px: int,
    ) -> None:
        silhouette = bone.render(view, T0) > 0.02
        if silhouette.sum() < 20:
            raise ValueError(f"bone {bone.name} leaves the field of view")
        mask = binary_dilation(silhouette, iterations=max(1, dilation_px))
        rows, cols = np.nonzero(mask)
        margin = math.ceil(3 * sigma_px)
        r0, r1 = max(0, rows.min() - margin), min(view.rows, rows.max() + margin + 1)
        c0, c1 = max(0, cols.min() - margin), min(view.cols, cols.max() + margin + 1)
        self.view = view.cropped(r0, c0, r1 - r0, c1 - c0)
        self.mask = mask[r0:r1, c0:c1]
        self.target = target_hp[r0:r1, c0:c1]
        self.background = background_hp[r0:r1, c0:c1]
        self.bone, self.T0, self.sigma = bone, T0, sigma_px
        self.evaluations = 0

    def image(self, T: np.ndarray) -> np.ndarray:
        return self.background + highpass(self.bone.render(self.view, T), self.sigma)

    def __call__(self, x: np.ndarray) -> float:
        self.evaluations += 1
        T = compose(np.asarray(x, dtype=np.float64), self.T0, self.bone.centroid_mm)
        return -ncc(self.target, self.image(T), self.mask)


def principal_axes(points_mm: np.ndarray) -> np.ndarray:
    """Columns: the bone's principal axes (PCA), the longest first."""
    centered = points_mm - points_mm.mean(axis=0)
    _, _, vt = np.linalg.svd(centered[:: max(1, len(centered) // 20000)], full_matrices=False)
    return vt.T


class Tracker:
    """Registers every bone in every frame of a fluoroscopy sequence.

    Args:
        view: the fluoroscopy view at full resolution.
        frames: line integrals (F, rows, cols).
        bones: the tracked bones (registration.drr.bone_models).
        background: fixed scene part per frame (soft tissue), or None.
        settings: registration settings.
    """

    def __init__(
        self,
        view: View,
        frames: np.ndarray,
        bones: dict[str, BoneModel],
        settings: Settings | None = None,
    ) -> None:
        self.view = view
        self.frames = np.asarray(frames, dtype=np.float32)
        self.bones = bones
        self.settings = settings or Settings()
        self._views = {b: view.binned(b) for b in self.settings.levels}
        self._targets: dict[tuple[int, int], np.ndarray] = {}

    def _sigma_px(self, level: int) -> float:
        return self.settings.highpass_mm / self._views[level].pitch_u_mm

    def _target(self, frame: int, level: int) -> np.ndarray:
        key = (frame, level)
        if key not in self._targets:
            image = self.frames[frame]
            if level > 1:
                rows, cols = self._views[level].rows, self._views[level].cols
                image = (
                    image[: rows * level, : cols * level]
                    .reshape(rows, level, cols, level)
                    .mean(axis=(1, 3))
                )
            self._targets[key] = highpass(image, self._sigma_px(level))
        return self._targets[key]

    def _objective(self, frame: int, level: int, name: str, poses: dict[str, np.ndarray]):
        view = self._views[level]
        others = np.zeros((view.rows, view.cols), dtype=np.float32)
        for other, model in self.bones.items():
            if other != name:
                others += model.render(view, poses[other])
        dilation = round(self.settings.mask_dilation_mm / view.pitch_u_mm)
        return _Objective(
            view,
            self._target(frame, level),
            highpass(others, self._sigma_px(level)),
            self.bones[name],
            poses[name],
            self._sigma_px(level),
            dilation,
        )

    def _refine(
        self, frame: int, name: str, poses: dict[str, np.ndarray]
    ) -> tuple[np.ndarray, int]:
        s = self.settings
        evaluations = 0
        for i, level in enumerate(s.levels):
            objective = self._objective(frame, level, name, poses)
            x0 = np.zeros(6)
            if s.powell and i == 0:
                x0 = minimize(
                    objective,
                    x0,
                    method="Powell",
                    options={"maxfev": s.powell_maxfev, "xtol": 1e-2, "ftol": 1e-6},
                ).x
            step = 1.0 if i == 0 else 0.3
            simplex = np.vstack((x0, x0 + step * np.eye(6)))
            x = minimize(
                objective,
                x0,
                method="Nelder-Mead",
                options={
                    "maxfev": s.nelder_mead_maxfev,
                    "initial_simplex": simplex,
                    "xatol": 1e-3,
                    "fatol": 1e-7,
                },
            ).x
            poses = {**poses, name: compose(x, poses[name], self.bones[name].centroid_mm)}
            evaluations += objective.evaluations
        return poses[name], evaluations

    def _global(
        self, frame: int, name: str, poses: dict[str, np.ndarray], scale: float = 1.0
    ) -> tuple[np.ndarray, int]:
        """Differential evolution in a box aligned with the bone's principal axes."""
        s = self.settings
        level = s.levels[0]
        objective = self._objective(frame, level, name, poses)
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

    def _score(self, frame: int, name: str, poses: dict[str, np.ndarray]) -> tuple[float, float]:
        level = self.settings.levels[-1]
        objective = self._objective(frame, level, name, poses)
        image = objective.image(poses[name])
        return (
            ncc(objective.target, image, objective.mask),
            gradient_ncc(objective.target, image, objective.mask),
        )

    def _kpm(self, frame: int, name: str, poses, history) -> tuple[np.ndarray, int]:
        """Line search along the last frame-to-frame motion (the kinematic direction)."""
        T1, T2 = history[-2][name], history[-1][name]
        twist = np.real(logm(np.linalg.inv(T1) @ T2))
        level = self.settings.levels[0]
        base = {**poses, name: T2}
        objective = self._objective(frame, level, name, base)

        def along(lam: float) -> float:
            return -ncc(objective.target, objective.image(T2 @ expm(lam * twist)), objective.mask)

        best = minimize_scalar(
            along, bounds=(-0.5, 2.5), method="bounded", options={"xatol": 0.02, "maxiter": 25}
        )
        return T2 @ expm(best.x * twist), best.nfev

    def register(
        self, frame: int, poses: dict[str, np.ndarray], history: list[dict[str, np.ndarray]]
    ) -> FrameResult:
        """Register every bone in ``frame`` starting from ``poses`` (previous estimates)."""
        s = self.settings
        result = FrameResult(frame)
        poses = dict(poses)
        for name in TRACK_ORDER:
            start = time.perf_counter()
            evaluations = 0
            if not history and s.global_init:
                poses[name], n = self._global(frame, name, poses)
                evaluations += n
            elif s.kpm and len(history) >= 2:
                poses[name], n = self._kpm(frame, name, poses, history)
                evaluations += n
            poses[name], n = self._refine(frame, name, poses)
            evaluations += n
            score, grad = self._score(frame, name, poses)
            failed = score < s.fail_ncc
            if failed and s.kpm and history:  # the prediction failed: widen the search
                poses[name], n = self._global(frame, name, poses, scale=0.5)
                poses[name], m = self._refine(frame, name, poses)
                evaluations += n + m
                score, grad = self._score(frame, name, poses)
                failed = score < s.fail_ncc
            result.bones[name] = BoneResult(
                poses[name], score, grad, time.perf_counter() - start, evaluations, failed
            )
        return result

    def track(self, initial: dict[str, np.ndarray], progress=None) -> list[FrameResult]:
        """Register every frame in order; ``initial`` are the first frame's starting poses."""
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
