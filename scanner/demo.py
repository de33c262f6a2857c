"""``cbct demo``: the main job on the simulated scanner, in one study folder (DESIGN.md).

1. plan the knee reverse spiral on the scanner (IK, clearance, timing);
2. scan the steel-ball phantom on the vibrating mock arms and calibrate every view;
3. scan the standing knee phantom on the same plan;
4. weighted FDK with the calibrated geometry (NIfTI, MetaImage, DICOM series, preview);
5. segment femur, tibia-fibula and patella (labels, meshes);
6. simulate lateral fluoroscopy of a flexion-extension with a varus imbalance mid-motion;
7. track the bones with BoneAxis-Reg, scored against the simulation's truth;
8. assess the registered motion (report, plots, metrics, 4D series);
9. merge every stage's rerun recording into ``recording.rrd``.

Each stage is marked in ``study.json`` when complete, with its files' checksums; a stage
writes into ``<stage>.partial/`` and is renamed when done, so ``--resume`` redoes only what
is missing (the scans continue from their last stored view).
"""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from calibration.calibrate import calibrate, corrected_geometry
from recon.config import ScanProtocol, load_config, load_protocol
from recon.dicom import write_dicom_series
from recon.fdk import Progress, fdk_reconstruct
from recon.io import read_projections, read_volume, write_volume
from recon.preview import save_orthogonal_slices
from recon.rtk_xml import read_rtk_geometry
from recon.volume import VolumeGrid
from registration.boneaxis import Settings
from registration.labels import BONE_UNITS
from registration.poses import read_poses
from registration.segment import bone_surfaces, segment_bones
from registration.track import register_files
from scanner.jobs import Status, write_assessment
from scanner.recording import merge_recordings, record_volume
from scanner.session import read_inputs, scan_stage
from scanner.study import Study, StudyError
from sim.fluoro import lateral_view, save_sequence, simulate_fluoroscopy
from sim.motion import flexion_extension
from sim.phantoms.bb import BBPhantomSpec
from sim.phantoms.knee import KneePhantomSpec, attenuation_per_mm, rasterize_knee

FULL = {
    "views": 180,
    "panel": 256,
    "calibration_panel": 512,
    "phantom_voxel_mm": 0.75,
    "recon_voxel_mm": 0.8,
    "fluoro_panel": 512,
    "fluoro_voxel_mm": 0.5,
    "frames": 30,
    "max_flexion_deg": 90.0,
}
QUICK = {
    "views": 90,
    "panel": 256,
    "calibration_panel": 512,
    "phantom_voxel_mm": 1.0,
    "recon_voxel_mm": 1.0,
    "fluoro_panel": 256,
    "fluoro_voxel_mm": 1.0,
    "frames": 8,
    "max_flexion_deg": 40.0,
}
VARUS_DEG = 3.0
"""Varus tilt built into the fluoroscopy motion (frames 40-60 % of the way through)."""
RECON_GRID_MM = (100.0, 100.0, 240.0)
"""Reconstructed field: x, y, z extent around the knee, mm (what the fluoroscopy field sees)."""
FLUORO_PANEL_MM = 307.2
"""Fluoroscopy panel width (the 0.3 mm x 1024 panel), read out binned."""
STAGES = (
    "plan",
    "calibration_scan",
    "calibration",
    "scan",
    "recon",
    "segmentation",
    "fluoro",
    "registration",
    "assessment",
)


def _protocols(configs: Path, size: dict) -> tuple[ScanProtocol, ScanProtocol]:
    """The knee protocol and its calibration read-out (same plan, finer pixels)."""
    base = load_protocol(configs / "protocols" / "demo_knee.yaml")
    orbit = base.orbit.model_copy(update={"views": size["views"]})

    def readout(n: int) -> ScanProtocol:
        width = base.detector.width_mm
        panel = base.detector.model_copy(update={"rows": n, "cols": n, "pixel_pitch_mm": width / n})
        data = base.model_copy(update={"detector": panel, "orbit": orbit}).model_dump()
        return ScanProtocol.model_validate(data)

    return readout(size["panel"]), readout(size["calibration_panel"])


