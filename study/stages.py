"""The derived stages of a study (docs/design.md): reconstruction, segmentation, registration,
assessment. ``cbct demo`` and ``cbct batch`` run the same functions.

Each stage reads what it needs from the study folder and its config snapshot, writes into
``<stage>.partial/`` and renames it when done, records every file's sha256 and marks itself
complete in ``study.json`` (:func:`run_stage`); a failure marks it incomplete with the reason
and leaves the stages before it untouched, so running again redoes only what is missing.
Segmentation, registration and assessment import their code when they run (a scan's process
reconstructs, and needs none of it).
"""

from __future__ import annotations

import json
import os
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from calibration.calibrate import corrected_geometry
from recon.config import ScanProtocol
from recon.dicom import write_dicom_series
from recon.fdk import FDKResult, Progress, fdk_reconstruct
from recon.geometry import Geometry
from recon.io import read_projections, read_volume, write_volume
from recon.iterative import iterations_said, iterative_reconstruct, protocol_settings
from recon.motion import BodyMotion, read_motion_csv, read_view_times
from recon.preview import save_orthogonal_slices
from recon.rtk_xml import read_rtk_geometry
from recon.volume import VolumeGrid
from registration.labels import BONE_UNITS, LABELS
from scanner.study_folder import Study, StudyError
from sim.phantoms.knee import KneePhantomSpec, attenuation_per_mm, rasterize_knee
from study.study_recording import record_volume

if TYPE_CHECKING:
    from assessment.results import KneeKinematics
    from registration.scan_motion import MotionEstimate
    from registration.settings import Settings
    from study.jobs import RegisterOptions

Say = Callable[[str], None]

RECON_EXTENT_MM = (140.0, 140.0, 320.0)
"""Reconstructed field: x, y, z extent, mm: the leg's whole cross-section, and as much thigh as
a knee flexed to 90 degrees brings into a lateral fluoroscopy field. The registration's soft
tissue ends where this box does; a box that cuts the leg leaves edges in its DRRs that the
frames do not have (measured on the quick demo: a 100 x 100 x 240 mm box drew the femur to its
mirror pose at the flexed frames)."""
RECON_OFFSET_MM = (0.0, 0.0, 40.0)
"""Its centre relative to the orbit's isocentre, mm."""
REAL_SCAN_ENERGY_KEV = 70.0
"""Effective energy assumed for the HU scale of a real scan's DICOM series, keV."""


def run_stage(study: Study, name: str, work: Callable[[], dict | None], say: Say) -> bool:
    """Run ``work`` unless the stage is complete; mark it. Returns whether it ran."""
    if study.stage(name).get("status") == "complete":
        say(f"{name}: complete, skipped")
        return False
    started = time.perf_counter()
    try:
        details = work() or {}
    except BaseException as err:
        if study.stage(name).get("status") != "incomplete":  # scans mark their own
            study.mark(name, "incomplete", reason=f"{type(err).__name__}: {err}")
        raise
    if study.stage(name).get("status") != "complete":
        seconds = round(time.perf_counter() - started, 2)
        study.mark(name, "complete", **{**details, "seconds": seconds})
    return True


def derived_folder(study: Study, name: str, fill: Callable[[Path], dict | None]) -> dict | None:
    """Write a stage into ``<name>.partial/``, then rename it to ``<name>/`` and record its
    files. The stage is not complete yet, so what an interrupted earlier attempt left (either
    folder) is derived data and is made again."""
    final = study.path / name
    partial = study.path / f"{name}.partial"
    for stale in (final, partial):  # an interrupted earlier attempt: derived data, made again
        if stale.exists():
            shutil.rmtree(stale)
    partial.mkdir()
    details = fill(partial)
    partial.rename(final)
    study.adopt(name)
    study.save()
    return details


def require(study: Study, *stages: str) -> None:
    missing = [s for s in stages if study.stage(s).get("status") != "complete"]
    if missing:
        raise StudyError(f"{study.path}: needs the stage(s) {missing} complete first")


