"""A patient's motion during a static scan, estimated from the scan's own projections.

No markers and no prior scan: the bones of a first reconstruction are registered to every
projection (2D/3D, the way Berger et al., Med Phys 2016, did for weight-bearing knees), coarse
to fine, and the reconstruction is made again through the motion found:

1. **First volume.** Weighted FDK on a grid of :attr:`MotionSettings.voxel_mm` over the
   requested field, sharpened by one iterative correction (the FDK of what its own
   reprojection misses): FDK's cone-beam and ramp-window departures from the projections bias
   the registration (measured on the demo knee at 4 mm of sway: the in-plane error at the bone
   surface 0.40 -> 0.12 mm for the thigh, 0.18 -> 0.10 mm for the shank).
2. **One body.** Each view's rigid pose of the whole leg (6 parameters) by Gauss-Newton on the
   line integrals, ``|p_i - A_i(T) f|^2`` over the pixels whose rays stay inside the trusted
   field (:func:`trusted_pixels`), the Jacobian by finite differences of the Joseph projector.
   The poses are then re-centred so that their mean is the identity: the volume shows the
   patient's average pose.
3. **Two bodies.** The volume compensated for that motion is segmented
   (registration.segment): the thigh (femur, patella) and the shank (tibia, fibula) take each
   voxel in the proportion of its distance to their bones (a logistic blend over
   :attr:`MotionSettings.blend_mm`: soft tissue follows the nearest bone, no seam); every
   view's two poses (12 parameters) are fitted as in step 2 from the one-body poses. Where the
   segmentation finds no femur and tibia the leg stays one body, and the estimate says so.
   Each round fits the even views to a volume made from the odd ones and the odd views to one
   made from the even ones (each through the round before's motion): a volume holding a
   view's own data reprojects that view's pose error back to it, so fitted to such a volume
   the errors are kept from round to round (docs/algorithms/motion.md).
4. The caller reconstructs through the motion (recon.fdk with ``motion=``): each voxel
   projects through the blend of the bodies' moved matrices.

A first volume holding an implant's metal is refused (:func:`refuse_metal`): the metal hides the
bone the fit follows and its shadow is no motion.

Per-view times are not needed by the fit (every view is fitted on its own, from its
neighbour's pose); where a scan has them they are kept for the plots, else views stand for
time. A still scan comes back as identity poses within noise, and its compensated volume is
plain FDK's within noise (tests/registration/test_scan_motion.py).
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace

import numpy as np
from scipy import ndimage

from recon.fdk import estimate_orbit, fdk_reconstruct
from recon.geometry import Geometry
from recon.iterative import subsets
from recon.mar import METAL_SEED, MIN_METAL_MM3, metal_levels, soft_tissue_level
from recon.motion import BodyMotion
from recon.volume import Volume, VolumeGrid
from registration.labels import LABELS
from registration.motion_fit import ViewFit, recentred
from registration.motion_volume import missed_by, sharpened, tissue_box, trusted_pixels
from registration.segment import segment_bones

BODY_LABELS: dict[str, tuple[int, ...]] = {
    "thigh": (LABELS["femur"], LABELS["patella"]),
    "shank": (LABELS["tibia"], LABELS["fibula"]),
}
"""The bones each moving body carries."""
LEG = "leg"
"""The one body of a leg whose joint the segmentation could not separate."""

MIN_VIEWS = 60
"""Fewest views the estimate runs on: each view is fitted on its own, but the volume it is
fitted to needs an orbit's worth of views."""

MAX_COMPENSABLE_MM = 8.0
"""Largest displacement of a bone's surface (from the average pose) the compensation is trusted
for, mm: a "semi-flexed" sway peaks at 3-5 mm at the knee, and 1.2-1.6 times that at the far
ends of the bones in the field; beyond, bones blur in the first volume past what its
segmentation and the fit start from, and a scan is to be repeated."""

_NEGLIGIBLE = 1e-3
"""A body's share below which a voxel is wholly the other body's (each body's projector then
holds only its part of the field)."""
_COARSEST_MM = 2.0
"""The one-body stage runs at twice the estimate's voxel, but no coarser than this, mm: the
bones' cortex must still stand out of the soft tissue there."""
_BETTER = 0.01
"""A fitted motion is kept when it brings the projections' reprojection residual at least
this share below the still patient's."""


