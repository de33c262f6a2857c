"""BoneAxis-Reg's tracker: every body (a bone or an implant component) in every frame of a
fluoroscopy sequence seen by one camera or several (docs/algorithms/registration.md).

Each body is scored against the scene (registration.objective): the soft tissue and the other
bodies at their current estimates stay fixed while one moves. Frame by frame:

a) first frame: differential evolution in a box along the body's principal axes (the long
   bones alone and at once, then the patella against them), Powell then Nelder-Mead coarse to
   fine, the frames' blur matched to the renders (registration.resolution), and further
   passes that refine each body against the others' new estimates;
b) later frames with the kinematic priority module (KPM, registration.priors): every body
   starts at its constant-velocity prediction, is placed by a line search along its last
   motion and refined by Levenberg-Marquardt on the coarse levels, then on the finest against
   the others' new estimates; a body whose score fails or drops is searched again about its
   last pose, keeping the better.

The patella carries the patellofemoral prior, and any body may carry a depth prior
(registration.settings.Settings).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import replace

import numpy as np
from threadpoolctl import threadpool_limits

from recon.geometry import View
from registration.drr import SoftTissue
from registration.implants import ImplantModel
from registration.objective import BodyModel, OutOfView
from registration.priors import (
    JOINT_SCAN_DEG,
    KPM_LAMBDA,
    carried_pose,
    carrier_pose,
    held_depth,
    joint_screw,
    kinematic_direction,
    predict,
)
from registration.results import BodyResult, FrameResult
from registration.roles import LONE_ROLES, Role, partners, tracking_order
from registration.scene import Poses, Scene
from registration.se3 import twist_exp
from registration.search import at_once, kinematic_line_search
from registration.settings import Settings
from registration.views import Views

Refined = Callable[[Poses], tuple[np.ndarray, int, float, float]]
"""A refinement of one body from poses: its pose, the evaluations, its NCC and gradient NCC."""


class Tracker:
    """Registers every body in every frame of a fluoroscopy sequence.

    Args:
        view: the fluoroscopy view at full resolution, or one per camera (biplane and
            multi-view fluoroscopy, registration.views: each body's pose is scored on every
            view that sees it; the first view's depth is the KPM's held depth).
        frames: line integrals (F, rows, cols), or one such stack per view (frames paired by
            index).
        bodies: the tracked bodies by name: bones (registration.drr.bone_models) or implant
            components (registration.implants.implant_model).
        settings: registration settings.
        soft_tissue: the soft tissue, deformed by the femur and the tibia
            (registration.drr.SoftTissue); None leaves it out.
        field: bool (rows, cols), the pixels the beam reaches (an image intensifier's round
            field, a collimator's shutters: registration.frames.Frames.field); the rest, and
            the band where the high-pass filter sees the field's edge, is left out of the
            similarity. None: every pixel. With several views, one per view (or None).
        roles: each body's anatomical role (femur, tibia, patella) by name, for bodies whose
            names do not say it (registration.roles.roles_of: bones and components named as
            the pipeline names them need none). The roles set the order bodies are registered
            in, which are searched alone first, and which is carried by which.
    """

    def __init__(
        self,
        view: View | Sequence[View],
        frames: np.ndarray | Sequence[np.ndarray],
        bodies: dict[str, BodyModel],
        settings: Settings | None = None,
        soft_tissue: SoftTissue | None = None,
        field: np.ndarray | Sequence[np.ndarray | None] | None = None,
        roles: dict[str, Role] | None = None,
    ) -> None:
        if not bodies:
            raise ValueError("no body to track")
        self.settings = settings or Settings()
        one = isinstance(view, View)  # one camera: its frames and field as they are
        views = [view] if one else list(view)
        stacks = [frames] if one else list(frames)
        if one or field is not None:
            fields = [field] if one else list(field)
        else:
            fields = [None] * len(views)
        if not len(views) == len(stacks) == len(fields):
            raise ValueError(
                f"{len(views)} views, {len(stacks)} frame stacks and {len(fields)} fields: "
                "one of each per camera"
            )
        self.view = views[0]
        scenes = [
            Scene(v, f, bodies, self.settings, soft_tissue, m, roles)
            for v, f, m in zip(views, stacks, fields, strict=True)
        ]
        self.scene: Scene | Views = scenes[0] if len(scenes) == 1 else Views(scenes)
        """The frames and the bodies, as each body's searches see them."""
        self.order = tracking_order(self.scene.roles)
        """The tracked bodies in the order they are registered in a frame."""
        self.partners = partners(self.scene.roles)
        """Each body's partner in the joint (registration.roles.partners), by name."""
        self._last_ncc: dict[str, float] = {}

    @property
    def roles(self) -> dict[str, Role]:
        """Each tracked body's anatomical role, by name."""
        return self.scene.roles

    @property
    def frames(self) -> np.ndarray:
        """The frames' line integrals (F, rows, cols), float32."""
        return self.scene.frames

    @property
    def bodies(self) -> dict[str, BodyModel]:
        """The tracked bodies' models by name (a mesh's with the blur matched to the frames)."""
        return self.scene.bodies

    @property
    def levels(self) -> tuple[int, ...]:
        """Binning factors of the resolution pyramid, coarse to fine."""
        return self.scene.levels

    @property
    def frame_blur_mm(self) -> dict[str, tuple[float, float]]:
        """Per body: the frames' matching blur along (u, v), panel mm."""
        return self.scene.frame_blur_mm

    def track(
        self, initial: Poses, progress: Callable[[int, int], None] | None = None
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
            poses = {name: r.T_world_body for name, r in result.bodies.items()}
            history.append(poses)
            results.append(result)
            if progress is not None:
                progress(frame + 1, len(self.frames))
        return results

    def register(self, frame: int, poses: Poses, history: list[Poses]) -> FrameResult:
        """Register every body in ``frame`` starting from ``poses`` (previous estimates).

        Warm frames with the KPM start every body at its constant-velocity prediction, so each
        is scored against the others' predictions rather than their previous poses. Cold
        frames (no history) with global initialisation run differential evolution on every
        body first: the long bones alone and at once (the rest of the scene is still at its
        wrong starting estimate), the patella, small and overlapped by the femoral condyles,
        against the long bones' new estimates; then every body is refined against the others'
        global estimates (body by body alternation). BLAS runs single-threaded meanwhile (its
        threads would fight the renderer's for the cores).

        Args:
            frame: Index of the frame.
            poses: Starting poses (4x4, mm) by body: the previous frame's estimates.
            history: The poses of the frames registered so far, oldest first.
        """
        with threadpool_limits(limits=1, user_api="blas"):
            poses = dict(poses)
            self.scene.start_frame(frame, history[-1] if history else {})
            if self.settings.kpm and len(history) >= 2:  # at constant-velocity predictions
                poses = {b: self._predicted(b, history) for b in self.order}
            if history and self._by_least_squares():
                return self._register_warm(frame, poses, history)
            return self._register_cold(frame, poses, history)

    def best_start(
        self, frame: int, name: str, candidates: list[np.ndarray], placed: Poses
    ) -> np.ndarray:
        """Body ``name``'s best start in ``frame`` among its candidate poses.

        Differential evolution in twice the first frame's box about each candidate, the
        bodies already placed in the scene, scored by its NCC on the coarsest level
        (registration.autostart); the candidates' searches run at once
        (registration.search.at_once).

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
        trials, searches = [], []
        for T in candidates:
            trial = {**{b: T for b in self.order}, **placed, name: T}
            try:
                searches.append(
                    self.scene.prepared_global_search(frame, name, trial, 2.0, True, beside)
                )
            except OutOfView:
                continue
            trials.append(trial)
        best, best_score = None, -math.inf
        for trial, (pose, _) in zip(trials, at_once(searches), strict=True):
            try:
                objective = self.scene.objective(
                    frame, self.scene.levels[0], name, trial | {name: pose}, True, beside=beside
                )
                score = objective.scores(pose)[0]
            except OutOfView:
                continue
            if score > best_score:
                best, best_score = pose, score
        if best is None:
            raise ValueError(f"no candidate start of {name} stays in the view")
        return best

    # -- a frame

    def _register_cold(self, frame: int, poses: Poses, history: list[Poses]) -> FrameResult:
        """A first frame (or any frame without least squares): the global search, then each
        body tracked (:meth:`_track_body`), the frames' blur matched, and further passes."""
        s = self.settings
        spent = {name: (0.0, 0) for name in self.order}
        if not history and s.global_init:  # the long bones at once, then the rest in turn
            lone = [name for name in self.order if self.roles[name] in LONE_ROLES]
            start = time.perf_counter()
            searches = [self.scene.prepared_global_search(frame, n, poses, lone=True) for n in lone]
            for name, (poses[name], n) in zip(lone, at_once(searches), strict=True):
                spent[name] = ((time.perf_counter() - start) / len(lone), n)
            for name in (name for name in self.order if name not in lone):
                start = time.perf_counter()
                poses[name], n = self.scene.global_search(frame, name, poses)
                spent[name] = (time.perf_counter() - start, n)
        bodies: dict[str, BodyResult] = {}
        for name in self.order:
            start = time.perf_counter()
            try:
                body = self._track_body(frame, name, poses, history)
            except OutOfView as err:
                body = BodyResult(poses[name], math.nan, math.nan, 0.0, 0, True, str(err))
            bodies[name] = body.spent(spent[name][0] + time.perf_counter() - start, spent[name][1])
            poses[name] = body.T_world_body
        matching = not history and s.frame_blur_mm is None
        if matching:  # then at least one more pass, against the matched frames
            self._match_resolution(frame, poses, bodies)
        for _ in range(max(s.passes - 1, int(matching))):  # each against the others' new poses
            for name, body in bodies.items():
                if not math.isnan(body.ncc):
                    bodies[name] = self._another_pass(frame, name, poses, body, bool(history))
                    poses[name] = bodies[name].T_world_body
        return FrameResult(frame, bodies)

    def _register_warm(self, frame: int, poses: Poses, history: list[Poses]) -> FrameResult:
        """A frame after the first, refined by least squares: each body placed by the KPM
        (the second frame's at its last pose, carried) and refined on the coarse levels, then
        each on the finest level against the others' new estimates and scored there
        (:meth:`_finish_warm`)."""
        coarse = self.scene.levels[:-1] or self.scene.levels
        bodies: dict[str, BodyResult] = {}
        for name in self.order:  # first pass: the KPM and the coarse levels
            start, n = time.perf_counter(), 0
            try:
                poses[name], n = self._place(frame, name, poses, history)
                poses[name], m, _ = self.scene.least_squares(frame, name, poses, coarse)
                body = BodyResult(poses[name], math.nan, math.nan, 0.0, n + m, False)
            except OutOfView as err:
                body = BodyResult(poses[name], math.nan, math.nan, 0.0, n, True, str(err))
            bodies[name] = replace(body, seconds=time.perf_counter() - start)
        for name, body in bodies.items():  # second pass: the finest level, the check
            if not body.failed:
                bodies[name] = self._finish_warm(frame, name, poses, body, history)
                poses[name] = bodies[name].T_world_body
        return FrameResult(frame, bodies)

    # -- a body

    def _track_body(self, frame: int, name: str, poses: Poses, history: list[Poses]) -> BodyResult:
        """KPM prediction (warm frames), refinement, and a wider search if the score fails."""
        s = self.settings
        evaluations = 0
        poses = dict(poses)
        if s.kpm:
            poses[name], evaluations = self._place(frame, name, poses, history)
        poses[name], n = self.scene.refine(frame, name, poses)
        score, grad = self.scene.score(frame, name, poses)
        evaluations += n
        if s.kpm and history:

            def refined(wide: Poses) -> tuple[np.ndarray, int, float, float]:
                pose, m = self.scene.refine(frame, name, wide)
                return pose, m, *self.scene.score(frame, name, {**wide, name: pose})

            poses, score, grad, m = self._widened(frame, name, poses, history, score, grad, refined)
            evaluations += m
        self._remember(name, score)
        body = BodyResult(poses[name], score, grad, 0.0, evaluations, False)
        return body.scored(score, grad, s.fail_ncc)

    def _finish_warm(
        self, frame: int, name: str, poses: Poses, body: BodyResult, history: list[Poses]
    ) -> BodyResult:
        """Body ``name`` refined on the finest level from ``poses``, scored, and searched again
        about its last frame's pose when its score fails or drops (:meth:`_widened`)."""
        start = time.perf_counter()
        try:
            pose, n, objective = self.scene.least_squares(
                frame, name, poses, self.scene.levels[-1:]
            )
            score, grad = objective.scores(pose)
        except OutOfView as err:
            return replace(body, failed=True, reason=str(err))

        def refined(wide: Poses) -> tuple[np.ndarray, int, float, float]:
            pose, k, objective = self.scene.least_squares(frame, name, wide, self.scene.levels)
            return pose, k, *objective.scores(pose)

        poses = {**poses, name: pose}
        poses, score, grad, m = self._widened(frame, name, poses, history, score, grad, refined)
        self._remember(name, score)
        body = replace(body, T_world_body=poses[name]).scored(score, grad, self.settings.fail_ncc)
        return body.spent(time.perf_counter() - start, n + m)

    def _remember(self, name: str, score: float) -> None:
        """Body ``name``'s NCC in this frame as the bar :meth:`_widened` measures the next
        frame's drop against, unless it failed (a failed frame's score is not the body's own)."""
        if score >= self.settings.fail_ncc:
            self._last_ncc[name] = score

    def _widened(
        self,
        frame: int,
        name: str,
        poses: Poses,
        history: list[Poses],
        score: float,
        grad: float,
        refined: Refined,
    ) -> tuple[Poses, float, float, int]:
        """When body ``name``'s ``score`` fails or drops (``fail_ncc``, ``drop_ncc``, against
        its last score that did not fail): search about its last frame's pose carried by its
        carrier's new pose (differential evolution in half the first frame's box), and when
        that too fails or drops, along its motion relative to its partner in the joint
        (:meth:`_along_joint`, a line scan); each start is ``refined``, and the best by score
        less prior is kept. Returns the poses, the score, the gradient score and the
        evaluations spent."""
        s = self.settings
        previous = self._last_ncc.get(name, score)

        def lost(value: float) -> bool:
            return value < s.fail_ncc or value < previous - s.drop_ncc

        def about_last() -> tuple[Poses, int]:
            wide = {**poses, name: self._carried_forward(name, poses, history[-1])}
            wide[name], n = self.scene.global_search(frame, name, wide, scale=0.5)
            return wide, n

        def along_joint() -> tuple[Poses | None, int]:
            joint = self._along_joint(frame, name, poses, history)
            return (None, 0) if joint is None else ({**poses, name: joint[0]}, joint[1])

        best, spent = (poses, score, grad), 0
        for search in (about_last, along_joint):
            if not lost(best[1]):
                break
            trial, n = search()
            spent += n
            if trial is None:
                continue
            trial[name], m, trial_score, trial_grad = refined(trial)
            spent += m
            before = best[1] - self.scene.penalty(name, best[0])
            if trial_score - self.scene.penalty(name, trial) > before:
                best = (trial, trial_score, trial_grad)
        return *best, spent

    def _along_joint(
        self, frame: int, name: str, poses: Poses, history: list[Poses]
    ) -> tuple[np.ndarray, int] | None:
        """Body ``name``'s best start along its motion relative to its partner in the joint
        (registration.priors.joint_screw over the frames tracked so far): the partner's pose
        in this frame times the last relative pose, turned by each of
        :data:`JOINT_SCAN_DEG` about that screw, scored on the coarsest level; with the
        evaluations it took. None without a partner or a screw."""
        partner = self.partners.get(name)
        if partner is None or len(history) < 2:
            return None
        relative = [np.linalg.inv(h[partner]) @ h[name] for h in history]
        screw = joint_screw(relative)
        if screw is None:
            return None
        start = poses[partner] @ relative[-1]
        line = start @ twist_exp(np.radians(JOINT_SCAN_DEG)[:, None] * screw)
        objective = self.scene.objective(
            frame, self.scene.levels[0], name, poses, reach=tuple(line[::5])
        )
        costs = objective.costs(line)
        return line[int(np.argmin(costs))], len(costs)

    def _another_pass(
        self, frame: int, name: str, poses: Poses, body: BodyResult, polish: bool
    ) -> BodyResult:
        """Body ``name`` refined again against the others' newest estimates (Powell in 0.4
        of the refinement box, then Nelder-Mead; ``polish``: Nelder-Mead on the finest level
        only), kept when it scores better less its prior."""
        start = time.perf_counter()
        try:
            pose, n = self.scene.refine(frame, name, poses, 0.4, polish=polish)
            score, grad = self.scene.score(frame, name, {**poses, name: pose})
        except OutOfView:  # the refinement walked off the panel: keep the pass before
            pose, n, score, grad = body.T_world_body, 0, -math.inf, math.nan
        before = body.ncc - self.scene.penalty(name, poses)
        if score - self.scene.penalty(name, {**poses, name: pose}) > before:
            body = replace(body, T_world_body=pose).scored(score, grad, self.settings.fail_ncc)
        return body.spent(time.perf_counter() - start, n)

    def _place(
        self, frame: int, name: str, poses: Poses, history: list[Poses]
    ) -> tuple[np.ndarray, int]:
        """Body ``name``'s start in ``frame`` with the KPM, and the evaluations it took: its
        line search from the third frame; on the second, a carried body at its last pose
        relative to its carrier; else ``poses[name]`` as it is."""
        if len(history) >= 2:
            return self._kpm(frame, name, poses, history)
        if history and name in self.scene.carriers:  # carried at its last relative pose
            return self._carried_forward(name, poses, history[-1]), 0
        return poses[name], 0

    def _carried_forward(self, name: str, poses: Poses, last: Poses) -> np.ndarray:
        """Body ``name`` at its pose relative to its carrier in ``last`` (the frame before),
        carried by the carrier's pose in ``poses`` (in the world where it has no carrier)."""
        carrier = self.scene.carriers.get(name)
        return carrier_pose(carrier, poses) @ carried_pose(name, carrier, last)

    def _predicted(self, name: str, history: list[Poses]) -> np.ndarray:
        """Body ``name``'s constant-velocity prediction from the last two frames."""
        T_before, T_last = history[-2][name], history[-1][name]
        return self._held(
            name, predict(T_before, T_last, self.scene.bodies[name].centroid_mm), T_last
        )

    def _kpm(
        self, frame: int, name: str, poses: Poses, history: list[Poses]
    ) -> tuple[np.ndarray, int]:
        """Line search along the kinematic direction (registration.priors.kinematic_direction)
        from the last pose: a scan of :data:`KPM_LAMBDA` steps, then Brent between the best
        one's neighbours. A carried body (the patella) moves along its motion relative to its
        carrier, from the carrier's pose in this frame."""
        carrier = self.scene.carriers.get(name)
        base = carrier_pose(carrier, poses)
        carried = [carried_pose(name, carrier, h) for h in history[-3:]]
        xi = kinematic_direction(carried, self.scene.bodies[name].centroid_mm)
        start = base @ carried[-1]
        if xi is None:
            return start, 0

        def at(lam: float) -> np.ndarray:
            return self._held(name, start @ twist_exp(lam * xi), start)

        line = self._held(name, start @ twist_exp(KPM_LAMBDA[:, None] * xi), start)
        # about the frame's prediction: the soft tissue deformed as the other bodies' objectives
        objective = self.scene.objective(
            frame, self.scene.levels[0], name, poses, reach=(line[0], line[-1])
        )
        return kinematic_line_search(objective, at, line)

    def _held(self, name: str, T: np.ndarray, T_last: np.ndarray) -> np.ndarray:
        """Predictions ``T`` (..., 4, 4) of body ``name``, their depth held at ``T_last``'s
        when the settings say so (:attr:`Settings.kpm_depth`, registration.priors.held_depth)."""
        if self.settings.kpm_depth == "extrapolate":
            return T
        return held_depth(T, T_last, self.scene.bodies[name].centroid_mm, self.view.source_mm)

    def _by_least_squares(self) -> bool:
        """Whether bodies are refined by least squares (:attr:`Settings.refinement`)."""
        return self.settings.kpm and self.settings.refinement == "least_squares"

    def _match_resolution(self, frame: int, poses: Poses, bodies: dict[str, BodyResult]) -> None:
        """Per body in ``bodies`` (re-scored in place), the frames' blur that maximises its
        NCC at ``poses``, or a mesh's own blur (registration.scene.Scene.match_frame_blur,
        match_model_blur)."""
        for name, body in bodies.items():
            if math.isnan(body.ncc):
                continue
            if isinstance(self.scene.bodies[name], ImplantModel):
                self.scene.match_model_blur(frame, name, poses)
            else:
                self.scene.match_frame_blur(frame, name, poses)
            bodies[name] = body.scored(
                *self.scene.score(frame, name, poses), self.settings.fail_ncc
            )
            self._last_ncc[name] = bodies[name].ncc
        self.scene.forget_other_blurs()