def scan_protocol(study: Study) -> ScanProtocol:
    """The protocol the study's scan ran (its config snapshot)."""
    return ScanProtocol.model_validate(study.manifest["config"]["scan"]["protocol"])


def simulated_knee(study: Study) -> KneePhantomSpec | None:
    """The knee phantom a simulated scan imaged (its ground truth), None for a real one."""
    config = study.manifest["config"]["scan"]
    phantom = dict(config.get("phantom", {}))
    if config["backend"]["kind"] != "sim" or phantom.pop("kind", None) != "knee":
        return None
    return KneePhantomSpec.model_validate(phantom)


def recon_grid(protocol: ScanProtocol, voxel_mm: float) -> VolumeGrid:
    """The recon stage's box (:data:`RECON_EXTENT_MM` about the orbit's isocentre, shifted by
    :data:`RECON_OFFSET_MM`) in cubic voxels of ``voxel_mm``."""
    size = tuple(round(e / voxel_mm) for e in RECON_EXTENT_MM)
    center = np.asarray(protocol.orbit.isocenter_mm) + np.asarray(RECON_OFFSET_MM)
    return VolumeGrid.centered(size, voxel_mm, tuple(center))


def recon_geometry(
    study: Study, protocol: ScanProtocol, planned: Geometry
) -> tuple[Geometry, bool]:
    """The geometry a study's scan is reconstructed on, known before its first view: the
    calibrated views when the study has a calibration (False: they place the rays too), else
    the plan's views, whose orbit sets FDK's angular weights while each view's rays come from
    its recorded matrix (True), so that the arms' tracking noise stays out of the weights."""
    if study.stage("calibration").get("status") == "complete":
        return corrected_geometry(study.path / "calibration", protocol), False
    return planned, True


@dataclass(frozen=True)
class ScanGeometry:
    """A stored scan's geometries, and the one its reconstruction takes (:func:`recon_geometry`).

    Attributes:
        recorded: Each view as recorded.
        planned: The plan's views.
        rays: The views the rays come from: the calibrated ones, else the recorded ones.
        weights: The views whose orbit sets FDK's angular weights (the plan's, with recorded
            rays), or None (the rays' own).
    """

    recorded: Geometry
    planned: Geometry
    rays: Geometry
    weights: Geometry | None

    @classmethod
    def of(cls, study: Study, protocol: ScanProtocol, header: object) -> ScanGeometry:
        """The geometries of ``study``'s scan (``header``: its projection stack's)."""
        recorded = read_rtk_geometry(study.path / "scan" / "geometry.xml", header)
        planned = read_rtk_geometry(study.path / "scan" / "planned_geometry.xml", header)
        orbit, per_view = recon_geometry(study, protocol, planned)
        if per_view:
            return cls(recorded, planned, recorded, orbit)
        return cls(recorded, planned, orbit, None)

    @property
    def calibrated(self) -> bool:
        """The rays come from the calibration."""
        return self.weights is None

    def fdk(
        self,
        projections: np.ndarray,
        grid: VolumeGrid,
        progress: Progress | None = None,
        motion: BodyMotion | None = None,
    ) -> FDKResult:
        """Weighted FDK of projections of this scan on ``grid`` (through the patient's
        ``motion`` when given)."""
        return fdk_reconstruct(
            projections,
            self.rays,
            grid,
            orbit_geometry=self.weights,
            motion=motion,
            progress=progress,
        )


def kinematics_summary(kin: KneeKinematics, truth: KneeKinematics | None = None) -> dict:
    """An assessment stage's figures: frames, those measured and why the others are not,
    whether they suffice for flags, max |MLD|, flexion range, flagged frames, DDV (over the
    measured frames; None when there is none); with ``truth`` (the simulation's true poses
    assessed alike), the frames the truth flags."""
    from assessment.flags import exclusion_sentences

    measured = kin.measured.any()
    figures = {
        "frames": len(kin.frames),
        "measured_frames": int(kin.measured.sum()),
        "not_measured": exclusion_sentences(kin),
        "tracking_sufficient": kin.sufficient,
        "max_abs_mld_mm": float(np.nanmax(np.abs(kin.mld_mm))) if measured else None,
        "flexion_range_deg": float(np.nanmax(kin.flexion_deg) - np.nanmin(kin.flexion_deg))
        if measured
        else None,
        "flagged_frames": [int(f) for f in kin.frames[kin.flagged]],
        "ddv_mm2": kin.ddv_mm2 if measured else None,
    }
    if truth is not None:
        figures["truth_flagged_frames"] = [int(f) for f in truth.frames[truth.flagged]]
    return figures


