"""The similarity one body's pose is searched on: a frame against the scene rendered with the
body moved, the rest fixed (docs/algorithms/registration.md)."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from scipy.ndimage import binary_dilation

from recon.geometry import View
from recon.project import JosephProjector, row_spans
from registration.drr import BoneModel
from registration.implants import ImplantModel
from registration.se3 import compose
from registration.similarity import BlurredHighpass, gradient_ncc, highpass, ncc

BodyModel = BoneModel | ImplantModel
"""A tracked body's model: a bone from the static scan (registration.drr) or an implant
component from its mesh (registration.implants)."""

MIN_SILHOUETTE_PX = 20
"""A body casting fewer pixels (at a pyramid level) than this is out of the field of view."""


class OutOfView(ValueError):
    """The body's projection (nearly) misses the detector: its frame is flagged, not guessed."""


class Objective:
    """-NCC of one body at one pyramid level against a frame, the rest of the scene fixed.

    The soft tissue is deformed by the bodies' estimates at the start; the body carries its
    share of it (``carried``: its projector and the body's pose in the deformation, rendered
    moved by the body's motion from there). The similarity is taken over the body's
    silhouette at the start pose (and at the ``reach`` poses), dilated, less the ``excluded``
    pixels (the frame's 2D mask), in a crop of the view around it; the fixed rest of the scene
    (``background``: its line integrals through a view) is rendered once, over the crop and
    the reach of the high-pass filter around it.
    """

    def __init__(
        self,
        view: View,
        target_hp: np.ndarray,
        background: Callable[[View], np.ndarray],
        body: BodyModel,
        carried: tuple[JosephProjector, np.ndarray] | None,
        T0: np.ndarray,
        sigma_px: float,
        dilation_px: int,
        coarse: bool,
        prior: Callable[[np.ndarray], np.ndarray] | None = None,
        reach: tuple[np.ndarray, ...] = (),
        excluded: np.ndarray | None = None,
    ) -> None:
        silhouette = body.render(view, T0, coarse) > 0.02
        for T in reach:  # poses the search will visit far from T0: the mask covers them too
            silhouette |= body.render(view, T, coarse) > 0.02
        if silhouette.sum() < MIN_SILHOUETTE_PX:
            raise OutOfView(f"{body.name} leaves the field of view")
        mask = binary_dilation(silhouette, iterations=max(1, dilation_px))
        if excluded is not None:
            mask &= ~excluded
            if mask.sum() < MIN_SILHOUETTE_PX:
                raise OutOfView(
                    f"{body.name} lies where the frame tells nothing: the static scan's "
                    "box cuts it, or it is outside the exposed field"
                )
        rows, cols = np.nonzero(mask)
        margin = math.ceil(3 * sigma_px)
        r0, r1 = max(0, rows.min() - margin), min(view.rows, rows.max() + margin + 1)
        c0, c1 = max(0, cols.min() - margin), min(view.cols, cols.max() + margin + 1)
        self.view = view.cropped(r0, c0, r1 - r0, c1 - c0)
        self.crop = (slice(r0, r1), slice(c0, c1))
        self.mask = mask[self.crop]
        self.spans = row_spans(self.mask, math.ceil(4 * sigma_px))
        self.target = target_hp[self.crop]
        halo = int(4 * sigma_px + 0.5) + 1  # scipy's Gaussian reaches 4 sigma: exact in the crop
        h0, g0 = max(0, r0 - halo), max(0, c0 - halo)
        outer = view.cropped(h0, g0, min(view.rows, r1 + halo) - h0, min(view.cols, c1 + halo) - g0)
        inner = (slice(r0 - h0, r1 - h0), slice(c0 - g0, c1 - g0))
        self.background = highpass(background(outer), sigma_px)[inner]
        self.body, self.carried, self.T0 = body, carried, T0
        self._deformed_inv = None if carried is None else np.linalg.inv(carried[1])
        self.sigma, self.coarse, self.prior = sigma_px, coarse, prior
        self._sharp = None  # a mesh's render: its blur and the high-pass in one filter
        if isinstance(body, ImplantModel) and carried is None:
            blur_px = body.blur_mm / self.view.pitch_u_mm
            self._sharp = BlurredHighpass(self.mask.shape, blur_px, sigma_px)
        self.evaluations = 0
        self._unit_target: np.ndarray | None = None

    def image(self, T: np.ndarray) -> np.ndarray:
        """The scene rendered with the body at pose ``T``, high-passed (rows, cols)."""
        return self.images(T[None])[0]

    def images(self, Ts: np.ndarray) -> np.ndarray:
        """:meth:`image` at each of the poses ``Ts`` (n, 4, 4), (n, rows, cols): a bone's
        renders (and its carried soft tissue's) each in one call of the projector."""
        if self._sharp is not None:
            return np.array(
                [
                    self.background
                    + self._sharp(self.body.render(self.view, T, self.coarse, blurred=False))
                    for T in Ts
                ]
            )
        moving = self.body.render_many(self.view, Ts, self.coarse, self.spans)
        if self.carried is not None:
            deformed = np.array([T @ self._deformed_inv for T in Ts])
            moving += self.carried[0].project_moved_many(self.view, deformed, self.spans)
        return np.array([self.background + highpass(m, self.sigma) for m in moving])

    def __call__(self, x: np.ndarray) -> float:
        self.evaluations += 1
        return self.cost(compose(np.asarray(x, dtype=np.float64), self.T0, self.body.centroid_mm))

    def residuals(self, x: np.ndarray) -> np.ndarray:
        """Target minus render over the mask, each zero-mean and of unit norm (half the
        squared norm is 1 - NCC), and the prior's terms times sqrt(2), at pose ``x``."""
        return self.residuals_many(np.asarray(x, dtype=np.float64)[None])[0]

    def residuals_many(self, xs: np.ndarray) -> np.ndarray:
        """:meth:`residuals` at each of the poses ``xs`` (n, 6), (n, m): rendered together
        (:meth:`images`), or one by one when one of them is behind a view's source."""
        self.evaluations += len(xs)
        Ts = np.array([compose(x, self.T0, self.body.centroid_mm) for x in xs])
        if self._unit_target is None:
            self._unit_target = _unit(self.target[self.mask])
        return np.array(
            [
                np.append(
                    # no view renders the pose: the worst residual
                    self._unit_target
                    - (-self._unit_target if image is None else _unit(image[self.mask])),
                    _prior_terms(self.prior, T),
                )
                for image, T in zip(self._each_image(Ts), Ts, strict=True)
            ]
        )

    def scores(self, T: np.ndarray) -> tuple[float, float]:
        """NCC and gradient NCC at pose ``T`` (no prior)."""
        image = self.image(T)
        return ncc(self.target, image, self.mask), gradient_ncc(self.target, image, self.mask)

    def cost(self, T: np.ndarray) -> float:
        """-NCC at pose T plus the prior (if any); +1 (worst) for poses no view can render
        (e.g. behind the source)."""
        return self.costs(T[None])[0]

    def costs(self, Ts: np.ndarray) -> np.ndarray:
        """:meth:`cost` at each of the poses ``Ts`` (n, 4, 4), rendered together
        (:meth:`images`)."""
        return np.array(
            [
                _penalty(self.prior, T)
                + (1.0 if image is None else -ncc(self.target, image, self.mask))
                for image, T in zip(self._each_image(Ts), Ts, strict=True)
            ]
        )

    def _each_image(self, Ts: np.ndarray) -> list[np.ndarray | None]:
        """:meth:`image` at each of the poses ``Ts``, None where no view renders the pose
        (behind the source): rendered together, or one by one when one of them is not."""
        try:
            return list(self.images(Ts))
        except ValueError:
            pass
        each: list[np.ndarray | None] = []
        for T in Ts:
            try:
                each.append(self.image(T))
            except ValueError:
                each.append(None)
        return each