@dataclass(frozen=True)
class MotionSettings:
    """How the motion is estimated.

    Attributes:
        voxel_mm: grid of the volume the bodies are registered from, mm (about the pixel
            pitch at the isocentre: finer is slower, coarser biases the fit); the one-body
            stage runs at twice it (at most 2 mm), on projections binned to match.
        margin_mm: rays within this distance of the field's ends along the rotation axis are
            left out (FDK's data are incomplete there), mm.
        blend_mm: width of the thigh-shank blend, mm.
        two_body_rounds: rounds of the two-body fit, each from a volume reconstructed
            through the motion of the round before (0: the whole leg as one body).
        fit_pixel: the two-body fits run on the panel's pixels binned as far as their pitch at
            the isocentre stays within this many voxels (finer pixels: slower and more
            accurate, docs/algorithms/motion.md); the one-body fit, the start, keeps pixels no
            coarser than its voxel.
    """

    voxel_mm: float = 1.0
    margin_mm: float = 20.0
    blend_mm: float = 4.0
    two_body_rounds: int = 2
    fit_pixel: float = 1.5

    def __post_init__(self) -> None:
        for name, low, unit in (
            ("voxel_mm", 0.05, "mm"),
            ("margin_mm", 0.0, "mm"),
            ("blend_mm", 0.1, "mm"),
            ("fit_pixel", 0.1, "voxels"),
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= low):
                raise ValueError(f"{name} must be >= {low} {unit}, got {value!r}")
        if self.two_body_rounds < 0:
            raise ValueError(f"two_body_rounds must be >= 0, got {self.two_body_rounds!r}")


@dataclass(frozen=True)
class MotionEstimate:
    """The motion found, and what it amounts to.

    Attributes:
        motion: the bodies' poses per view and their weights (on the estimation grid).
        times_s: per-view times, s (None: the scan has none; views stand for time).
        displacement_mm: per view and body, the largest displacement of the body's bone
            surface from its average pose, mm (N, K).
        surface_points: per body, the bone-surface points (world mm, average pose) measured.
        notes: what the estimate had to decide (plain sentences).
        seconds: per stage, wall time.
        reprojection_rms: how far the projections are from the reprojection of the volume made
            through no motion (``still``) and through the motion fitted (``moving``), over the
            trusted pixels (line integrals).
    """

    motion: BodyMotion
    times_s: np.ndarray | None
    displacement_mm: np.ndarray
    surface_points: dict[str, np.ndarray]
    notes: tuple[str, ...] = ()
    seconds: dict[str, float] = field(default_factory=dict)
    reprojection_rms: dict[str, float] = field(default_factory=dict)

    @property
    def peak_mm(self) -> dict[str, float]:
        """Largest displacement per body over the scan, mm."""
        return {
            b: float(self.displacement_mm[:, k].max()) for k, b in enumerate(self.motion.bodies)
        }

    @property
    def peak_view(self) -> int:
        """The view where some body moved most."""
        return int(np.unravel_index(np.argmax(self.displacement_mm), self.displacement_mm.shape)[0])

    @property
    def compensable(self) -> bool:
        """Every body stayed within :data:`MAX_COMPENSABLE_MM` of its average pose."""
        return max(self.peak_mm.values()) <= MAX_COMPENSABLE_MM

    @property
    def still(self) -> bool:
        """No motion was kept: every body stood at its average pose in every view."""
        return float(self.displacement_mm.max()) == 0.0

    def verdict(self) -> str:
        """One plain sentence on the motion: how much, where, and whether to trust it."""
        peak, view = float(self.displacement_mm.max()), self.peak_view
        if self.still:
            return "stood still: no motion found in the projections"
        if not self.compensable:
            return (
                f"moved {peak:.0f} mm at view {view}, more than the {MAX_COMPENSABLE_MM:g} mm "
                "motion compensation is trusted for: repeat the scan"
            )
        parts = ", ".join(f"{b} {v:.1f} mm" for b, v in self.peak_mm.items())
        return f"moved up to {peak:.1f} mm (at view {view}; {parts}): compensated"