class _Stages:
    """Runs the demo's stages in order, skipping the complete ones."""

    def __init__(self, study: Study, say: Status) -> None:
        self.study, self.say = study, say
        self.seconds: dict[str, float] = {}

    def run(self, name: str, number: int, title: str, work: Callable[[], dict | None]) -> None:
        if self.study.stage(name).get("status") == "complete":
            self.say(f"stage {number}/{len(STAGES)} {name}: complete, skipped")
            return
        self.say(f"stage {number}/{len(STAGES)} {name}: {title}")
        started = time.perf_counter()
        try:
            details = work() or {}
        except BaseException as err:
            if self.study.stage(name).get("status") != "incomplete":  # scans mark their own
                self.study.mark(name, "incomplete", reason=f"{type(err).__name__}: {err}")
            raise
        self.seconds[name] = round(time.perf_counter() - started, 2)
        if self.study.stage(name).get("status") != "complete":
            self.study.mark(name, "complete", **{**details, "seconds": self.seconds[name]})

    def folder(self, name: str, fill: Callable[[Path], dict | None]) -> dict | None:
        """Write a derived stage into ``<name>.partial/``, then rename it and adopt its files."""
        final = self.study.path / name
        partial = self.study.path / f"{name}.partial"
        if final.exists():
            raise StudyError(f"{final} exists but {name} is not complete: remove it to redo")
        if partial.exists():
            shutil.rmtree(partial)
        partial.mkdir()
        details = fill(partial)
        partial.rename(final)
        self.study.adopt(name)
        return details


