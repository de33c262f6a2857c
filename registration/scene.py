"""One view's frames and the bodies tracked in them: a body's objective on a pyramid level
(the other bodies and the soft tissue at their estimates, the frame prepared to match, the
body's priors) and the searches on it, level by level (docs/algorithms/registration.md).
:class:`Searches` holds the searches, which registration.views runs on several views."""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from recon.geometry import View
from registration import search
from registration.drr import SoftTissue, scene
from registration.implants import ImplantModel
from registration.objective import BodyModel, Objective, Searched
from registration.priors import Prior, depth_prior, joined, patellofemoral_prior
from registration.resolution import frame_blur, model_blur
from registration.roles import Role, carriers, roles_of
from registration.se3 import compose
from registration.settings import Settings
from registration.targets import Targets
from registration.tissue import DeformedTissue, truncation_mask

Poses = dict[str, np.ndarray]
"""Poses by body name, each 4x4 (mm)."""


class Searches(ABC):
    """The searches on one body's objective, level by level: a :class:`Scene`'s, or several
    views' at once (registration.views.Views)."""

    settings: Settings
    bodies: dict[str, BodyModel]
    levels: tuple[int, ...]
    views: int = 1
    """How many views each objective scores a pose on (at most)."""

    @abstractmethod
    def objective(
        self,
        frame: int,
        level: int,
        name: str,
        poses: Poses,
        lone: bool = False,
        reach: tuple[np.ndarray, ...] = (),
        beside: tuple[str, ...] = (),
        *,
        outline: bool = False,
    ) -> Searched:
        """The objective of body ``name`` on pyramid ``level`` of ``frame``, the others at
        ``poses`` (:meth:`Scene.objective`)."""

    def refine(
        self, frame: int, name: str, poses: Poses, scale: float = 1.0, polish: bool = False
    ) -> tuple[np.ndarray, int]:
        """Coarse to fine: Powell (bounded about the start by ``scale`` x refine_range) on the
        coarsest level, Nelder-Mead on the finer ones (on every level without Powell);
        ``polish``: Nelder-Mead on the finest level only."""
        s = self.settings
        box = (scale * s.refine_range[0], scale * s.refine_range[1])
        evaluations = 0
        levels = self.levels[-1:] if polish and s.powell else self.levels
        for i, level in enumerate(levels, start=len(self.levels) - len(levels)):
            objective = self.objective(frame, level, name, poses)
            by_powell = s.powell and i == 0
            if by_powell:
                x = search.powell(objective, box, s)
            if not by_powell or len(self.levels) == 1:
                x0 = x if by_powell else np.zeros(6)
                fine = i == len(self.levels) - 1
                x = search.nelder_mead(objective, x0, 0.3 if fine and i > 0 else 1.0, s)
            poses = {**poses, name: compose(x, poses[name], self.bodies[name].centroid_mm)}
            evaluations += objective.evaluations
        return poses[name], evaluations

    def least_squares(
        self, frame: int, name: str, poses: Poses, levels: tuple[int, ...]
    ) -> tuple[np.ndarray, int, Searched]:
        """Levenberg-Marquardt (registration.search) on each of ``levels`` in turn,
        ``ls_max_steps`` each (coarse, finest; ``ls_max_steps_views`` on several views).
        Returns the pose, the evaluations and the last level's objective."""
        evaluations = 0
        steps = self.settings.ls_max_steps_views if self.views > 1 else self.settings.ls_max_steps
        for level in levels:
            objective = self.objective(frame, level, name, poses)
            finest = int(level == self.levels[-1])
            broyden = self.settings.ls_broyden[finest]
            x = search.levenberg_marquardt(objective, self.settings, steps[finest], broyden)
            poses = {**poses, name: compose(x, poses[name], self.bodies[name].centroid_mm)}
            evaluations += objective.evaluations
        return poses[name], evaluations, objective

    def global_search(
        self,
        frame: int,
        name: str,
        poses: Poses,
        scale: float = 1.0,
        lone: bool = False,
        beside: tuple[str, ...] = (),
    ) -> tuple[np.ndarray, int]:
        """Differential evolution in a box aligned with the body's principal axes at its
        current pose (registration.search.global_search) on the coarsest level, a mesh
        rendered from its coarse mesh (:meth:`Scene.objective`). Returns the pose and the
        evaluations it took."""
        return self.prepared_global_search(frame, name, poses, scale, lone, beside)()

    def prepared_global_search(
        self,
        frame: int,
        name: str,
        poses: Poses,
        scale: float = 1.0,
        lone: bool = False,
        beside: tuple[str, ...] = (),
    ) -> Callable[[], tuple[np.ndarray, int]]:
        """:meth:`global_search` ready to run, its objective built now (:class:`OutOfView`
        now, not when it runs): for several run at once (registration.search.at_once), each
        from its own poses."""
        objective = self.objective(
            frame, self.levels[0], name, poses, lone, beside=beside, outline=True
        )
        T0 = poses[name]
        axes = T0[:3, :3] @ search.principal_axes(self.bodies[name].points_mm)

        def run() -> tuple[np.ndarray, int]:
            x = search.global_search(objective, axes, self.settings, scale)
            return compose(x, T0, self.bodies[name].centroid_mm), objective.evaluations

        return run

    def score(self, frame: int, name: str, poses: Poses) -> tuple[float, float]:
        """Body ``name``'s NCC and gradient NCC at ``poses`` on the finest level."""
        return self.objective(frame, self.levels[-1], name, poses).scores(poses[name])