def body_weights(labels: Volume, blend_mm: float) -> np.ndarray | None:
    """Thigh and shank shares of each voxel (2, nz, ny, nx), float32: a logistic of the
    difference of the distances to their bones over ``blend_mm``; None unless both bodies
    have bone."""
    masks = [np.isin(labels.data, values) for values in BODY_LABELS.values()]
    if not all(m.any() for m in masks):
        return None
    spacing = labels.grid.spacing_mm[::-1]
    thigh, shank = (ndimage.distance_transform_edt(~m, sampling=spacing) for m in masks)
    share = 1.0 / (1.0 + np.exp(np.clip((thigh - shank) / blend_mm, -60.0, 60.0)))
    share = np.where(share < _NEGLIGIBLE, 0.0, np.where(share > 1.0 - _NEGLIGIBLE, 1.0, share))
    return np.stack((share, 1.0 - share)).astype(np.float32)


def _surface(mask: np.ndarray, grid: VolumeGrid, count: int = 600) -> np.ndarray:
    """Up to ``count`` points (world mm) of the mask's surface voxels, evenly drawn."""
    edge = mask & ~ndimage.binary_erosion(mask)
    index = np.argwhere(edge)
    if len(index) > count:
        index = index[np.linspace(0, len(index) - 1, count).astype(int)]
    return grid.index_to_world(index[:, ::-1].astype(np.float64))


def surface_errors_mm(
    motion: BodyMotion,
    points: dict[str, np.ndarray],
    truth: dict[str, np.ndarray],
    sources_mm: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray | None]:
    """How far ``motion`` is from the ``truth`` (``T_world_body`` (N, 4, 4) by body): per view
    and true body, the mean distance between where the two put the body's ``points`` (world
    mm, average pose; by true body), mm, and with the views' sources (N, 3) the same across
    each view's rays (what the view sees). A body of the motion the truth does not have (the
    one-body ``leg``) is compared with every true body."""
    full, across = [], []
    for k, body in enumerate(motion.bodies):
        for true_body in [body] if body in truth else list(truth):
            h = np.hstack((points[true_body], np.ones((len(points[true_body]), 1))))
            mine = np.einsum("nij,pj->npi", motion.poses[:, k, :3], h)
            theirs = np.einsum("nij,pj->npi", truth[true_body][:, :3], h)
            diff = mine - theirs
            full.append(np.linalg.norm(diff, axis=2).mean(axis=1))
            if sources_mm is not None:
                ray = theirs - np.asarray(sources_mm)[:, None]
                ray /= np.linalg.norm(ray, axis=2, keepdims=True)
                side = diff - (diff * ray).sum(axis=2, keepdims=True) * ray
                across.append(np.linalg.norm(side, axis=2).mean(axis=1))
    return np.concatenate(full), np.concatenate(across) if across else None


def check_scan(projections: np.ndarray, geometry: Geometry, times_s: np.ndarray | None) -> None:
    """ValueError (naming the field, the value and the limit) for a scan the estimate cannot
    run on: too few views, projections that do not match the geometry, times that are not one
    increasing value per view."""
    if len(geometry) < MIN_VIEWS:
        raise ValueError(
            f"the scan has {len(geometry)} views; motion estimation needs at least {MIN_VIEWS} "
            "(an orbit's worth to reconstruct what every view is registered to)"
        )
    shape = (len(geometry), geometry.rows, geometry.cols)
    if np.shape(projections) != shape:
        raise ValueError(f"projections have shape {np.shape(projections)}; the geometry {shape}")
    if times_s is not None:
        t = np.asarray(times_s, dtype=np.float64)
        if t.shape != (len(geometry),) or not np.isfinite(t).all():
            raise ValueError(f"times: one finite time per view expected, got shape {t.shape}")
        if np.any(np.diff(t) <= 0):
            first = int(np.flatnonzero(np.diff(t) <= 0)[0]) + 1
            raise ValueError(f"times must increase view by view; view {first} is at {t[first]} s")


def estimation_grid(grid: VolumeGrid, voxel_mm: float) -> VolumeGrid:
    """``grid``'s extent in cubic voxels of ``voxel_mm``."""
    extent = np.asarray(grid.spacing_mm) * np.asarray(grid.size_xyz)
    size = tuple(max(8, round(e / voxel_mm)) for e in extent)
    return VolumeGrid.centered(size, voxel_mm, tuple(grid.center_mm))


