"""Iterative reconstruction: ordered-subsets SART, alone or with total variation (TV).

Both run through the Joseph forward projector (recon.project) and its voxel-driven adjoint,
for any per-view projection matrices, and start from weighted FDK. One iteration visits every
view once, in ``subsets`` interleaved subsets visited in a golden-ratio order (by default
:data:`SUBSETS` where every view sees the whole grid, else one per :data:`VIEWS_PER_SUBSET`
views); each subset updates the volume by the SART step

    x <- max(0, x + relaxation * (N / n_s) * A_s^T [(p_s - A_s x) / A_s 1] / A^T 1)

(``A_s 1``: each ray's length through the grid, mm; ``A^T 1``: every view's rays backprojected;
``N / n_s`` turns the full count into the subset's). ``tv`` follows each iteration by a TV
denoising step (Chambolle's projection, scikit-image) of strength ``tv_weight``: a proximal
gradient method for least squares plus TV, which keeps edges and flattens the streaks of a
sparse orbit and the noise of a low dose. The iterations stop at ``iterations`` or when an
iteration changes the volume by less than ``tolerance`` (relative, in the root mean square).

The default ``tv_weight`` is derived from the data: a multiple (:data:`TV_PER_NOISE`) of the
noise of the FDK start, estimated robustly from neighbouring voxels' differences inside the
object (:func:`noise_sigma`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
from skimage.restoration import denoise_tv_chambolle

from recon.config import ReconstructionSpec
from recon.fdk import (
    FDKResult,
    Progress,
    corner_pixels,
    estimate_orbit,
    fdk_reconstruct,
    offset_voxels,
    seen_along_z,
)
from recon.geometry import DetectorSpec, Geometry, short_scan_arc_deg
from recon.project import (
    ADJOINT_WEIGHT,
    JosephProjector,
    adjoint_scale,
    backproject_weighted,
    centre_chords,
    check_in_front,
)
from recon.volume import Volume, VolumeGrid

Method = Literal["fdk", "sart", "tv"]
METHODS: tuple[str, ...] = ("fdk", "sart", "tv")
TV_PER_NOISE = 0.25
"""Default TV weight per unit of the FDK start's voxel noise (:func:`noise_sigma`)."""
MIN_SPARSE_VIEWS = 20
"""Fewest views a sparse subset of a scan (:func:`sparse_views`) may keep."""
END_SLICE_SHARE = 0.01
"""Share of an end slice the object must cover for it to continue beyond the grid."""
SENSITIVITY_BATCH = 16
"""Views backprojected together for the voxels' sensitivity (as FDK's batches)."""
SUBSETS = 30
"""Default subsets per iteration where every view's panel holds the whole grid (a circle about
the object): the fastest to converge on bench/iterative.py's scans at 60-360 views
(docs/algorithms/iterative.md)."""
VIEWS_PER_SUBSET = 10
"""Default views per subset where some view's panel does not hold the whole grid (a spiral, or
a grid extended along a leg): a voxel near an end is seen by some subsets only, and the shared
voxel normalisation holds only for subsets of many views (smaller ones oscillate)."""
GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0
"""The subsets are visited in the order of k * GOLDEN modulo 1 (k: the subset's first view), so
each lies far from the last ones visited: neighbouring subsets hold nearly the same rays, and
visited in turn they repeat much of one update."""
MIN_RAY_VOXELS = 1.0
"""Rays shorter than this many voxels through the grid are left out of the SART step (a ray
grazing a corner would divide its residual by almost nothing)."""