def recon_stage(
    study: Study,
    voxel_mm: float = 1.0,
    progress: Progress | None = None,
    say: Say = print,
    result: FDKResult | None = None,
    written: Path | None = None,
    compensate: bool = True,
    fit_progress: Callable[[str, int, int], None] | None = None,
    motion_rounds: int = 2,
    iteration_progress: Progress | None = None,
) -> bool:
    """Weighted FDK of ``scan/`` on :func:`recon_geometry` -> ``recon/`` (NIfTI, MetaImage,
    DICOM series, preview, recording; against the phantom when simulated). ``result`` is the
    reconstruction made during the scan (:mod:`study.live_recon`), taken as it is, and
    ``written`` its volume already on disk (moved into the stage as ``volume.mha``).

    ``compensate``: the patient's motion is estimated from the projections and, where any was
    found, the volume reconstructed through it (registration.scan_motion; the scan's volume
    made during it is kept as ``live_volume.mha``), the motion written as ``motion.csv``
    with its QA figure ``motion.png``, its peak per body recorded (``motion_rounds``: rounds
    of the two-body fit); a motion beyond what compensation is trusted for fails the stage
    with the words to repeat the scan. A protocol whose reconstruction is sart or tv
    (recon.iterative) has its volume made so from the FDK volume (``iteration_progress``
    counts subsets; the FDK volume kept as ``live_volume.mha``), unless the patient's motion
    was compensated (iterations through a motion are not built)."""

    def fill(folder: Path) -> dict:
        nonlocal result
        protocol = scan_protocol(study)
        stack = read_projections(study.path / "scan" / "projections.mha")
        views = ScanGeometry.of(study, protocol, stack.header)
        recorded, planned, calibrated = views.recorded, views.planned, views.calibrated
        grid = recon_grid(protocol, voxel_mm)
        streamed = result is not None
        estimate, unestimated = None, None
        if compensate:
            try:
                estimate = _motion(study, stack.data, views, grid, say, fit_progress, motion_rounds)
            except MotionNotEstimated as err:
                unestimated = str(err)
                say(f"motion not estimated, the volume is plain FDK's: {unestimated}")
        if result is None:
            result = views.fdk(stack.data, grid, progress)
        elif result.volume.grid != grid:
            raise ValueError(f"the reconstruction's grid {result.volume.grid} is not {grid}")
        live = result
        moved = estimate is not None and not estimate.still
        if moved:  # a still patient's volume is the plain one as it was made
            result = views.fdk(stack.data, grid, progress, estimate.motion)
        iterative = protocol_settings(protocol.reconstruction)
        if iterative is not None and moved:
            said = (
                f"{iterative.method.upper()} through the patient's motion is not built: the "
                "volume is the motion-compensated FDK"
            )
            say(said)
            method = {"method": iterative.method, "ran": False, "why": said}
        elif iterative is not None:
            run = iterative_reconstruct(
                stack.data, views.rays, grid, iterative, start=result, progress=iteration_progress
            )
            say(iterations_said(run))
            plain, result = result, run.as_fdk()
            method = {
                "method": iterative.method,
                "ran": True,
                "iterations": run.iterations,
                "stopped": run.stopped,
                "tv_weight_per_mm": run.settings.tv_weight,
            }
        else:
            method = {"method": "fdk"}
        volume = result.volume
        remade = result is not live  # compensated or iterated: the live volume kept beside
        kept = "live_volume.mha" if remade else "volume.mha"
        if written is not None:
            os.replace(written, folder / kept)
            shutil.rmtree(written.parent)
        elif remade:
            write_volume(folder / kept, live.volume)
        if remade or written is None:
            write_volume(folder / "volume.mha", volume)
        write_volume(folder / "volume.nii.gz", volume)
        knee = simulated_knee(study)
        energy = REAL_SCAN_ENERGY_KEV if knee is None else knee.effective_energy_kev
        water = attenuation_per_mm(energy)["water"]
        write_dicom_series(folder / "dicom", volume, mu_water_per_mm=water)
        title = "weighted FDK" if not method.get("ran") else method["method"].upper()
        save_orthogonal_slices(volume, folder / "slices.png", title=title)
        record_volume(volume, folder / "recording.rrd")
        details = {
            "geometry": "calibrated" if calibrated else "recorded",
            "voxel_mm": voxel_mm,
            "during_scan": streamed,
            "reconstruction": method,
        }
        if estimate is not None:
            details["motion"] = _motion_outputs(study, estimate, live, result, folder)
        elif unestimated is not None:
            details["motion"] = {"verdict": f"was not followed: {unestimated}", "estimated": False}
        if knee is not None:  # simulation: against the phantom, and the other geometries
            labels, truth = rasterize_knee(knee, grid, supersample=2)
            inside = (labels > 0) & result.mask
            rmse = {details["geometry"]: _rmse(volume.data, truth, inside)}
            if estimate is not None:
                rmse["uncompensated"] = _rmse(live.volume.data, truth, inside)
            if method.get("ran"):
                rmse["fdk"] = _rmse(plain.volume.data, truth, inside)
            others = {"recorded": recorded}
            true_path = study.path / "scan" / "true_geometry.xml"
            if true_path.exists():
                others["true"] = read_rtk_geometry(true_path, stack.header)
            for name, other in others.items():
                if name not in rmse:
                    motion = estimate.motion if moved else None
                    other_result = fdk_reconstruct(
                        stack.data, other, grid, orbit_geometry=planned, motion=motion
                    )
                    data = other_result.volume.data
                    rmse[name] = _rmse(data, truth, inside)
            details |= {f"rmse_{name}_per_mm": value for name, value in rmse.items()}
        (folder / "metrics.json").write_text(json.dumps(details, indent=2), encoding="utf-8")
        return details

    require(study, "scan")
    return run_stage(study, "recon", lambda: derived_folder(study, "recon", fill), say)