def _binned(
    projections: np.ndarray, geometry: Geometry, factor: int
) -> tuple[np.ndarray, Geometry]:
    """Projections and views with ``factor x factor`` pixels averaged."""
    if factor == 1:
        return projections, geometry
    n, rows, cols = projections.shape
    r, c = rows // factor, cols // factor
    cut = projections[:, : r * factor, : c * factor]
    binned = cut.reshape(n, r, factor, c, factor).mean(axis=(2, 4), dtype=np.float32)
    return binned, Geometry([v.binned(factor) for v in geometry])


def estimate_motion(
    projections: np.ndarray,
    geometry: Geometry,
    grid: VolumeGrid,
    *,
    times_s: np.ndarray | None = None,
    orbit_geometry: Geometry | None = None,
    settings: MotionSettings = MotionSettings(),
    say: Callable[[str], None] | None = None,
    progress: Callable[[str, int, int], None] | None = None,
) -> MotionEstimate:
    """The patient's motion during a scan, from its projections (module docstring).

    Args:
        projections: line integrals (N, rows, cols).
        geometry: the views the projections were taken through.
        grid: the field to reconstruct (its extent is the estimate's).
        times_s: per-view times, s; None: views stand for time (and the estimate says so).
        orbit_geometry: the views whose orbit sets FDK's weights (as in recon.fdk).
        settings: how to estimate.
        say: a line per stage.
        progress: ``progress(stage, views_done, views_total)`` during the fits.

    Raises:
        ValueError: :func:`check_scan`'s, or a first volume without bone.
    """
    check_scan(projections, geometry, times_s)
    scan = _Estimation(
        np.asarray(projections, dtype=np.float32),
        geometry,
        orbit_geometry,
        settings,
        say or (lambda _m: None),
        progress,
    )
    if times_s is None:
        scan.notes.append("the geometry carries no per-view times: motion is given per view index")
    voxel = max(settings.voxel_mm, max(grid.spacing_mm))  # no finer than the field asked for
    motion, coarse, bone = scan.one_body(grid, voxel)
    fine = estimation_grid(coarse, voxel)
    scan = scan.binned_to(settings.fit_pixel * voxel)
    motion, surfaces = scan.two_bodies(motion, fine, {LEG: _surface(bone, coarse)})
    motion, misses = scan.kept_if_consistent(motion, fine)
    displacement = motion.displacement_mm(surfaces)
    times = None if times_s is None else np.asarray(times_s, dtype=np.float64)
    return MotionEstimate(
        motion, times, displacement, surfaces, tuple(scan.notes), scan.seconds, misses
    )