def run(
    out: Path,
    configs: Path,
    *,
    quick: bool = False,
    resume: bool = False,
    status: Status | None = None,
    progress: Progress | None = None,
) -> str:
    """Run the demo into the new folder ``out`` (or continue it); returns the summary."""
    say = status or (lambda _msg: None)
    size = QUICK if quick else FULL
    protocol, cal_protocol = _protocols(configs, size)
    knee = load_config(configs / "phantoms" / "knee.yaml", KneePhantomSpec)
    bb = load_config(configs / "phantoms" / "bb_helix.yaml", BBPhantomSpec)
    settings = load_config(configs / "registration.yaml", Settings)

    def inputs(p: ScanProtocol, phantom: str):
        return read_inputs(
            p,
            configs / "scanner.yaml",
            "sim",
            configs / "backends" / "sim.yaml",
            configs / "phantoms" / ("knee.yaml" if phantom == "knee" else "bb_helix.yaml"),
            phantom_voxel_mm=size["phantom_voxel_mm"],
            phantom_kind=phantom,
        )

    knee_inputs, bb_inputs = inputs(protocol, "knee"), inputs(cal_protocol, "bb")
    if resume:
        study = Study.open(out)
        if study.manifest["config"].get("demo", {}).get("size") != size:
            raise StudyError(f"{out} was made with other demo settings (--quick differs)")
    else:
        study = Study.create(out, {"demo": {"size": size, "varus_deg": VARUS_DEG}})
    stages = _Stages(study, say)
    started = time.perf_counter()
    results: dict = {}

    stages.run(
        "calibration_scan",
        1,
        "plan, then scan the steel-ball phantom",
        lambda: scan_stage(
            study,
            None if "calibration_scan" in study.manifest["config"] else bb_inputs,
            "calibration_scan",
            say=say,
        ),
    )

    def do_calibration() -> dict:
        stack = read_projections(out / "calibration_scan" / "projections.mha")
        planned = cal_protocol.orbit.geometry(cal_protocol.detector)
        cal = calibrate(stack.data, planned, bb, cal_protocol, progress=progress)
        cal.save(out / "calibration")
        study.adopt("calibration")
        summary = cal.summary()
        return {k: v for k, v in summary.items() if not isinstance(v, (list, dict))}

    stages.run("calibration", 2, "fit every view's projection matrix", do_calibration)
    stages.run(
        "scan",
        3,
        "scan the standing knee",
        lambda: scan_stage(
            study, None if "scan" in study.manifest["config"] else knee_inputs, "scan", say=say
        ),
    )

    def recon(folder: Path) -> dict:
        stack = read_projections(out / "scan" / "projections.mha")
        geometry = corrected_geometry(out / "calibration", protocol)
        recorded = read_rtk_geometry(out / "scan" / "geometry.xml", protocol.detector)
        grid = _recon_grid(knee, size["recon_voxel_mm"])
        result = fdk_reconstruct(stack.data, geometry, grid, progress=progress)
        volume = result.volume
        write_volume(folder / "volume.nii.gz", volume)
        write_volume(folder / "volume.mha", volume)
        mu = attenuation_per_mm(knee.effective_energy_kev)
        write_dicom_series(
            folder / "dicom",
            volume,
            mu_water_per_mm=mu["water"],
            series_description="dualarm-cbct demo knee",
        )
        save_orthogonal_slices(volume, folder / "slices.png", title="cbct demo: weighted FDK")
        record_volume(volume, folder / "recording.rrd")
        labels, truth = rasterize_knee(knee, grid, supersample=2)
        inside = (labels > 0) & result.mask
        rmse = {"calibrated": _rmse(volume.data, truth, inside)}
        true = read_rtk_geometry(out / "scan" / "true_geometry.xml", protocol.detector)
        for name, other in (("recorded", recorded), ("true", true)):
            rmse[name] = _rmse(fdk_reconstruct(stack.data, other, grid).volume.data, truth, inside)
        metrics = {
            "rmse_per_mm": rmse,
            "rmse_relative_to_soft_tissue": rmse["calibrated"] / mu["muscle"],
            "voxels_xyz": list(grid.size_xyz),
            "voxel_mm": size["recon_voxel_mm"],
        }
        (folder / "metrics.json").write_text(json.dumps(metrics, indent=2), encoding="utf-8")
        results["recon"] = metrics
        return {
            "rmse_true_per_mm": rmse["true"],
            "rmse_calibrated_per_mm": rmse["calibrated"],
            "rmse_recorded_per_mm": rmse["recorded"],
        }

    stages.run(
        "recon",
        4,
        "weighted FDK with the calibrated geometry",
        lambda: stages.folder("recon", recon),
    )

    def segmentation(folder: Path) -> dict:
        volume = read_volume(out / "recon" / "volume.nii.gz", unit="1/mm")
        labels = segment_bones(volume, side=knee.side)
        write_volume(folder / "labels.nii.gz", labels)
        for name, mesh in bone_surfaces(labels).items():
            mesh.export(folder / f"{name}.stl")
        truth = rasterize_knee(knee, labels.grid, supersample=1)[0]
        dice = {name: _dice(labels.data, truth, values) for name, values in BONE_UNITS.items()}
        (folder / "dice.json").write_text(json.dumps(dice, indent=2), encoding="utf-8")
        return {"dice": dice}

    stages.run(
        "segmentation",
        5,
        "bones from the reconstruction",
        lambda: stages.folder("segmentation", segmentation),
    )

    def fluoro(folder: Path) -> dict:
        n = size["frames"]
        first, last = round(0.4 * (n - 1)), round(0.6 * (n - 1))
        motion = flexion_extension(knee, n, size["max_flexion_deg"], VARUS_DEG, (first, last))
        panel = protocol.detector.model_copy(
            update={
                "rows": size["fluoro_panel"],
                "cols": size["fluoro_panel"],
                "pixel_pitch_mm": FLUORO_PANEL_MM / size["fluoro_panel"],
            }
        )
        view = lateral_view(knee, panel)
        sequence = simulate_fluoroscopy(
            knee, motion, view, voxel_mm=size["fluoro_voxel_mm"], status=say
        )
        save_sequence(sequence, folder)
        return {"frames": n, "max_flexion_deg": size["max_flexion_deg"], "varus_deg": VARUS_DEG}

    stages.run(
        "fluoro",
        6,
        "lateral fluoroscopy of a flexion-extension",
        lambda: stages.folder("fluoro", fluoro),
    )

    def registration() -> dict:
        target = out / "registration"
        if target.exists():
            shutil.rmtree(target)  # an interrupted earlier attempt: derived data, made again
        register_files(
            out / "recon" / "volume.nii.gz",
            out / "segmentation" / "labels.nii.gz",
            out / "fluoro" / "frames.mha",
            out / "fluoro" / "view.xml",
            target,
            truth_path=out / "fluoro" / "poses.csv",
            settings=settings,
            progress=lambda done, total: say(f"  registered frame {done}/{total}"),
        )
        study.adopt("registration")
        metrics = json.loads((target / "metrics.json").read_text(encoding="utf-8"))
        results["registration"] = metrics
        keep = (
            "tre_mm",
            "tre_mm_median",
            "rsr_pct",
            "in_plane_mm_median",
            "out_of_plane_mm_median",
        )
        details = {k: metrics[k] for k in keep}
        details["tre_mm_max"] = max(row["tre_mm"] for row in metrics["per_frame"])
        return details

    stages.run("registration", 7, "BoneAxis-Reg tracking", registration)

    def assessment(folder: Path) -> dict:
        labels = read_volume(out / "segmentation" / "labels.nii.gz", unit="label")
        poses = read_poses(out / "registration" / "poses.csv")
        folder.rmdir()  # write_assessment makes its own new folder
        result = write_assessment(
            labels,
            poses,
            folder,
            knee.side,
            title="Demo: registered weight-bearing flexion-extension",
        )
        kin = result.kinematics
        return {
            "frames": len(kin.frames),
            "max_abs_mld_mm": float(np.abs(kin.mld_mm).max()),
            "flagged_frames": [int(f) for f in kin.frames[kin.flagged]],
            "ddv_mm2": kin.ddv_mm2,
        }

    stages.run(
        "assessment", 8, "knee kinematics report", lambda: stages.folder("assessment", assessment)
    )

    recording = out / "recording.rrd"
    if not recording.exists():
        say(f"stage 9/{len(STAGES)}: one recording of every stage")
        parts = [
            out / "plan" / "recording.rrd",
            *sorted((out / "calibration_scan").glob("recording*.rrd")),
            *sorted((out / "scan").glob("recording*.rrd")),
            out / "recon" / "recording.rrd",
            out / "assessment" / "series.rrd",
        ]
        merge_recordings(parts, recording)
        study.adopt("recording.rrd")
        study.save()
    return _summary(study, out, time.perf_counter() - started)