class MotionNotEstimated(ValueError):
    """The scan's motion could not be estimated (too few views, no bone to register)."""


def _motion(
    study: Study,
    projections: np.ndarray,
    views: ScanGeometry,
    grid: VolumeGrid,
    say: Say,
    progress: Callable[[str, int, int], None] | None,
    rounds: int,
) -> MotionEstimate:
    """The patient's motion during the study's scan (its exposure log's times); ValueError
    with the words to repeat the scan when it is beyond compensation;
    :class:`MotionNotEstimated` for a scan the estimate cannot run on (too few views, no bone)."""
    from registration.scan_motion import MotionSettings
    from study.jobs import MotionBeyondCompensation, compensable_motion

    log = study.path / "scan" / "exposure_log.csv"
    try:
        return compensable_motion(
            projections,
            views.rays,
            grid,
            times=read_view_times(log) if log.is_file() else None,
            orbit=views.weights,
            say=say,
            progress=progress,
            settings=MotionSettings(two_body_rounds=rounds),
        )
    except MotionBeyondCompensation:
        raise
    except ValueError as err:
        raise MotionNotEstimated(str(err)) from None


def _motion_outputs(
    study: Study, estimate: MotionEstimate, before: FDKResult, after: FDKResult, folder: Path
) -> dict:
    """motion.csv and motion.png in ``folder``; the figures study.json keeps (against the
    simulation's true motion where the scan has it)."""
    from study.jobs import write_motion

    write_motion(
        estimate, before.volume, after.volume, folder / "motion.csv", folder / "motion.png"
    )
    figures = {
        "bodies": list(estimate.motion.bodies),
        "peak_mm": {b: round(v, 2) for b, v in estimate.peak_mm.items()},
        "peak_view": estimate.peak_view,
        "verdict": estimate.verdict(),
        "notes": list(estimate.notes),
        "seconds": estimate.seconds,
        "reprojection_rms": {k: round(v, 5) for k, v in estimate.reprojection_rms.items()},
    }
    truth = study.path / "scan" / "true_motion.csv"
    if truth.is_file():
        figures["error_mm"] = motion_error(estimate, truth)
    return figures