@dataclass(frozen=True)
class IterativeSettings:
    """How an iterative reconstruction runs.

    Attributes:
        method: "sart" (OS-SART) or "tv" (OS-SART with a TV step after each iteration).
        iterations: most iterations (each visits every view once), >= 1.
        subsets: ordered subsets per iteration (interleaved over the orbit; at most one per
            view), >= 1; None: :data:`SUBSETS` where every view sees the whole grid (
            :func:`sees_whole_grid`), else one per :data:`VIEWS_PER_SUBSET` views.
        relaxation: SART's step, in (0, 2).
        tv_weight: TV step's strength (1/mm, the volume's unit); None: TV_PER_NOISE times
            the FDK start's noise. Only for "tv".
        tolerance: stop once an iteration changes the volume by less than this (relative
            root mean square), >= 0; 0 runs every iteration.
        tv_steps: iterations of each TV step's own solver (Chambolle), >= 1.
    """

    method: Method = "tv"
    iterations: int = 12
    subsets: int | None = None
    relaxation: float = 0.8
    tv_weight: float | None = None
    tolerance: float = 2e-3
    tv_steps: int = 15

    def __post_init__(self) -> None:
        if self.method not in ("sart", "tv"):
            raise ValueError(f"method {self.method!r}: iterative methods are 'sart' and 'tv'")
        if self.iterations < 1:
            raise ValueError(f"iterations {self.iterations}: at least 1")
        if self.subsets is not None and self.subsets < 1:
            raise ValueError(f"subsets {self.subsets}: at least 1")
        if not 0.0 < self.relaxation < 2.0:
            raise ValueError(f"relaxation {self.relaxation}: must lie in (0, 2)")
        if self.tv_weight is not None and not self.tv_weight >= 0.0:
            raise ValueError(f"tv_weight {self.tv_weight} 1/mm: must be 0 or more")
        if self.tv_weight is not None and self.method != "tv":
            raise ValueError(f"tv_weight is for method 'tv', not {self.method!r}")
        if not self.tolerance >= 0.0:
            raise ValueError(f"tolerance {self.tolerance}: must be 0 or more")
        if self.tv_steps < 1:
            raise ValueError(f"tv_steps {self.tv_steps}: at least 1")


@dataclass(frozen=True)
class IterativeResult:
    """An iterative reconstruction and how it went.

    Attributes:
        fdk: the FDK start; its coverage and mask hold for the iterative volume too.
        volume: the reconstruction (1/mm), zero where the FDK mask is False.
        settings: the settings as run, ``subsets`` resolved and ``tv_weight`` for "tv"
            (None for "sart").
        changes: per iteration, the volume's relative root-mean-square change.
        residuals: per iteration, the root-mean-square residual (p - A x) over the rays
            through the grid before the iteration's updates (line integral, dimensionless).
        stopped: "tolerance" or "iterations".
        seconds: per iteration, wall time (s); the preparation before the first (each ray's
            length, the voxels' sensitivity: one projection and one backprojection) is not
            in it.
    """

    fdk: FDKResult
    volume: Volume
    settings: IterativeSettings
    changes: tuple[float, ...] = field(default=())
    residuals: tuple[float, ...] = field(default=())
    stopped: str = "iterations"
    seconds: tuple[float, ...] = field(default=())

    @property
    def iterations(self) -> int:
        """Iterations run."""
        return len(self.changes)

    def as_fdk(self) -> FDKResult:
        """The FDK result with this volume in place of FDK's (coverage and mask kept)."""
        return replace(self.fdk, volume=self.volume)


def covered_slices(volume: np.ndarray) -> np.ndarray:
    """Per z slice, whether the object covers it: more than :data:`END_SLICE_SHARE` of the
    slice above a tenth of the object's level (the volume's 99th percentile)."""
    data = np.asarray(volume)
    level = float(np.percentile(data, 99.0)) if data.size else 0.0
    if level <= 0.0:
        return np.zeros(len(data), dtype=bool)
    return (data > 0.1 * level).mean(axis=(1, 2)) > END_SLICE_SHARE


def continues_beyond_ends(volume: np.ndarray) -> bool:
    """Whether the object covers the volume's first or last z slice (:func:`covered_slices`),
    as a leg does above and below a knee's field of view."""
    covered = covered_slices(volume)
    return bool(covered[0] or covered[-1])