@dataclass
class _Estimation:
    """A scan's projections and views, and the stages of :func:`estimate_motion` run on them
    (each timed into ``seconds``; what they find out, in ``notes``)."""

    proj: np.ndarray
    geometry: Geometry
    orbit_geometry: Geometry | None
    settings: MotionSettings
    tell: Callable[[str], None]
    progress: Callable[[str, int, int], None] | None
    notes: list[str] = field(default_factory=list)
    seconds: dict[str, float] = field(default_factory=dict)

    def binned_to(self, pixel_mm: float) -> _Estimation:
        """The scan with its pixels binned as far as their pitch at the isocentre stays within
        ``pixel_mm`` (notes and timings shared with this one)."""
        factor = _binning(self.geometry, pixel_mm)
        if factor == 1:
            return self
        proj, geometry = _binned(self.proj, self.geometry, factor)
        orbit = self.orbit_geometry
        orbit = None if orbit is None else _binned(self.proj[:1], orbit, factor)[1]
        return replace(self, proj=proj, geometry=geometry, orbit_geometry=orbit)

    def fitted(
        self,
        stage: str,
        fits: list[tuple[np.ndarray, ViewFit]],
        start: np.ndarray | None,
        iterations: int,
    ) -> np.ndarray:
        """Every view's poses, re-centred, (N, bodies, 4, 4): each ``(views, fit)`` of ``fits``
        fits its views (indices into the scan) from ``start``'s."""
        n, done = len(self.geometry), 0
        poses = np.empty((n, len(fits[0][1].parts), 4, 4))
        for views, fit in fits:
            report = None if self.progress is None else self._reporter(stage, done, n)
            first = None if start is None else start[views]
            poses[views] = fit.all_views(first, iterations, report)
            done += len(views)
        return recentred(poses, fits[0][1].centers)

    def _reporter(self, stage: str, done: int, total: int) -> Callable[[int, int], None]:
        """A fit's ``progress(views_done, views)`` as the stage's, ``done`` views ahead."""
        progress = self.progress
        return lambda d, _t: progress(stage, done + d, total)

    def one_body(self, grid: VolumeGrid, voxel: float) -> tuple[BodyMotion, VolumeGrid, np.ndarray]:
        """The whole leg's motion at half the resolution (the motion the two bodies share, to
        start from); the tissue's box it was fitted on, and the bone there (bool)."""
        coarse = estimation_grid(grid, max(voxel, min(2.0 * voxel, _COARSEST_MM)))
        scan = self.binned_to(coarse.spacing_mm[0])
        small, views, small_orbit = scan.proj, scan.geometry, scan.orbit_geometry
        with _timed(self.seconds, "one body"):
            first = fdk_reconstruct(small, views, coarse, orbit_geometry=small_orbit)
            refuse_metal(Volume(first.volume.data, coarse, "1/mm"))
            coarse = tissue_box(Volume(first.volume.data, coarse, "1/mm"))
            self.tell(
                f"one body: {coarse.size_xyz} voxels of {coarse.spacing_mm[0]:g} mm, "
                f"{len(self.geometry)} views"
            )
            volume, mask = sharpened(small, views, coarse, None, small_orbit)
            try:
                labels = segment_bones(Volume(volume, coarse, "1/mm"))
                bone = np.isin(labels.data, [v for vals in BODY_LABELS.values() for v in vals])
            except ValueError as err:
                if "without bone" in str(err):
                    raise ValueError(
                        f"no bone to register in the first volume ({err}): motion is estimated "
                        "from the bones"
                    ) from None
                bone = volume > 0.5 * np.percentile(volume, 99)
            center = coarse.index_to_world(np.argwhere(bone).mean(axis=0)[::-1])
            leg = np.ones((1, *coarse.shape), np.float32)
            margin = self.settings.margin_mm
            trusted = trusted_pixels(views, Volume(volume, coarse, "1/mm"), mask, margin)
            fit = ViewFit(volume, coarse, leg, center[None], small, views, trusted)
            poses = self.fitted("one body", [(np.arange(len(views)), fit)], None, 2)
        return BodyMotion((LEG,), poses), coarse, bone

    def two_bodies(
        self, motion: BodyMotion, fine: VolumeGrid, surfaces: dict[str, np.ndarray]
    ) -> tuple[BodyMotion, dict[str, np.ndarray]]:
        """The thigh's and the shank's motion on ``fine``, from the leg's, over
        ``settings.two_body_rounds`` rounds; the leg's (and a note) where the segmentation does
        not separate them. Each body's surface points, mm.

        Each round reconstructs the even and the odd views apart, through the motion of the
        round before, and fits each view to the volume of the other half: a volume holding a
        view's own data reprojects that view's pose error back to it, and the rounds would
        keep it (module docstring)."""
        proj, geometry, margin = self.proj, self.geometry, self.settings.margin_mm
        halves = subsets(len(geometry), 2)  # the even views, the odd views: each spans the orbit
        for round_ in range(self.settings.two_body_rounds):
            stage = f"two bodies, round {round_ + 1}"
            with _timed(self.seconds, stage):
                made = [self._half_volume(views, motion, fine) for views in halves]
                if round_ == 0:
                    volume = Volume(0.5 * (made[0][0] + made[1][0]), fine, "1/mm")
                    trusted = trusted_pixels(geometry, volume, made[0][1] & made[1][1], margin)
                    try:
                        labels = segment_bones(volume)
                        weights = body_weights(labels, self.settings.blend_mm)
                    except ValueError as err:
                        self.notes.append(
                            f"the leg is one body: its bones were not separated ({err})"
                        )
                        break
                    if weights is None:
                        self.notes.append(
                            "the leg is one body: the femur or the tibia was not found"
                        )
                        break
                    masks = [np.isin(labels.data, v) for v in BODY_LABELS.values()]
                    centers = np.array(
                        [fine.index_to_world(np.argwhere(m).mean(axis=0)[::-1]) for m in masks]
                    )
                    surfaces = {
                        b: _surface(m, fine) for b, m in zip(BODY_LABELS, masks, strict=True)
                    }
                    start = np.repeat(motion.poses, 2, axis=1)
                else:
                    start = motion.poses
                self.tell(
                    f"{stage}: the thigh and the shank registered to each of {len(geometry)} "
                    "views, each to the other half's volume"
                )
                fits = []
                for views, (other, _mask) in zip(halves, made[::-1], strict=True):
                    part = ViewFit(
                        other, fine, weights, centers, proj[views], geometry[views], trusted[views]
                    )
                    fits.append((views, part))
                poses = self.fitted(stage, fits, start, 1)
                motion = BodyMotion(tuple(BODY_LABELS), poses, weights, fine)
        return motion, surfaces

    def _half_volume(
        self, views: np.ndarray, motion: BodyMotion, grid: VolumeGrid
    ) -> tuple[np.ndarray, np.ndarray]:
        """The sharpened volume of ``views`` alone through ``motion`` on ``grid``, and its
        FDK mask."""
        orbit = None if self.orbit_geometry is None else self.orbit_geometry[views]
        return sharpened(
            self.proj[views], self.geometry[views], grid, motion.of_views(views), orbit
        )

    def kept_if_consistent(
        self, motion: BodyMotion, fine: VolumeGrid
    ) -> tuple[BodyMotion, dict[str, float]]:
        """``motion``, or the still patient (and a note) unless the projections agree with a
        volume made through it better than with the still one's (noise in a still scan's fit
        is not motion); the reprojection RMS of both."""
        proj, geometry, orbit = self.proj, self.geometry, self.orbit_geometry
        with _timed(self.seconds, "consistency"):
            volume, mask, missed = missed_by(proj, geometry, fine, None, orbit)
            margin = self.settings.margin_mm
            seen = trusted_pixels(geometry, Volume(volume, fine, "1/mm"), mask, margin)
            misses = {"still": float(np.sqrt(np.mean(missed[seen] ** 2)))}
            missed = missed_by(proj, geometry, fine, motion, orbit)[2]
            misses["moving"] = float(np.sqrt(np.mean(missed[seen] ** 2)))
        if misses["moving"] >= misses["still"] * (1.0 - _BETTER):
            self.notes.append(
                "no motion found: the projections agree as well with the still patient "
                f"(reprojection RMS {misses['still']:.4g}) as with the motion fitted "
                f"({misses['moving']:.4g})"
            )
            still = np.tile(np.eye(4), (len(geometry), len(motion.bodies), 1, 1))
            motion = BodyMotion(motion.bodies, still, motion.weights, motion.grid)
        return motion, misses


