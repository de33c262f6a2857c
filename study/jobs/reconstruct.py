"""Reconstruct files: a scan's projections and geometry into a volume (FDK or iterative),
through the patient's motion when it moved; a scan checked against its protocol's plan."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np

from calibration.calibrate import corrected_geometry
from recon.config import ScanProtocol, load_protocol
from recon.fdk import FDKResult, Progress, check_axis_on_panel, default_grid, fdk_reconstruct
from recon.geometry import Geometry
from recon.io import read_projections, write_volume
from recon.iterative import (
    IterativeSettings,
    iterations_said,
    iterative_reconstruct,
    sparse_views,
)
from recon.mar import nmar
from recon.motion import read_view_times, write_motion_csv
from recon.preview import save_orthogonal_slices
from recon.rtk_xml import read_rtk_geometry
from recon.volume import Volume, VolumeGrid
from registration.motion_figure import save_motion_figure
from registration.scan_motion import MotionEstimate, MotionSettings, estimate_motion

PLAN_TOLERANCE_MM = 1e-3
"""How far a scan's planned views may lie from its protocol's nominal orbit, mm (the plan's
inverse kinematics leaves ~1e-5 mm)."""


def check_is_plan(geometry: Geometry, protocol: ScanProtocol, path: Path) -> None:
    """ValueError unless ``geometry`` is ``protocol``'s orbit within :data:`PLAN_TOLERANCE_MM`,
    saying by how much and which view differ.

    Args:
        geometry: The views read from ``path``.
        protocol: The protocol they should be the plan of.
        path: The geometry file, for the message.
    """
    nominal = protocol.orbit.geometry(protocol.detector)
    hint = (
        "give the protocol that acquired the scan and its planned geometry (a study's "
        "scan/planned_geometry.xml)"
    )
    if (len(geometry), geometry.rows, geometry.cols) != (len(nominal), nominal.rows, nominal.cols):
        raise ValueError(
            f"{path}: {len(geometry)} views of {geometry.cols} x {geometry.rows} pixels, but "
            f"protocol {protocol.name!r} plans {len(nominal)} of {nominal.cols} x "
            f"{nominal.rows}: {hint}"
        )
    for k, (view, planned) in enumerate(zip(geometry, nominal, strict=True)):
        if not view.isclose(planned, PLAN_TOLERANCE_MM):
            apart = max(
                float(np.abs(getattr(view, a) - getattr(planned, a)).max())
                for a in ("source_mm", "detector_origin_mm")
            )
            raise ValueError(
                f"{path} is not the plan of protocol {protocol.name!r}: view {k} lies "
                f"{apart:.3g} mm from it (source or panel; tolerance {PLAN_TOLERANCE_MM:g} mm): "
                f"{hint}"
            )


class MotionBeyondCompensation(ValueError):
    """The patient moved more than motion compensation is trusted for: repeat the scan."""


def compensable_motion(
    projections: np.ndarray,
    geometry: Geometry,
    grid: VolumeGrid,
    *,
    times: np.ndarray | None,
    orbit: Geometry | None,
    say: Callable[[str], None],
    progress: Callable[[str, int, int], None] | None,
    settings: MotionSettings | None = None,
) -> MotionEstimate:
    """The patient's motion estimated from the projections (registration.scan_motion), its
    notes and verdict said; :class:`MotionBeyondCompensation` (the verdict's words to repeat
    the scan) when it is beyond compensation, ValueError for a scan it cannot run on."""
    estimate = estimate_motion(
        projections,
        geometry,
        grid,
        times_s=times,
        orbit_geometry=orbit,
        settings=settings or MotionSettings(),
        say=say,
        progress=progress,
    )
    for note in estimate.notes:
        say(note)
    if not estimate.compensable:
        raise MotionBeyondCompensation(f"the patient {estimate.verdict()}")
    say(f"the patient {estimate.verdict()}")
    return estimate


def write_motion(
    estimate: MotionEstimate, before: Volume, after: Volume, csv_path: Path, figure: Path
) -> None:
    """The motion's file (recon.motion) and its QA figure (registration.motion_figure)."""
    write_motion_csv(csv_path, estimate.motion)
    save_motion_figure(estimate, before, after, figure)


def _compensated(
    projections: np.ndarray,
    geometry: Geometry,
    grid: VolumeGrid,
    orbit: Geometry | None,
    times: np.ndarray | None,
    motion_out: tuple[Path, Path],
    fdk: Callable[[np.ndarray, VolumeGrid], FDKResult],
    say: Callable[[str], None],
    progress: Callable[[str, int, int], None] | None,
) -> FDKResult:
    """FDK through the motion estimated from the projections; the motion CSV and the QA
    figure written to ``motion_out``; ValueError (nothing written) beyond compensation."""
    estimate = compensable_motion(
        projections, geometry, grid, times=times, orbit=orbit, say=say, progress=progress
    )
    before = fdk(projections, grid)
    result = fdk_reconstruct(
        projections, geometry, grid, orbit_geometry=orbit, motion=estimate.motion
    )
    write_motion(estimate, before.volume, result.volume, *motion_out)
    return result


