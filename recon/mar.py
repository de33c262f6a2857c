"""Metal artefact reduction: normalised MAR (NMAR; Meyer et al., Med. Phys. 37, 2010).

1. Reconstruct the projections as they are (weighted FDK).
2. Segment the metal: voxels above :data:`METAL_SEED` x the soft tissue's level, grown through
   those above :data:`METAL_GROW` x it, in regions of at least :data:`MIN_METAL_MM3`.
3. A prior free of metal: a volume without the metal's shadow (first the trace interpolated
   linearly, then the corrected one of the pass before: :data:`PRIOR_PASSES`) smoothed, air
   set to 0, soft tissue to its level, bone kept, the metal set to soft tissue.
4. Project the metal (its trace on the panel) and the prior. Divide the projections by the
   prior's, interpolate the quotient linearly along each detector row across the trace,
   multiply back: the shadow of the metal is filled with the anatomy the prior predicts there,
   at the level its edges measure.
5. Reconstruct the corrected projections and put the metal back in: the voxels of step 2
   above :data:`METAL_SHOWN` of their region's median (its blurred rim is left corrected).

A shadow too wide to interpolate (the metal's trace covering more than
:data:`MAX_TRACE_SHARE` of the object's shadow in some view) is refused, naming the view and
the share measured.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numba
import numpy as np
from scipy import ndimage

from recon.fdk import FDKResult, fdk_reconstruct, offset_voxels, seen_along_z
from recon.geometry import Geometry
from recon.project import JosephProjector
from recon.volume import Volume, VolumeGrid

METAL_SEED = 8.0
"""Metal certainly: above this many times the soft tissue's attenuation (bone is under 3)."""
METAL_GROW = 4.0
"""Metal's extent: above this many times the soft tissue's, connected to a seed."""
METAL_TRACED = 0.5
"""The metal whose shadow is replaced: its voxels above this share of their region's median
(its surface at half its level; a voxel a fifth full of metal is still far above bone)."""
METAL_SHOWN = 0.75
"""The metal put back in the corrected volume: its voxels above this share of their region's
median (the blur about the metal, between half and this, is corrected tissue: put back, its
metal values lay over the bone next to it)."""
MIN_METAL_MM3 = 50.0
"""A metal region smaller than this is a streak's peak, not an implant, mm^3."""
AIR_SHARE = 0.5
"""In the prior, a voxel below this share of the soft tissue's level is air."""
BONE_SHARE = 1.35
"""In the prior, a voxel above this share of the soft tissue's level keeps its value (bone)."""
PRIOR_SIGMA_VOXELS = 1.0
"""The prior is the first volume smoothed by a Gaussian of this sigma (its streaks' grain)."""
TRACE_DILATION_VOXELS = 1
"""The metal is grown by this many voxels before its trace is projected: its blurred edge in
the first volume falls below the threshold, its shadow does not."""
TRACE_LENGTH_MM = 0.05
"""A pixel is in the metal's trace where its ray crosses at least this much metal, mm."""
SHADOW_LINE_INTEGRAL = 0.1
"""A pixel is in the object's shadow where its line integral is above this."""
MAX_TRACE_SHARE = 0.6
"""The largest share of a view's object shadow the metal's trace may cover."""
PRIOR_PASSES = 2
"""Priors made in turn: the first from the linear interpolation's volume, each next from the
volume the one before corrected (its bone next to the metal is sharper)."""
OFFSET = 0.05
"""Added to both projections before they are divided (a ray through air has none)."""


@dataclass(frozen=True)
class MarResult:
    """A metal-reduced reconstruction.

    Attributes:
        volume: The corrected volume with the metal put back, 1/mm.
        uncorrected: The first reconstruction (step 1), 1/mm.
        metal: The metal's voxels put back (:data:`METAL_SHOWN`), bool [z, y, x].
        soft_tissue_per_mm: The soft tissue's level the thresholds scale with, 1/mm.
        trace_share: Per view, the share of the object's shadow in the metal's trace (V,).
        fdk: The corrected reconstruction's FDK result (coverage, mask).
    """

    volume: Volume
    uncorrected: Volume
    metal: np.ndarray
    soft_tissue_per_mm: float
    trace_share: np.ndarray
    fdk: FDKResult

    @property
    def metal_mm3(self) -> float:
        """The metal's volume, mm^3."""
        return float(self.metal.sum()) * self.volume.grid.voxel_volume_mm3