class JointObjective:
    """One body's objective over several views of a time point: the mean of the views'
    similarity (each an :class:`Objective` without a prior) plus one prior, at the same pose
    in the common world.

    ``cost`` is the views' mean -NCC plus the prior's squared terms; ``residuals`` stacks the
    views' residuals scaled by ``1/sqrt(N)`` and the prior's terms times sqrt(2) (half the
    squared norm is the mean of ``1 - NCC`` plus the prior); ``scores`` are the views' mean NCC
    and gradient NCC (registration.views.Views builds it of the views that see the body).
    """

    def __init__(
        self,
        objectives: list[Objective],
        prior: Callable[[np.ndarray], np.ndarray] | None = None,
    ) -> None:
        if not objectives:
            raise ValueError("no view holds the body")
        self.views, self.prior = objectives, prior
        self.body, self.T0 = objectives[0].body, objectives[0].T0
        self.evaluations = 0

    def __call__(self, x: np.ndarray) -> float:
        self.evaluations += 1
        return self.cost(compose(np.asarray(x, dtype=np.float64), self.T0, self.body.centroid_mm))

    def residuals(self, x: np.ndarray) -> np.ndarray:
        """The views' residuals (:meth:`Objective.residuals`) stacked over ``sqrt(N)``, then
        the prior's terms times sqrt(2), at pose ``x``."""
        return self.residuals_many(np.asarray(x, dtype=np.float64)[None])[0]

    def residuals_many(self, xs: np.ndarray) -> np.ndarray:
        """:meth:`residuals` at each of the poses ``xs`` (n, 6), (n, m), each view's rendered
        together (:meth:`Objective.residuals_many`)."""
        self.evaluations += len(xs)
        scale = 1.0 / math.sqrt(len(self.views))
        stacked = np.hstack([o.residuals_many(xs) for o in self.views]) * scale
        if self.prior is None:
            return stacked
        Ts = [compose(x, self.T0, self.body.centroid_mm) for x in xs]
        return np.hstack((stacked, [_prior_terms(self.prior, T) for T in Ts]))

    def scores(self, T: np.ndarray) -> tuple[float, float]:
        """The views' mean NCC and mean gradient NCC at pose ``T`` (no prior)."""
        pairs = np.array([o.scores(T) for o in self.views])
        return float(pairs[:, 0].mean()), float(pairs[:, 1].mean())

    def cost(self, T: np.ndarray) -> float:
        """The views' mean cost (:meth:`Objective.cost`) plus the prior at pose ``T``."""
        return self.costs(T[None])[0]

    def costs(self, Ts: np.ndarray) -> np.ndarray:
        """:meth:`cost` at each of the poses ``Ts`` (n, 4, 4), each view's rendered together
        (:meth:`Objective.costs`)."""
        views = np.array([o.costs(Ts) for o in self.views])
        return np.array(
            [float(np.mean(views[:, k])) + _penalty(self.prior, T) for k, T in enumerate(Ts)]
        )


Searched = Objective | JointObjective
"""What the searches run on: one view's objective or several views' (registration.search)."""


def _penalty(prior: Callable[[np.ndarray], np.ndarray] | None, T: np.ndarray) -> float:
    """The prior's squared terms at pose ``T`` (0 without a prior)."""
    return 0.0 if prior is None else float(np.sum(prior(T) ** 2))


def _prior_terms(prior: Callable[[np.ndarray], np.ndarray] | None, T: np.ndarray) -> np.ndarray:
    """The prior's residual terms at pose ``T``, its terms times sqrt(2) (none without one):
    half their squared norm is :func:`_penalty`."""
    return np.empty(0) if prior is None else math.sqrt(2.0) * prior(T)


def _unit(values: np.ndarray) -> np.ndarray:
    """``values`` less their mean, scaled to unit norm (float64; zeros when constant)."""
    centred = values.astype(np.float64) - values.mean(dtype=np.float64)
    norm = np.linalg.norm(centred)
    return centred / norm if norm > 0 else centred
