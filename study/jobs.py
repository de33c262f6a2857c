"""File-level jobs of the study pipeline: calibrate from a steel-ball scan, reconstruct
files, assess poses, fit the fluoroscopy panel's distortion.

Each job validates everything it reads before the long work starts and refuses to overwrite:
outputs go to new files or to a folder that does not exist yet (or is empty).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
import trimesh

from assessment.components import assess_components
from assessment.handoff import Motion, check_static_volume, write_handoff
from assessment.knee import BONE_LABELS, KneeAssessment, assess_knee
from assessment.report import frame_overlays, write_report
from assessment.series import bone_mesh, export_series, record_series
from assessment.viewer import motion_scene
from calibration.calibrate import Calibration, calibrate, corrected_geometry
from calibration.distortion import DewarpGridSpec, fit_distortion
from calibration.phantom import BBPhantomSpec
from recon.attenuation import DEFAULT_EFFECTIVE_ENERGY_KEV
from recon.config import ScanProtocol, load_config, load_protocol
from recon.distortion import Distortion
from recon.fdk import FDKResult, Progress, check_axis_on_panel, default_grid, fdk_reconstruct
from recon.geometry import Geometry
from recon.io import read_projections, read_volume, write_volume
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
from recon.static_volume import StaticUnit, read_attenuation
from recon.volume import Volume, VolumeGrid
from registration.frames import read_frames
from registration.implants import read_mesh
from registration.motion_figure import save_motion_figure
from registration.poses import BodyPose, read_poses
from registration.scan_motion import MotionEstimate, MotionSettings, estimate_motion
from registration.segment import bone_surfaces, segment_bones
from registration.tracking import fluoroscopy_view
from scanner.scan_files import new_folder

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
            f"(the most any voxel gets: {float(result.coverage_deg.max()):.0f}): lower "
            "--min-coverage-deg"
        )
    write_volume(out, result.volume)
    if metal is not None:
        write_volume(metal_path, metal)
    if preview is not None:
        method = "weighted FDK" if iterative is None else iterative.method.upper()
        save_orthogonal_slices(result.volume, preview, title=f"{method} of {projections_path.name}")
    return result


def write_assessment(
    labels: Volume,
    poses: list[BodyPose],
    out: Path,
    side: str,
    *,
    tka: bool = False,
    plateau_offset_mm: float = 0.0,
    title: str = "Knee kinematics",
    volume: Path | None = None,
    overlays: Path | None = None,
    scan_rows: dict[str, str] | None = None,
) -> KneeAssessment:
    """Assess the motion and write the report, metrics.csv, plots, the 4D series (meshes
    per frame and a rerun recording) and the hand-off for other tools (``export/``: ITK
    transforms, Autoscoper .tra, a 3D Slicer scene with the static ``volume`` when given) into
    the new folder ``out``. ``overlays``: the registration's overlays folder, played in the
    report; ``scan_rows``: what the report's summary says of the static scan (e.g. the
    patient's motion during it)."""
    result = assess_knee(labels, poses, side, tka=tka, plateau_offset_mm=plateau_offset_mm)
    motion, meshes = bone_motion(poses, labels, "poses")
    plane = "polyethylene insert" if tka else "fitted tibial plateau"
    extra = {"TP plane": f"{plane}, offset {plateau_offset_mm:g} mm along its normal"}
    extra |= scan_rows or {}
    _write_outputs(result, poses, motion, meshes, out, title, extra, volume, overlays)
    return result


def write_component_assessment(
    components: dict[str, trimesh.Trimesh],
    plateau: trimesh.Trimesh,
    poses: list[BodyPose],
    out: Path,
    side: str,
    *,
    plateau_offset_mm: float = 0.0,
    title: str = "Knee replacement kinematics",
    overlays: Path | None = None,
    insert: bool = True,
) -> KneeAssessment:
    """:func:`write_assessment` of a knee replacement from its tracked components' poses:
    ``components`` by body ("femur": the femoral component, "tibia_fibula" or "tibia": the
    tray), ``plateau`` the insert (``insert``) or the tray in the tray's frame
    (assessment.components)."""
    result = assess_components(
        components["femur"],
        plateau,
        poses,
        side,
        plateau_offset_mm=plateau_offset_mm,
        insert=insert,
    )
    tracked = [p for p in poses if p.body in components]
    motion = Motion.of(tracked)
    missing = sorted(set(components) - set(motion.poses))
    if missing:
        raise ValueError(f"poses: no poses of the component(s) {missing}")
    extra = {"TP plane": f"the insert's top, offset {plateau_offset_mm:g} mm along its normal"}
    _write_outputs(result, tracked, motion, components, out, title, extra, None, overlays)
    return result


def _write_outputs(
    result: KneeAssessment,
    poses: list[BodyPose],
    motion: Motion,
    meshes: dict[str, trimesh.Trimesh],
    out: Path,
    title: str,
    extra: dict[str, str],
    volume: Path | None,
    overlays: Path | None,
) -> None:
    """The assessment's files in the new folder ``out`` (see :func:`write_assessment`)."""
    new_folder(out)
    frames = [] if overlays is None else frame_overlays(overlays, result.kinematics, poses)
    scene = motion_scene(result, motion.frames, motion.poses, meshes)
    write_report(
        result.kinematics, out, title=title, extra_rows=extra, overlays=frames, scene=scene
    )
    export_series(meshes, motion.frames, motion.poses, out / "series")
    record_series(meshes, motion.frames, motion.poses, out / "series.rrd")
    write_handoff(out / "export", motion, meshes, volume)