def soft_tissue_level(data: np.ndarray) -> float:
    """The soft tissue's attenuation in a knee volume: the mode of the voxels above a tenth
    of their 90th percentile (air left out), 1/mm."""
    sample = data[::2, ::2, ::2]
    tissue = sample[sample > 0.1 * np.percentile(sample, 90)]
    if tissue.size == 0 or not np.percentile(tissue, 90) > 0.0:
        raise ValueError("MAR: the volume has no tissue (nothing above air)")
    counts, edges = np.histogram(tissue, bins=256, range=(0.0, float(np.percentile(tissue, 90))))
    peak = int(np.argmax(ndimage.gaussian_filter1d(counts.astype(np.float64), 2.0)))
    return 0.5 * float(edges[peak] + edges[peak + 1])


def metal_levels(volume: np.ndarray, soft: float, voxel_mm3: float) -> np.ndarray:
    """Each voxel's metal region's median, inf outside metal (float [z, y, x]): regions of
    seeds above :data:`METAL_SEED` x ``soft`` grown through voxels above :data:`METAL_GROW` x
    it, of :data:`MIN_METAL_MM3` or more. The metal at a share of its level is
    ``volume >= share * levels`` (:data:`METAL_TRACED`, :data:`METAL_SHOWN`)."""
    grown = ndimage.binary_propagation(volume > METAL_SEED * soft, mask=volume > METAL_GROW * soft)
    regions, n = ndimage.label(grown)
    if n == 0:
        return np.full(volume.shape, np.inf)
    index = np.arange(1, n + 1)
    sizes = ndimage.sum_labels(grown, regions, index) * voxel_mm3
    level = np.where(sizes >= MIN_METAL_MM3, ndimage.median(volume, regions, index), np.inf)
    return np.concatenate(([np.inf], level))[regions]


def metal_free_prior(volume: np.ndarray, metal: np.ndarray, soft: float) -> np.ndarray:
    """Step 3's prior (float32 [z, y, x], 1/mm)."""
    prior = ndimage.gaussian_filter(np.where(metal, soft, volume), PRIOR_SIGMA_VOXELS)
    prior = np.where(prior < AIR_SHARE * soft, 0.0, prior)
    prior = np.where((prior >= AIR_SHARE * soft) & (prior < BONE_SHARE * soft), soft, prior)
    prior[metal] = soft
    return prior.astype(np.float32)


@numba.njit(parallel=True, cache=True)
def _fill_rows(values, trace):  # pragma: no cover
    """Linear interpolation along each row (last axis) of ``values`` across its ``trace``
    runs, from the nearest pixel outside each side (the edge value where a run reaches the
    row's end), in place."""
    rows = values.shape[0]
    n = values.shape[1]
    for r in numba.prange(rows):
        c = 0
        while c < n:
            if not trace[r, c]:
                c += 1
                continue
            start = c
            while c < n and trace[r, c]:
                c += 1
            left = start - 1
            right = c
            if left < 0 and right >= n:
                continue
            a = values[r, left] if left >= 0 else values[r, right]
            b = values[r, right] if right < n else values[r, left]
            for k in range(start, c):
                t = (k - left) / (right - left)
                values[r, k] = a + t * (b - a)


def interpolate_trace(projections: np.ndarray, prior: np.ndarray, trace: np.ndarray) -> np.ndarray:
    """Step 4: the projections with the trace filled by the normalised interpolation
    (float32 (views, rows, cols))."""
    quotient = (projections + OFFSET) / (prior + OFFSET)
    flat = np.ascontiguousarray(quotient.reshape(-1, quotient.shape[-1]), dtype=np.float64)
    _fill_rows(flat, np.ascontiguousarray(trace.reshape(flat.shape)))
    filled = flat.reshape(projections.shape) * (prior + OFFSET) - OFFSET
    return np.where(trace, filled, projections).astype(np.float32)


