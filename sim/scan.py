"""Simulated CBCT scans of the digital knee phantom: projections with quantum and readout noise.

The phantom is rasterised on a fine grid, projected through the protocol's views with the
recon projector, and turned into detector counts with Poisson quantum noise plus Gaussian
electronic noise at the protocol's technique; the stored projections are line integrals
``-ln(counts / I0)`` (docs/conventions.md), and the raw counts are kept beside them.

Photon fluence model (stated, not calibrated to a particular tube): ``K (kVp / 100)^2`` photons
per mm^2 per mAs at 1 m behind the filtration, with K = 2.0e6, scaled by ``(1000 / SDD)^2``.
For the clinical knee technique (110 kVp, 0.765 mAs, 0.6 mm pixels, SDD 1 m) that gives
~6.7e5 photons per unattenuated pixel.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from recon.config import ExposureSpec, ScanProtocol
from recon.geometry import DetectorSpec, Geometry
from recon.project import JosephProjector
from recon.volume import Volume, VolumeGrid
from sim.phantoms.knee import KneePhantomSpec, knee_grid, rasterize_knee
from sim.sway import Sway, SwayingKnee, SwayPivots, SwaySpec

SCAN_S = 18.0
"""A scan's length when nothing else says, s (the robot's 360-degree knee scan)."""

PROJECT_BATCH_VIEWS = 30
"""Views projected at a time (a progress report after each batch)."""

FLUENCE_PER_MM2_MAS_AT_1M = 2.0e6
"""Photons per mm^2 per mAs at 1 m and 100 kVp (rule-of-thumb tube output)."""

ELECTRONIC_NOISE_PHOTONS = 5.0
"""Standard deviation of the panel's readout noise, in photon equivalents per pixel."""


def photons_per_pixel(exposure: ExposureSpec, detector: DetectorSpec, sdd_mm: float) -> float:
    """Mean unattenuated photons reaching one pixel per view.

    Args:
        exposure: tube voltage (kV) and current-time product (mAs) of one view.
        detector: the panel (its pixel pitch, mm).
        sdd_mm: source to detector distance, mm (inverse-square from 1 m).
    """
    fluence = FLUENCE_PER_MM2_MAS_AT_1M * (exposure.tube_kv / 100.0) ** 2 * exposure.mas
    return fluence * detector.pixel_pitch_mm**2 * (1000.0 / sdd_mm) ** 2


def _counts(line_integrals: np.ndarray, photons: float, rng: np.random.Generator) -> np.ndarray:
    """Poisson(photons * exp(-p)) plus Gaussian readout noise, clipped to one photon, float64."""
    expected = photons * np.exp(-line_integrals.astype(np.float64))
    counts = rng.poisson(expected) + rng.normal(0.0, ELECTRONIC_NOISE_PHOTONS, expected.shape)
    return np.maximum(counts, 1.0)


def detected_counts(
    line_integrals: np.ndarray, photons: float, rng: np.random.Generator
) -> np.ndarray:
    """The detector counts of :func:`add_noise` alone (the same for the same ``rng``), float32;
    a panel's read-out, whose logarithm the scanner takes itself."""
    return _counts(line_integrals, photons, rng).astype(np.float32)