def motion_error(estimate: MotionEstimate, truth_csv: Path) -> dict:
    """Median and 95th percentile over views of the mean distance between the estimated and
    the true positions of each body's bone-surface points, mm (a one-body estimate against
    each true body)."""
    from registration.scan_motion import LEG, surface_errors_mm

    bodies, poses = read_motion_csv(truth_csv)
    truth = dict(zip(bodies, np.moveaxis(poses, 1, 0), strict=True))
    surfaces = estimate.surface_points
    points = {b: surfaces[b] if b in surfaces else surfaces[LEG] for b in truth}
    e, _ = surface_errors_mm(estimate.motion, points, truth)
    return {"median": round(float(np.median(e)), 3), "p95": round(float(np.percentile(e, 95)), 3)}


def segmentation_stage(study: Study, say: Say = print) -> bool:
    """Bones of ``recon/`` -> ``segmentation/`` (labels, one mesh per bone; Dice against the
    phantom when simulated)."""
    from registration.segment import bone_surfaces, segment_bones

    def fill(folder: Path) -> dict:
        volume = read_volume(study.path / "recon" / "volume.nii.gz", unit="1/mm")
        knee = simulated_knee(study)
        labels = segment_bones(volume, side=None if knee is None else knee.side)
        write_volume(folder / "labels.nii.gz", labels)
        for name, mesh in bone_surfaces(labels).items():
            mesh.export(folder / f"{name}.stl")
        details = {"side": _side(labels)}
        if knee is not None:
            truth = rasterize_knee(knee, labels.grid, supersample=1)[0]
            dice = {name: _dice(labels.data, truth, v) for name, v in BONE_UNITS.items()}
            (folder / "dice.json").write_text(json.dumps(dice, indent=2), encoding="utf-8")
            details["dice"] = dice
        return details

    require(study, "recon")
    return run_stage(
        study, "segmentation", lambda: derived_folder(study, "segmentation", fill), say
    )


def registration_settings_file(configs: Path, meshes_alone: bool) -> Path:
    """The registration settings tracking takes by default: ``registration_implants.yaml``
    for implant components tracked from their meshes alone (no static scan), else
    ``registration.yaml``, in ``configs``."""
    return configs / ("registration_implants.yaml" if meshes_alone else "registration.yaml")


def track_fluoro(
    study: Study,
    say: Say,
    progress: Progress | None,
    inputs: dict[str, object],
    options: RegisterOptions,
) -> dict:
    """``study.jobs.register_files`` of ``fluoro/`` (its frames and view; ``inputs`` the rest
    of the :class:`study.jobs.RegisterInputs`) into ``registration/`` (an interrupted
    attempt's folder made again), adopted by the study; the figures of its metrics.json (none
    without truth)."""
    from study.jobs import RegisterInputs, register_files

    target = study.path / "registration"
    if target.exists():
        shutil.rmtree(target)  # an interrupted earlier attempt: derived data, made again
    fluoro = study.path / "fluoro"
    register_files(
        RegisterInputs(fluoro / "frames.mha", fluoro / "view.xml", **inputs),
        target,
        options,
        progress or (lambda done, total: say(f"registered frame {done}/{total}")),
    )
    study.adopt("registration")
    study.save()
    if not (target / "metrics.json").exists():
        return {}
    metrics = json.loads((target / "metrics.json").read_text(encoding="utf-8"))
    keep = ("tre_mm", "tre_mm_median", "rsr_pct", "in_plane_mm_median", "out_of_plane_mm_median")
    details = {k: metrics[k] for k in keep}
    details["tre_mm_max"] = max(row["tre_mm"] for row in metrics["per_frame"])
    return details