def refuse_metal(first: Volume) -> None:
    """ValueError when the first volume holds an implant's metal (recon.mar's threshold).

    Measured on the knee replacement (bench/motion.py): its femoral component, tray and stem
    fill the bone ends the fit follows, and their shadows, beam hardening and starved photons
    pull every view's pose by millimetres in a still scan and by 15-40 mm in a swaying one,
    also with the rays through the metal left out and filled (docs/algorithms/motion.md).
    """
    data = np.asarray(first.data)
    try:
        soft = soft_tissue_level(data)
    except ValueError:
        return  # no tissue: the bone check that follows says what is wrong
    levels = metal_levels(data, soft, first.grid.voxel_volume_mm3)
    if np.isfinite(levels).any():
        cm3 = np.isfinite(levels).sum() * first.grid.voxel_volume_mm3 / 1000.0
        raise ValueError(
            f"metal in the field ({cm3:.0f} cm^3 above {METAL_SEED:g} x the soft tissue's "
            f"attenuation in regions of {MIN_METAL_MM3:g} mm^3 or more): the patient's motion is "
            "not estimated next to an implant, whose shadow hides the bone the fit follows: "
            "reconstruct without motion compensation"
        )


def _binning(geometry: Geometry, pixel_mm: float) -> int:
    """The largest pixel binning that keeps the panel's pitch at the isocentre within
    ``pixel_mm`` (>= 1)."""
    orbit = estimate_orbit(geometry)
    view = geometry[0]
    at_iso = view.pitch_u_mm * float(np.median(orbit.sod_mm)) / view.sdd_mm
    return max(1, math.floor(pixel_mm / at_iso + 1e-9))


@contextlib.contextmanager
def _timed(seconds: dict[str, float], name: str) -> Iterator[None]:
    """Add the wall time of the block to ``seconds[name]``."""
    start = time.perf_counter()
    try:
        yield
    finally:
        seconds[name] = round(time.perf_counter() - start, 2)