def _object_slices(volume: np.ndarray, keep: tuple[int, int]) -> tuple[int, int]:
    """The z range (start, stop) of the slices the object covers, joined with ``keep``, one
    slice of margin."""
    covered = np.flatnonzero(covered_slices(volume))
    lo = min(keep[0], int(covered[0]) - 1) if covered.size else keep[0]
    hi = max(keep[1], int(covered[-1]) + 2) if covered.size else keep[1]
    return max(0, lo), min(len(volume), hi)


def _extended(
    projections: np.ndarray,
    geometry: Geometry,
    grid: VolumeGrid,
    x: np.ndarray,
    fdk_options: dict,
) -> tuple[VolumeGrid, np.ndarray, tuple[slice, ...]]:
    """``grid`` extended along z over the slices of the object the views see (from an FDK of
    the extended grid, every voxel kept), the start there with ``x`` in its middle, and where
    ``grid`` sits in it."""
    seen = seen_along_z(grid, geometry)
    options = {**fdk_options, "min_coverage_deg": 0.0}  # the ends, seen by a few views
    outer = np.maximum(fdk_reconstruct(projections, geometry, seen, **options).volume.data, 0.0)
    first = offset_voxels(seen, grid)[0]
    lo, hi = _object_slices(outer, (first, first + grid.shape[0]))
    origin = (seen.origin_mm[0], seen.origin_mm[1], seen.origin_mm[2] + lo * seen.spacing_mm[2])
    extended = VolumeGrid((hi - lo, *seen.shape[1:]), seen.spacing_mm, origin)
    start = outer[lo:hi].astype(np.float32)
    inner = (slice(first - lo, first - lo + grid.shape[0]), slice(None), slice(None))
    start[inner] = x
    return extended, start, inner


def sees_whole_grid(geometry: Geometry, grid: VolumeGrid) -> bool:
    """Every view's panel holds all of ``grid`` (its eight corners project onto the panel;
    pixel centres at whole (u, v), the panel's edges half a pixel beyond)."""
    u, v = corner_pixels(geometry, grid)
    inside = (u >= -0.5) & (u <= geometry.cols - 0.5) & (v >= -0.5) & (v <= geometry.rows - 0.5)
    return bool(np.all(inside))