def registration_stage(
    study: Study,
    settings: Settings | None = None,
    say: Say = print,
    progress: Progress | None = None,
) -> bool:
    """BoneAxis-Reg of ``fluoro/`` against the segmented volume -> ``registration/``
    (metrics.json when the sequence has ground truth); the frames are dewarped first when
    ``fluoro/`` holds an exposure of the dewarp grid (``dewarp_grid.mha`` and its
    ``dewarp_grid.yaml``). ``progress(done, total)`` counts frames (else ``say`` does)."""
    from study.jobs import RegisterOptions, fit_fluoro_distortion

    def work() -> dict:
        fluoro = study.path / "fluoro"
        truth = fluoro / "poses.csv"
        distortion = None
        if (fluoro / "dewarp_grid.mha").exists():
            distortion = fit_fluoro_distortion(
                fluoro / "dewarp_grid.mha", fluoro / "view.xml", fluoro / "dewarp_grid.yaml"
            )
            say(
                f"dewarp: {distortion.balls} grid balls, residual RMS {distortion.rms_mm:.3f} "
                f"mm, largest displacement {distortion.max_displacement_mm:.2f} mm"
            )
        inputs = {
            "volume": study.path / "recon" / "volume.nii.gz",
            "labels": study.path / "segmentation" / "labels.nii.gz",
            "truth": truth if truth.exists() else None,
        }
        options = RegisterOptions(distortion=distortion, settings=settings)
        return track_fluoro(study, say, progress, inputs, options)

    require(study, "segmentation", "fluoro")
    return run_stage(study, "registration", work, say)


def assessment_stage(study: Study, title: str = "Knee kinematics", say: Say = print) -> bool:
    """Knee kinematics of the registered poses -> ``assessment/`` (report, plots, metrics,
    4D series)."""
    from assessment.knee import assess_knee
    from registration.poses import read_poses
    from study.jobs import write_assessment

    def fill(folder: Path) -> dict:
        labels = read_volume(study.path / "segmentation" / "labels.nii.gz", unit="label")
        poses = read_poses(study.path / "registration" / "poses.csv")
        side = study.stage("segmentation")["side"]
        folder.rmdir()  # write_assessment makes its own new folder
        volume = study.path / "recon" / "volume.nii.gz"
        overlays = study.path / "registration" / "overlays"
        moved = study.stage("recon").get("motion")
        rows = None
        if moved:
            words = "the patient's motion" if moved.get("estimated") is False else "the patient"
            rows = {"Static scan": f"{words} {moved['verdict']}"}
        kin = write_assessment(
            labels,
            poses,
            folder,
            side,
            title=title,
            volume=volume,
            overlays=overlays,
            scan_rows=rows,
        ).kinematics
        truth_path = study.path / "fluoro" / "poses.csv"  # a simulation's true poses
        truth = None
        if truth_path.is_file():
            truth = assess_knee(labels, read_poses(truth_path), side).kinematics
        return kinematics_summary(kin, truth)

    require(study, "registration", "segmentation")
    return run_stage(study, "assessment", lambda: derived_folder(study, "assessment", fill), say)


def _side(labels) -> str:
    """ "right" when the fibula lies at -x of the tibia (lateral of a right knee), else "left"."""
    x = labels.grid.axes_mm()[0]
    centre = {
        bone: x[np.nonzero(labels.data == LABELS[bone])[2]].mean() for bone in ("tibia", "fibula")
    }
    return "right" if centre["fibula"] < centre["tibia"] else "left"


def _rmse(volume: np.ndarray, truth: np.ndarray, inside: np.ndarray) -> float:
    return float(np.sqrt(np.mean((volume - truth)[inside] ** 2)))


def _dice(labels: np.ndarray, truth: np.ndarray, values: tuple[int, ...]) -> float:
    a, b = np.isin(labels, values), np.isin(truth, values)
    return float(2 * np.sum(a & b) / max(np.sum(a) + np.sum(b), 1))