def nmar(
    projections: np.ndarray,
    geometry: Geometry,
    grid: VolumeGrid,
    *,
    fdk: Callable[[np.ndarray, VolumeGrid], FDKResult] | None = None,
    say: Callable[[str], None] = lambda _m: None,
) -> MarResult:
    """Reconstruct with normalised metal artefact reduction (the module's steps).

    Args:
        projections: Line integrals, float32 (views, rows, cols).
        geometry: One view per projection.
        grid: The volume's grid. The metal is segmented and projected on it extended along
            its z axis over all the views see (metal beyond the grid shadows them too).
        fdk: Reconstructs projections on a grid; default weighted FDK with its defaults.
        say: Takes a line per step.

    Returns:
        The corrected volume, the first one and the metal.

    Raises:
        ValueError: no metal found, or a trace too wide to interpolate (naming the view and
            the share).
    """
    seen = seen_along_z(grid, geometry)
    inner = tuple(
        slice(k, k + n) for k, n in zip(offset_voxels(seen, grid), grid.shape, strict=True)
    )
    fdk = fdk or (lambda p, g: fdk_reconstruct(p, geometry, g))
    first = fdk(projections, seen)
    data = np.asarray(first.volume.data, dtype=np.float32)
    soft = soft_tissue_level(data)
    levels = metal_levels(data, soft, seen.voxel_volume_mm3)
    metal = data >= METAL_TRACED * levels
    if not metal.any():
        raise ValueError(
            f"MAR: no metal in the volume (nothing above {METAL_SEED:g} x the soft tissue's "
            f"{soft:.4g} 1/mm in a region of {MIN_METAL_MM3:g} mm^3 or more)"
        )
    say(
        f"metal: {metal.sum() * seen.voxel_volume_mm3 / 1000:.1f} cm^3 "
        f"(soft tissue {soft:.4g} 1/mm)"
    )
    shadowing = ndimage.binary_dilation(metal, iterations=TRACE_DILATION_VOXELS)
    trace = JosephProjector(shadowing.astype(np.float32), seen).project(geometry) > TRACE_LENGTH_MM
    shadow = projections > SHADOW_LINE_INTEGRAL
    share = (trace & shadow).sum(axis=(1, 2)) / np.maximum(shadow.sum(axis=(1, 2)), 1)
    worst = int(np.argmax(share))
    if share[worst] > MAX_TRACE_SHARE:
        raise ValueError(
            f"MAR: the metal's shadow covers {100 * share[worst]:.0f} % of the object's in view "
            f"{worst} (at most {100 * MAX_TRACE_SHARE:.0f} % can be interpolated): too much metal"
        )
    say(f"metal trace: {100 * share.mean():.1f} % of the object's shadow on average")
    projections = np.asarray(projections, np.float32)
    estimate = fdk(interpolate_trace(projections, np.zeros_like(projections), trace), seen)
    for done in range(1, PRIOR_PASSES + 1):
        prior_volume = metal_free_prior(np.asarray(estimate.volume.data, np.float32), metal, soft)
        prior = JosephProjector(prior_volume, seen).project(geometry)
        if done < PRIOR_PASSES:
            estimate = fdk(interpolate_trace(projections, prior, trace), seen)
    corrected = fdk(interpolate_trace(projections, prior, trace), grid)
    volume = np.asarray(corrected.volume.data, dtype=np.float32).copy()
    shown = (data >= METAL_SHOWN * levels)[inner]
    data = data[inner]
    volume[shown] = data[shown]
    return MarResult(
        Volume(volume, grid, "1/mm"),
        Volume(data, grid, "1/mm"),
        shown,
        soft,
        share,
        corrected,
    )