def add_noise(
    line_integrals: np.ndarray, photons: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Detector counts and the noisy line integrals measured from them.

    Counts are Poisson(photons * exp(-p)) plus Gaussian readout noise; counts below one
    photon are clipped to one before the logarithm (a saturated-dark pixel).

    Args:
        line_integrals: noiseless line integrals ``p`` (any shape).
        photons: unattenuated photons per pixel (:func:`photons_per_pixel`).
        rng: the noise's generator.

    Returns:
        The counts and ``-ln(counts / photons)``, both float32 of the input's shape.
    """
    counts = _counts(line_integrals, photons, rng)
    noisy = -np.log(counts / photons)
    return counts.astype(np.float32), noisy.astype(np.float32)


@dataclass(frozen=True)
class SimulatedScan:
    """A simulated acquisition and its ground truth.

    Attributes:
        projections: line integrals -ln(I/I0), float32 (views, rows, cols).
        counts: detected photons per pixel, float32 (views, rows, cols); None when noise-free.
        geometry: the views acquired.
        attenuation: the phantom, 1/mm, on the simulation grid.
        labels: the phantom's labels (registration.labels.LABELS) on the same grid.
        photons_per_pixel: mean unattenuated photons per pixel per view (0 when noise-free).
        times_s: each view's time from the scan's start, s.
        true_poses: the swaying patient's bodies, ``T_world_body`` (views, 4, 4) by body; None
            when the patient stood still.
    """

    projections: np.ndarray
    counts: np.ndarray | None
    geometry: Geometry
    attenuation: Volume
    labels: Volume
    photons_per_pixel: float
    times_s: np.ndarray
    true_poses: dict[str, np.ndarray] | None = None


def simulate_knee_scan(
    protocol: ScanProtocol,
    phantom: KneePhantomSpec,
    *,
    voxel_mm: float = 0.5,
    supersample: int = 2,
    noise: bool = True,
    seed: int = 0,
    geometry: Geometry | None = None,
    grid: VolumeGrid | None = None,
    sway: SwaySpec | None = None,
    scan_s: float = SCAN_S,
    status: Callable[[str], None] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> SimulatedScan:
    """Scan the knee phantom with ``protocol``, its views evenly spread over ``scan_s``.

    Args:
        protocol: views, panel and technique.
        phantom: the knee.
        voxel_mm: simulation voxel size; finer than the reconstruction keeps the forward
            model independent of it.
        supersample: sub-voxel samples per edge when rasterising (partial volume).
        noise: add quantum and readout noise at the protocol's technique.
        seed: noise seed (repeatable scans).
        geometry: the views actually acquired (e.g. sim.vibration.vibrate of the plan);
            default the protocol's planned views.
        grid: the simulation grid; default sim.phantoms.knee.knee_grid at ``voxel_mm``.
        sway: the patient's sway during the scan (sim.sway); None or 0 mm: still.
        scan_s: the scan's length, s.
        status: optional callback receiving a line per stage.
        progress: optional ``progress(done, total)`` over the views projected.
    """
    say = status or (lambda _msg: None)
    if geometry is None:
        geometry = protocol.orbit.geometry(protocol.detector)
    if grid is None:
        grid = knee_grid(phantom, spacing_mm=voxel_mm)
    say(f"rasterising the knee phantom on {grid.size_xyz} voxels of {voxel_mm} mm")
    labels, mu = rasterize_knee(phantom, grid, supersample=supersample)
    say(f"projecting {len(geometry)} views of {geometry.rows} x {geometry.cols} pixels")
    line_integrals = np.empty((len(geometry), geometry.rows, geometry.cols), np.float32)
    times = np.linspace(0.0, scan_s, len(geometry))
    true_poses = None
    if sway is not None and sway.peak_mm > 0:
        say(f"the patient sways by up to {sway.peak_mm:g} mm at the knee")
        moving = Sway(sway, SwayPivots.of_knee(phantom), scan_s)
        knee = SwayingKnee(Volume(mu, grid, "1/mm"), Volume(labels, grid, "label"), phantom, moving)
        for i, (view, t) in enumerate(zip(geometry, times, strict=True)):
            line_integrals[i] = knee(view, float(t))
            if progress is not None and (i + 1) % PROJECT_BATCH_VIEWS == 0:
                progress(i + 1, len(geometry))
        true_poses = moving.poses(times)
    else:
        projector = JosephProjector(mu, grid)
        for first in range(0, len(geometry), PROJECT_BATCH_VIEWS):
            part = geometry[first : first + PROJECT_BATCH_VIEWS]
            line_integrals[first : first + len(part)] = projector.project(part)
            if progress is not None:
                progress(first + len(part), len(geometry))
    counts, photons = None, 0.0
    if noise:
        photons = photons_per_pixel(protocol.exposure, protocol.detector, protocol.orbit.sdd_mm)
        say(f"adding quantum noise at {photons:.3g} photons per pixel and readout noise")
        counts, line_integrals = add_noise(line_integrals, photons, np.random.default_rng(seed))
    return SimulatedScan(
        projections=line_integrals,
        counts=counts,
        geometry=geometry,
        attenuation=Volume(mu, grid, "1/mm"),
        labels=Volume(labels, grid, "label"),
        photons_per_pixel=photons,
        times_s=times,
        true_poses=true_poses,
    )
