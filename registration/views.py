"""Several views of each time point (biplane or multi-view fluoroscopy): every body has one
pose per time point, scored on all views at once (registration.objective.JointObjective), each
view with its own frames, field, pyramid targets and matched blur (one
registration.scene.Scene per view). A view whose frame at a time point tells nothing (a
dropped frame given as NaN, or one value throughout) is left out there, not the time point."""

from __future__ import annotations

import contextlib

import numpy as np

from registration.objective import BodyModel, JointObjective, OutOfView
from registration.priors import Prior
from registration.scene import Poses, Scene, Searches


class Views(Searches):
    """The scenes of several views of the same time points, searched as one.

    Args:
        scenes: one per view, of the same bodies, frames (time points) and pyramid levels;
            the first view's frames, levels and blurs stand for the whole.
    """

    def __init__(self, scenes: list[Scene]) -> None:
        if len(scenes) < 2:
            raise ValueError(f"views need two scenes or more, got {len(scenes)}")
        first = scenes[0]
        for k, other in enumerate(scenes[1:], start=2):
            if len(other.frames) != len(first.frames):
                raise ValueError(
                    f"view {k} has {len(other.frames)} frames, view 1 has {len(first.frames)}: "
                    "the views' frames are paired by index"
                )
            if other.levels != first.levels:
                raise ValueError(
                    f"view {k}'s pyramid (binning {other.levels}, pitch "
                    f"{other.view.pitch_u_mm:g} mm) differs from view 1's ({first.levels}, "
                    f"{first.view.pitch_u_mm:g} mm): give the views panels of one pitch"
                )
            if set(other.bodies) != set(first.bodies):
                raise ValueError(f"view {k} tracks other bodies than view 1")
        self.scenes = scenes
        self.settings = first.settings
        self.roles, self.carriers = first.roles, first.carriers
        self.levels = first.levels
        self.usable = np.array([[_tells(f) for f in scene.frames] for scene in scenes])
        """Per view and frame: whether the frame holds an image (:func:`_tells`)."""

    @property
    def views(self) -> int:
        """How many views each objective scores a pose on (at most): one per scene."""
        return len(self.scenes)

    @property
    def bodies(self) -> dict[str, BodyModel]:
        """The bodies' models by name (view 1's: a mesh's matched blur is each view's own)."""
        return self.scenes[0].bodies

    @property
    def frames(self) -> np.ndarray:
        """View 1's frames (line integrals (F, rows, cols), float32)."""
        return self.scenes[0].frames

    @property
    def frame_blur_mm(self) -> dict[str, tuple[float, float]]:
        """View 1's matching blur of the frames per body, panel mm."""
        return self.scenes[0].frame_blur_mm

    def start_frame(self, frame: int, before: Poses) -> None:
        """Every view forgets what belonged to other frames (:meth:`Scene.start_frame`)."""
        for scene in self.scenes:
            scene.start_frame(frame, before)

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
    ) -> JointObjective:
        """Body ``name``'s objective over the views that see it in ``frame`` (whose frame holds
        an image, :meth:`Scene.objective` in each); :class:`OutOfView` when none does."""
        objectives, missed = [], []
        for scene in self._seeing(frame):
            try:
                objectives.append(
                    scene.objective(
                        frame,
                        level,
                        name,
                        poses,
                        lone,
                        reach,
                        beside,
                        with_prior=False,
                        outline=outline,
                    )
                )
            except OutOfView as err:
                missed.append(str(err))
        if not objectives:
            why = "; ".join(missed) or f"no camera's frame {frame} holds an image"
            raise OutOfView(f"{name} is in no view: {why}")
        return JointObjective(objectives, None if lone else self.prior(name, poses))

    def prior(self, name: str, poses: Poses) -> Prior | None:
        """Body ``name``'s priors as the first view has them (:meth:`Scene.prior`): they hold
        what that view sees worst, its depth (the patella against the femur, a body against
        the frame before); along another view's ray they would pull against what the first
        view sees well."""
        return self.scenes[0].prior(name, poses)

    def penalty(self, name: str, poses: Poses) -> float:
        """The prior's cost of body ``name`` at ``poses`` (:meth:`prior`; 0 without one)."""
        return self.scenes[0].penalty(name, poses)

    def match_frame_blur(self, frame: int, name: str, poses: Poses) -> None:
        """Each view's frames' blur for body ``name`` (:meth:`Scene.match_frame_blur`), in the
        views that see it."""
        for scene in self._seeing(frame):
            with contextlib.suppress(OutOfView):
                scene.match_frame_blur(frame, name, poses)

    def match_model_blur(self, frame: int, name: str, poses: Poses) -> None:
        """A mesh body's render blur in each view that sees it (:meth:`Scene.match_model_blur`)."""
        for scene in self._seeing(frame):
            with contextlib.suppress(OutOfView):
                scene.match_model_blur(frame, name, poses)

    def forget_other_blurs(self) -> None:
        """Each view forgets the targets at blurs no body matched."""
        for scene in self.scenes:
            scene.forget_other_blurs()

    def _seeing(self, frame: int) -> list[Scene]:
        """The scenes whose ``frame`` holds an image."""
        return [scene for scene, ok in zip(self.scenes, self.usable[:, frame], strict=True) if ok]


def _tells(image: np.ndarray) -> bool:
    """Whether a frame holds an image: some finite pixel, and not one value throughout."""
    finite = image[np.isfinite(image)]
    return finite.size > 0 and bool(finite.max() > finite.min())