def bone_motion(
    poses: list[BodyPose], labels: Volume, where: Path | str
) -> tuple[Motion, dict[str, trimesh.Trimesh]]:
    """Every posed bone's motion, and its surface (world mm) from the label volume;
    ValueError naming ``where`` for a bone name the labels do not know."""
    motion = Motion.of(poses)
    unknown = sorted(set(motion.poses) - set(BONE_LABELS))
    if unknown:
        raise ValueError(f"{where}: unknown bone name(s) {unknown}; known: {sorted(BONE_LABELS)}")
    return motion, {bone: bone_mesh(labels, BONE_LABELS[bone]) for bone in motion.poses}


def segment_files(
    volume_path: Path,
    out: Path,
    *,
    unit: StaticUnit | None = None,
    side: str | None = None,
    effective_energy_kev: float = DEFAULT_EFFECTIVE_ENERGY_KEV,
    meshes: Path | None = None,
) -> Volume:
    """``cbct segment``: label the bones of a static knee scan as the demo does.

    Args:
        volume_path: The scan: a volume file or a DICOM CT series folder, in HU or 1/mm.
        out: The new label volume (registration.labels: air 0, soft tissue 1, femur 2,
            tibia 3, fibula 4, patella 5).
        unit: The scan's unit where its file does not say.
        side: "right" or "left"; inferred from the fibula when None.
        effective_energy_kev: Effective energy (keV) HU are converted to 1/mm at.
        meshes: A new folder for one surface (STL, world mm) per bone, or None.

    Returns:
        The labels.
    """
    for path in (out, meshes):
        if path is not None and path.exists():
            raise FileExistsError(f"{path} exists: nothing is overwritten")
    volume, _ = read_attenuation(volume_path, unit, effective_energy_kev)
    labels = segment_bones(volume, side=side)
    write_volume(out, labels)
    if meshes is not None:
        meshes.mkdir(parents=True)
        for name, mesh in bone_surfaces(labels).items():
            mesh.export(meshes / f"{name}.stl")
    return labels


def assess_files(
    poses_path: Path,
    labels_path: Path | None,
    out: Path,
    side: str,
    *,
    tka: bool = False,
    plateau_offset_mm: float = 0.0,
    volume: Path | None = None,
    overlays: Path | None = None,
    implants: dict[str, Path] | None = None,
    insert: Path | None = None,
    implant_unit: str = "mm",
) -> KneeAssessment:
    """``cbct assess``: read poses.csv and the label volume, then :func:`write_assessment`
    (``overlays``: the registration's overlays folder, for the report's player); or, with
    ``implants`` (body -> mesh: the femoral component as "femur", the tray as "tibia_fibula"
    or "tibia") and ``insert`` (in the tray's frame; else the tray's top is the plateau),
    :func:`write_component_assessment`."""
    if out.exists():
        raise FileExistsError(f"{out} exists: choose a new output folder")
    if volume is not None:
        check_static_volume(volume)
    poses = read_poses(poses_path)
    if implants:
        meshes = {body: read_mesh(path, implant_unit)[0] for body, path in implants.items()}
        tibia = next((b for b in ("tibia_fibula", "tibia") if b in meshes), None)
        if "femur" not in meshes or tibia is None:
            raise ValueError(
                f"--implant: {sorted(meshes)}; give femur=FEMORAL_COMPONENT and "
                "tibia=TRAY (the bodies the registration tracked them as)"
            )
        plateau = meshes[tibia] if insert is None else read_mesh(insert, implant_unit)[0]
        return write_component_assessment(
            meshes,
            plateau,
            poses,
            out,
            side,
            plateau_offset_mm=plateau_offset_mm,
            title=f"Knee replacement kinematics: {poses_path.name}",
            overlays=overlays,
            insert=insert is not None,
        )
    if labels_path is None:
        raise ValueError("give --labels (the static scan's labels), or the components' meshes")
    labels = read_volume(labels_path, unit="label")
    return write_assessment(
        labels,
        poses,
        out,
        side,
        tka=tka,
        plateau_offset_mm=plateau_offset_mm,
        title=f"Knee kinematics: {poses_path.name}",
        volume=volume,
        overlays=overlays,
    )


def export_files(
    poses_path: Path, labels_path: Path, out: Path, volume: Path | None = None
) -> list[Path]:
    """``cbct export``: the tracked motion of poses.csv for 3D Slicer, ITK and Autoscoper
    (assessment.handoff) in the new folder ``out``; bone models from the label volume."""
    if out.exists():
        raise FileExistsError(f"{out} exists: choose a new output folder")
    if volume is not None:
        check_static_volume(volume)
    poses = read_poses(poses_path)
    labels = read_volume(labels_path, unit="label")
    return write_handoff(out, *bone_motion(poses, labels, poses_path), volume)


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
    """The fluoroscopy panel's warp (calibration.distortion) from one exposure of the dewarp
    grid (``grid_image``: .mha or DICOM) through the static view in ``geometry`` (RTK XML, e.g.
    the frames' own)."""
    spec = load_config(grid_config, DewarpGridSpec)
    image = read_frames(grid_image, pixel_pitch_mm)
    if len(image.data) != 1:
        raise ValueError(f"{grid_image}: {len(image.data)} images; the grid needs exactly one")
    view = fluoroscopy_view(geometry, image, any_count=True)
    return fit_distortion(image.data[0], view, spec, degree)
