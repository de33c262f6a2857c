"""Calibrate files: a steel-ball scan into the study's per-view geometry, and the
fluoroscopy panel's distortion from an exposure of the dewarp grid."""

from __future__ import annotations

from pathlib import Path

from calibration.calibrate import Calibration, calibrate
from calibration.dewarp_grid import DewarpGridSpec, fit_distortion
from calibration.phantom import BBPhantomSpec
from recon.config import load_config, load_protocol
from recon.distortion import Distortion
from recon.fdk import Progress
from recon.io import read_projections
from recon.rtk_xml import read_rtk_geometry
from registration.frames import read_frames
from registration.tracking import fluoroscopy_view
from study.jobs.reconstruct import check_is_plan


def calibrate_to_study(
    projections_path: Path,
    geometry_path: Path,
    protocol_path: Path,
    phantom_path: Path,
    study: Path,
    progress: Progress | None = None,
) -> Calibration:
    """``cbct calibrate``: a BB-phantom scan + its planned views -> ``study/calibration``."""
    folder = study / "calibration"
    if folder.exists():
        raise FileExistsError(f"{folder} exists: a calibration is never written over")
    protocol = load_protocol(protocol_path)
    phantom = load_config(phantom_path, BBPhantomSpec)
    stack = read_projections(projections_path)
    planned = read_rtk_geometry(geometry_path, stack.header)
    check_is_plan(planned, protocol, geometry_path)
    calibration = calibrate(stack.data, planned, phantom, protocol, progress=progress)
    calibration.save(folder)
    return calibration


def fit_fluoro_distortion(
    grid_image: Path,
    geometry: Path,
    grid_config: Path,
    degree: int = 5,
    pixel_pitch_mm: float | None = None,
) -> Distortion:
    """The fluoroscopy panel's warp (calibration.dewarp_grid) from one exposure of the dewarp
    grid (``grid_image``: .mha or DICOM) through the static view in ``geometry`` (RTK XML, e.g.
    the frames' own)."""
    spec = load_config(grid_config, DewarpGridSpec)
    image = read_frames(grid_image, pixel_pitch_mm)
    if len(image.data) != 1:
        raise ValueError(f"{grid_image}: {len(image.data)} images; the grid needs exactly one")
    view = fluoroscopy_view(geometry, image, any_count=True)
    return fit_distortion(image.data[0], view, spec, degree)