def _recon_grid(knee: KneePhantomSpec, voxel_mm: float) -> VolumeGrid:
    size = tuple(round(e / voxel_mm) for e in RECON_GRID_MM)
    center = (0.0, -10.0, knee.joint_line_height_mm + 10.0)
    return VolumeGrid.centered(size, voxel_mm, center)


def _rmse(volume: np.ndarray, truth: np.ndarray, inside: np.ndarray) -> float:
    return float(np.sqrt(np.mean((volume - truth)[inside] ** 2)))


def _dice(labels: np.ndarray, truth: np.ndarray, values: tuple[int, ...]) -> float:
    a, b = np.isin(labels, values), np.isin(truth, values)
    return float(2 * np.sum(a & b) / max(np.sum(a) + np.sum(b), 1))


def _summary(study: Study, out: Path, seconds: float) -> str:
    stages = study.manifest["stages"]
    recon = stages["recon"]
    reg = stages["registration"]
    assess = stages["assessment"]
    return (
        f"[green]demo finished[/] in {seconds:.0f} s -> {out}\n"
        f"  report:     {out}/assessment/report.html (max |MLD| "
        f"{assess['max_abs_mld_mm']:.2f} mm, {len(assess['flagged_frames'])} frames flagged)\n"
        f"  recording:  rerun {out}/recording.rrd\n"
        f"  volume:     {out}/recon/volume.nii.gz (+ .mha, dicom/), preview "
        f"{out}/recon/slices.png; RMSE vs phantom {recon['rmse_calibrated_per_mm']:.5f} /mm "
        f"with the calibrated geometry ({recon['rmse_recorded_per_mm']:.5f} recorded, "
        f"{recon['rmse_true_per_mm']:.5f} true)\n"
        f"  registration: TRE mean {reg['tre_mm']:.2f} mm (median {reg['tre_mm_median']:.2f}), "
        f"RSR {reg['rsr_pct']:.1f} %  ({out}/registration/poses.csv)\n"
        f"  study:      {out}/study.json (every stage, every file's sha256)"
    )