def reconstruct_files(
    projections_path: Path,
    geometry_path: Path,
    out: Path,
    *,
    size_xyz: tuple[int, int, int] | None = None,
    spacing_mm: float | None = None,
    origin_mm: tuple[float, float, float] | None = None,
    window: str = "hann",
    min_coverage_deg: float = 170.0,
    progress: Progress | None = None,
    preview: Path | None = None,
    calibration: Path | None = None,
    protocol_path: Path | None = None,
    orbit_path: Path | None = None,
    mar: bool = False,
    say: Callable[[str], None] = lambda _m: None,
    motion_out: tuple[Path, Path] | None = None,
    times_path: Path | None = None,
    fit_progress: Callable[[str, int, int], None] | None = None,
    iterative: IterativeSettings | None = None,
    views_every: int = 1,
    iteration_progress: Progress | None = None,
) -> FDKResult:
    """Reconstruct an RTK projection stack + geometry XML into a volume file (and a PNG).

    The grid defaults to the orbit's field of view (recon.fdk.default_grid); ``origin_mm``
    needs ``size_xyz``. ``orbit_path`` (RTK XML, e.g. a scan's planned views) sets FDK's
    angular weights instead of the geometry's own orbit. ``mar``: normalised metal artefact
    reduction (recon.mar; its metal mask is written beside the volume as ``*_metal``).
    ``motion_out`` (a CSV and a PNG path): estimate the patient's motion from the projections
    and reconstruct through it (registration.scan_motion), writing the motion and its QA
    figure there; ``times_path``: a CSV with the per-view times (a ``clock_s`` or ``time_s``
    column, e.g. a study's scan/exposure_log.csv). ``iterative``: OS-SART or OS-SART + TV
    from the FDK volume (recon.iterative; ``iteration_progress`` counts its subsets);
    ``views_every``: reconstruct every K-th view only (a sparse scan). Nothing is written if
    any input is wrong, nor when the motion is beyond what compensation is trusted for.
    """
    for path in (out, preview):
        if path is not None and path.exists():
            raise FileExistsError(f"{path} exists: nothing is overwritten")
    stack = read_projections(projections_path)
    geometry = read_rtk_geometry(geometry_path, stack.header)
    if calibration is not None:
        if protocol_path is None:
            raise ValueError("--calibration needs --protocol (the scan's protocol)")
        protocol = load_protocol(protocol_path)
        check_is_plan(geometry, protocol, geometry_path)
        geometry = corrected_geometry(calibration, protocol)
    if len(geometry) != stack.data.shape[0]:
        raise ValueError(
            f"{projections_path} holds {stack.data.shape[0]} projections but {geometry_path} "
            f"describes {len(geometry)} views"
        )
    check_axis_on_panel(geometry, f"{projections_path} with {geometry_path}")
    orbit = None
    if orbit_path is not None:
        if calibration is not None:
            raise ValueError(
                "--orbit and --calibration exclude each other: a calibration is its own orbit"
            )
        orbit = read_rtk_geometry(orbit_path, stack.header)
        if len(orbit) != len(geometry):
            raise ValueError(
                f"{orbit_path} describes {len(orbit)} views, {geometry_path} {len(geometry)}"
            )
    projections = stack.data
    if views_every != 1:
        keep = sparse_views(geometry, views_every)
        projections, geometry = projections[keep], geometry[keep]
        orbit = None if orbit is None else orbit[keep]
    if iterative is not None and (mar or motion_out is not None):
        raise ValueError(
            f"--method {iterative.method} and --{'mar' if mar else 'compensate-motion'} "
            "exclude each other (not built yet): FDK only"
        )
    if origin_mm is not None and size_xyz is None:
        raise ValueError("--origin-mm needs --size (the grid's voxel counts)")
    grid = default_grid(geometry, spacing_mm, size_xyz)
    if origin_mm is not None:
        grid = VolumeGrid(grid.shape, grid.spacing_mm, origin_mm)
    base, dot, suffixes = out.name.partition(".")
    metal_path = out.with_name(f"{base}_metal{dot}{suffixes}")
    if mar and metal_path.exists():
        raise FileExistsError(f"{metal_path} exists: nothing is overwritten")
    if motion_out is not None and mar:
        raise ValueError("--compensate-motion and --mar exclude each other (not built yet)")
    times = None if times_path is None else read_view_times(times_path)

    def fdk(projections: np.ndarray, on: VolumeGrid) -> FDKResult:
        return fdk_reconstruct(
            projections,
            geometry,
            on,
            window=window,
            min_coverage_deg=min_coverage_deg,
            orbit_geometry=orbit,
            progress=progress,
        )

    metal = None
    if motion_out is not None:
        result = _compensated(
            projections, geometry, grid, orbit, times, motion_out, fdk, say, fit_progress
        )
    elif mar:
        reduced = nmar(projections, geometry, grid, fdk=fdk, say=say)
        result = replace(reduced.fdk, volume=reduced.volume)
        metal = Volume(reduced.metal.astype(np.uint8), grid, "label")
    else:
        result = fdk(projections, grid)
        if iterative is not None:
            run = iterative_reconstruct(
                projections, geometry, grid, iterative, start=result, progress=iteration_progress
            )
            say(iterations_said(run))
            result = run.as_fdk()
    if not result.mask.any():
        raise ValueError(
            f"every voxel is seen over less than {min_coverage_deg:g} degrees of the orbit "
            f"(the most any voxel gets: {float(result.count_deg.max()):.0f}): lower "
            "--min-coverage-deg"
        )
    write_volume(out, result.volume)
    if metal is not None:
        write_volume(metal_path, metal)
    if preview is not None:
        method = "weighted FDK" if iterative is None else iterative.method.upper()
        save_orthogonal_slices(result.volume, preview, title=f"{method} of {projections_path.name}")
    return result