class Scene(Searches):
    """A fluoroscopy sequence's frames and the bodies tracked in them, as one body's searches
    see them.

    Args:
        view: the fluoroscopy view at full resolution.
        frames: line integrals (F, rows, cols).
        bodies: the tracked bodies' models by name (bones or implant components).
        settings: registration settings.
        soft_tissue: the soft tissue, deformed by the femur and the tibia; None leaves it out.
        field: bool (rows, cols), the pixels the beam reaches (the rest, and the band where
            the high-pass filter sees the field's edge, is left out of the similarity); None:
            every pixel.
        roles: each body's anatomical role, by name (registration.roles.roles_of).
    """

    def __init__(
        self,
        view: View,
        frames: np.ndarray,
        bodies: dict[str, BodyModel],
        settings: Settings,
        soft_tissue: SoftTissue | None = None,
        field: np.ndarray | None = None,
        roles: dict[str, Role] | None = None,
    ) -> None:
        self.view, self.settings = view, settings
        self.roles = roles_of(bodies, roles)
        """Each body's anatomical role, by name."""
        self.carriers = carriers(self.roles)
        """Each carried body's carrier, by name (the patella's is the body playing the femur)."""
        frames = np.asarray(frames, dtype=np.float32)
        if field is not None and np.shape(field) != frames.shape[1:]:
            raise ValueError(f"field of {np.shape(field)} pixels for frames of {frames.shape[1:]}")
        field = None if field is None or np.all(field) else np.asarray(field, dtype=bool)
        self.bodies = dict(bodies)  # a mesh body's matched blur stays this scene's
        self.soft_tissue = soft_tissue
        self._tissue = None if soft_tissue is None else DeformedTissue(soft_tissue, view)
        self.levels = tuple(
            dict.fromkeys(max(1, round(mm / view.pitch_u_mm)) for mm in settings.pyramid_mm)
        )
        """Binning factors of the pyramid, coarse to fine."""
        self._views = {b: view.binned(b) for b in self.levels}
        self._targets = Targets(view, frames, field, self._views, settings.highpass_mm)
        blur = settings.frame_blur_mm or (0.0, 0.0)
        self.frame_blur_mm = {name: tuple(blur) for name in bodies}
        """Per body: the frames' matching blur along (u, v), panel mm (estimated on the first
        frame when the settings leave it open), at the body's :attr:`_blur_rotation`."""
        self._blur_rotation = {name: np.eye(3) for name in bodies}
        """Per body: its rotation when its blur was estimated (the static scan's, identity,
        for a blur given in the settings). The blur is the CBCT's, so it turns with the body."""
        self.before: Poses = {}
        """The poses of the frame before the one being registered (the depth prior's)."""

    @property
    def frames(self) -> np.ndarray:
        """The frames' line integrals (F, rows, cols), float32."""
        return self._targets.frames

    def start_frame(self, frame: int, before: Poses) -> None:
        """Forget what belonged to other frames; ``before``: the poses of the frame before
        (empty for the first)."""
        if self._tissue is not None:
            self._tissue.clear()
        self._targets.keep_frame(frame)
        self.before = before

    def objective(
        self,
        frame: int,
        level: int,
        name: str,
        poses: Poses,
        lone: bool = False,
        reach: tuple[np.ndarray, ...] = (),
        beside: tuple[str, ...] = (),
        *,
        with_prior: bool = True,
        outline: bool = False,
    ) -> Objective:
        """The objective of body ``name``, the others at ``poses`` (``lone``: the body alone
        but for those ``beside`` it, no prior, no soft tissue), masked to its silhouettes at
        ``poses`` and ``reach``; ``with_prior`` False leaves the prior out (several views
        share one: registration.views); ``outline``: a mesh renders from its coarse mesh (the
        differential evolution's hundreds of renders on the coarsest level)."""
        view = self._views[level]
        others = {b: m for b, m in self.bodies.items() if b != name and (not lone or b in beside)}
        stays = carried = None
        if not lone and self._tissue is not None:
            stays, carried = self._tissue.split(name, poses)

        def background(part: View) -> np.ndarray:
            image = scene(part, others, poses)
            if stays is not None:
                image += stays.project_moved(part, np.eye(4))
            return image

        blur_mm = self.frame_blur_mm[name]
        return Objective(
            view,
            self._targets.target(frame, level, blur_mm, self._blur_turn_deg(name, poses[name])),
            background,
            self.bodies[name],
            carried,
            poses[name],
            self._targets.sigma_px(level),
            round(self.settings.mask_dilation_mm / view.pitch_u_mm),
            self._coarse(level, name, outline),
            None if lone or not with_prior else self.prior(name, poses),
            reach,
            _either(
                self._truncation(level, name, poses, reach), self._targets.outside_field(level)
            ),
        )

    def prior(self, name: str, poses: Poses) -> Prior | None:
        """The priors of body ``name`` as a function of its pose, or None: the patellofemoral
        prior of a carried body (:attr:`carriers`) against its carrier's estimate, and the
        depth prior against the frame before (registration.priors)."""
        s, center = self.settings, self.bodies[name].centroid_mm
        carrier = self.carriers.get(name)
        patellofemoral = depth = None
        if carrier in poses:
            patellofemoral = patellofemoral_prior(s, poses[carrier], center, self.view)
        sigma_mm = s.depth_step_sigma_mm.get(name, s.depth_step_sigma_mm.get(self.roles[name]))
        if sigma_mm is not None and name in self.before:
            depth = depth_prior(s, sigma_mm, self.view, center, self.before[name])
        return joined([patellofemoral, depth])

    def penalty(self, name: str, poses: Poses) -> float:
        """The prior's cost of body ``name`` at ``poses`` (0 without a prior)."""
        prior = self.prior(name, poses)
        return 0.0 if prior is None else float(np.sum(prior(poses[name]) ** 2))

    def _truncation(
        self, level: int, name: str, poses: Poses, reach: tuple[np.ndarray, ...]
    ) -> np.ndarray | None:
        """The pixels of ``level``'s view near the static scan's cuts
        (registration.tissue.truncation_mask), or None without soft tissue or band."""
        band_mm = self.settings.truncation_band_mm
        if self.soft_tissue is None or band_mm == 0:
            return None
        return truncation_mask(self.soft_tissue, self._views[level], band_mm, name, poses, reach)

    def _coarse(self, level: int, name: str, outline: bool = False) -> bool:
        """Render with the pooled volumes when a pixel spans two voxels at the body; a mesh,
        from its coarse mesh when asked for (``outline``) on a level other than the finest."""
        view, body = self._views[level], self.bodies[name]
        if isinstance(body, ImplantModel):
            return outline and level != self.levels[-1]
        pixel_at_body = view.pitch_u_mm * float(view.depth(body.centroid_mm)[0])
        return pixel_at_body >= 2.0 * body.voxel_mm()

    def _blur_turn_deg(self, name: str, T: np.ndarray) -> int:
        """How far body ``name`` at pose ``T`` has turned in the panel's plane since its blur
        was estimated (the turn of the panel's u axis carried by the body, projected), whole
        degrees."""
        turned = T[:3, :3] @ self._blur_rotation[name].T @ self.view.e_u
        return round(math.degrees(math.atan2(turned @ self.view.e_v, turned @ self.view.e_u)))

    def match_frame_blur(self, frame: int, name: str, poses: Poses) -> None:
        """The frames' blur for body ``name`` that maximises its NCC at ``poses``
        (registration.resolution.frame_blur), turned with it from now on."""
        level = self.levels[-1]
        objective = self.objective(frame, level, name, poses)
        blur = frame_blur(
            objective, poses[name], lambda pair: self._targets.target(frame, level, pair)
        )
        self._blur_rotation[name] = poses[name][:3, :3].copy()
        self.frame_blur_mm[name] = blur

    def forget_other_blurs(self) -> None:
        """Forget the frames' targets at blurs no body matched."""
        self._targets.keep_blurs(set(self.frame_blur_mm.values()))

    def match_model_blur(self, frame: int, name: str, poses: Poses) -> None:
        """A mesh body's render blur (registration.resolution.model_blur) that maximises its
        NCC at ``poses`` against the unblurred frame."""
        level, model = self.levels[-1], self.bodies[name]

        def score(blur_mm: float) -> float:
            self.bodies[name] = replace(model, blur_mm=blur_mm)
            return self.objective(frame, level, name, poses).scores(poses[name])[0]

        self.bodies[name] = replace(model, blur_mm=model_blur(score))


def _either(a: np.ndarray | None, b: np.ndarray | None) -> np.ndarray | None:
    """The union of two optional pixel masks."""
    if a is None or b is None:
        return b if a is None else a
    return a | b