def _normalisations(
    geometry: Geometry, grid: VolumeGrid, relaxation: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """SART's normalisations: each ray's inverse length through ``grid`` (0 where shorter
    than :data:`MIN_RAY_VOXELS`), which rays count, the views' adjoint factors and each
    voxel's step (``relaxation`` over every view's counted rays backprojected; 0 unseen)."""
    inverse_length = centre_chords(geometry, grid)
    usable = inverse_length >= MIN_RAY_VOXELS * min(grid.spacing_mm)
    np.divide(1.0, inverse_length, out=inverse_length, where=usable)
    inverse_length[~usable] = 0.0
    per_view = adjoint_scale(geometry, grid)
    sensitivity = np.zeros(grid.shape, np.float32)
    for first in range(0, len(geometry), SENSITIVITY_BATCH):  # bounds the pixel quads' memory
        batch = slice(first, first + SENSITIVITY_BATCH)
        rays = usable[batch].astype(np.float32)
        backproject_weighted(
            rays, geometry[batch], grid, ADJOINT_WEIGHT, sensitivity, scale=per_view[batch]
        )
    seen = sensitivity > 1e-6 * float(sensitivity.max())
    step = np.zeros(grid.shape, np.float32)
    step[seen] = relaxation / sensitivity[seen]
    return inverse_length, usable, per_view, step


def protocol_settings(spec: ReconstructionSpec) -> IterativeSettings | None:
    """A protocol's reconstruction as iterative settings; None for FDK."""
    if spec.method == "fdk":
        return None
    return IterativeSettings(
        spec.method, iterations=spec.iterations, tv_weight=spec.tv_weight_per_mm
    )


def noise_sigma(volume: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Robust voxel noise of a volume (its unit): 1.4826 x the median absolute difference of
    neighbouring voxels along x, over sqrt(2), where both lie in ``mask`` and in the object
    (above a tenth of the 99th percentile), so that edges and empty air weigh nothing."""
    data = np.asarray(volume, dtype=np.float32)
    inside = np.ones(data.shape, bool) if mask is None else np.asarray(mask, bool)
    level = float(np.percentile(data[inside], 99.0)) if inside.any() else 0.0
    inside = inside & (data > 0.1 * level)
    pair = inside[..., 1:] & inside[..., :-1]
    if not pair.any():
        return 0.0
    diff = (data[..., 1:] - data[..., :-1])[pair]
    return float(1.4826 * np.median(np.abs(diff - np.median(diff))) / math.sqrt(2.0))


def subsets(n_views: int, count: int) -> list[np.ndarray]:
    """Interleaved ordered subsets of view indices in their visiting order: subset k holds
    views k, k + M, k + 2M, ... (M = min(count, n_views)), so every subset spans the whole
    orbit; they are visited in the order of k * :data:`GOLDEN` modulo 1."""
    count = max(1, min(count, n_views))
    order = np.argsort((np.arange(count) * GOLDEN) % 1.0, kind="stable")
    return [np.arange(k, n_views, count) for k in order]


def sparse_views(geometry: Geometry, every: int) -> np.ndarray:
    """Indices of every ``every``-th view (0, K, 2K, ...), refused unless at least
    :data:`MIN_SPARSE_VIEWS` remain and one pass still sweeps 180 degrees plus the fan."""
    if every < 1:
        raise ValueError(f"--views-every {every}: give 1 or more")
    keep = np.arange(0, len(geometry), every)
    if len(keep) < MIN_SPARSE_VIEWS:
        raise ValueError(
            f"--views-every {every} keeps {len(keep)} of {len(geometry)} views: at least "
            f"{MIN_SPARSE_VIEWS} must remain (give {max(1, len(geometry) // MIN_SPARSE_VIEWS)} "
            "or less)"
        )
    view = geometry[0]
    panel = DetectorSpec(rows=view.rows, cols=view.cols, pixel_pitch_mm=view.pitch_u_mm)
    need = short_scan_arc_deg(view.sdd_mm, panel)
    arc = estimate_orbit(geometry[keep]).span_deg
    if arc < need - 1e-6:
        raise ValueError(
            f"--views-every {every} leaves an arc of {arc:.1f} deg: at least 180 deg plus the "
            f"fan, {need:.1f} deg, must remain"
        )
    return keep


def iterations_said(result: IterativeResult) -> str:
    """One line on how an iterative reconstruction went."""
    settings = result.settings
    weight = "" if settings.method == "sart" else f", TV weight {settings.tv_weight:.3g} 1/mm"
    why = (
        f"the volume changed by less than {settings.tolerance:g}"
        if result.stopped == "tolerance"
        else "the iterations given"
    )
    return (
        f"{settings.method.upper()}: {result.iterations} iteration(s){weight}; stopped at {why} "
        f"(last change {result.changes[-1]:.2g}, residual {result.residuals[-1]:.3g})"
    )


def iterative_reconstruct(
    projections: np.ndarray,
    geometry: Geometry,
    grid: VolumeGrid,
    settings: IterativeSettings | None = None,
    *,
    start: FDKResult | None = None,
    progress: Progress | None = None,
    **fdk_options: object,
) -> IterativeResult:
    """Reconstruct line-integral projections by OS-SART or OS-SART + TV, from FDK.

    Args:
        projections: float32 (views, rows, cols), line integrals -ln(I/I0).
        geometry: one view per projection.
        grid: the output voxel grid (world mm).
        settings: the method and its parameters (default: "tv" with a noise-derived weight).
        start: an FDK reconstruction of the same data on ``grid`` (computed when None, with
            ``fdk_options`` passed to :func:`recon.fdk.fdk_reconstruct`).
        progress: optional callback ``progress(subsets_done, subsets_total)``.
        fdk_options: keyword arguments of :func:`recon.fdk.fdk_reconstruct` for the FDK
            volumes made here (the start when None, the extended grid's).

    Returns:
        :class:`IterativeResult` (volume in 1/mm).
    """
    settings = settings or IterativeSettings()
    proj = np.asarray(projections, dtype=np.float32)
    if proj.shape != (len(geometry), geometry.rows, geometry.cols):
        raise ValueError(
            f"projections have shape {proj.shape}; the geometry has {len(geometry)} views of "
            f"{geometry.rows} x {geometry.cols} pixels"
        )
    if not np.isfinite(proj).all():
        raise ValueError("projections contain NaN or infinite values")
    check_in_front(geometry, grid)
    if start is None:
        start = fdk_reconstruct(proj, geometry, grid, **fdk_options)  # type: ignore[arg-type]
    elif start.volume.grid != grid:
        raise ValueError("the FDK start lies on another grid than the reconstruction's")
    if settings.method == "tv" and settings.tv_weight is None:
        settings = replace(
            settings, tv_weight=TV_PER_NOISE * noise_sigma(start.volume.data, start.mask)
        )
    x = np.where(start.mask, np.maximum(start.volume.data, 0.0), 0.0).astype(np.float32)
    inner = tuple(slice(0, n) for n in grid.shape)
    if continues_beyond_ends(x):  # iterate on all of it the rays cross; the grid is inside
        grid, x, inner = _extended(proj, geometry, grid, x, fdk_options)
    if settings.subsets is None:
        whole = sees_whole_grid(geometry, grid)
        count = SUBSETS if whole else math.ceil(len(geometry) / VIEWS_PER_SUBSET)
        settings = replace(settings, subsets=count)
    groups = subsets(len(geometry), settings.subsets)
    views = [geometry[group] for group in groups]
    inverse_length, usable, per_view, step = _normalisations(geometry, grid, settings.relaxation)
    scales = [per_view[group] * (len(geometry) / len(group)) for group in groups]
    update = np.empty(grid.shape, np.float32)

    changes: list[float] = []
    residuals: list[float] = []
    stopped = "iterations"
    total = settings.iterations * len(groups)
    seconds: list[float] = []
    for iteration in range(settings.iterations):
        began = time.perf_counter()
        before = x.copy()
        squares, rays = 0.0, 0
        for k, (group, sub, scale) in enumerate(zip(groups, views, scales, strict=True)):
            residual = proj[group] - JosephProjector(x, grid).project(sub)
            through = residual[usable[group]]
            squares += float(np.dot(through, through))
            rays += through.size
            residual *= inverse_length[group]
            update.fill(0.0)
            backproject_weighted(residual, sub, grid, ADJOINT_WEIGHT, update, scale=scale)
            x += step * update
            np.maximum(x, 0.0, out=x)
            if progress is not None:
                progress(iteration * len(groups) + k + 1, total)
        if settings.method == "tv" and settings.tv_weight > 0.0:
            x = denoise_tv_chambolle(
                x, weight=settings.tv_weight, max_num_iter=settings.tv_steps
            ).astype(np.float32, copy=False)
            np.maximum(x, 0.0, out=x)
        residuals.append(math.sqrt(squares / max(rays, 1)))
        norm = float(np.linalg.norm(x))
        changes.append(float(np.linalg.norm(x - before)) / norm if norm > 0 else 0.0)
        seconds.append(time.perf_counter() - began)
        if changes[-1] < settings.tolerance:
            stopped = "tolerance"
            if progress is not None:
                progress(total, total)
            break
    x = np.where(start.mask, x[inner], 0.0).astype(np.float32)
    return IterativeResult(
        start,
        Volume(x, start.volume.grid, "1/mm"),
        settings,
        tuple(changes),
        tuple(residuals),
        stopped,
        tuple(seconds),
    )
