"""``cbct demo``: the main job on the simulated scanner, as far as the stack reaches today.

Plan the demo protocol on the scanner (robot motion, clearance, timing, a rerun recording),
scan the standing knee phantom with it (quantum and readout noise), reconstruct it with
weighted FDK, write the volume (NIfTI, MetaImage, DICOM series) and a preview, measure the
reconstruction against the phantom, and assess a simulated flexion-extension with a built-in
varus imbalance (the clinical report, from the simulator's ground-truth poses until
registration lands). Calibration and registration join as their packages land.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from recon.config import load_config, load_protocol
from recon.dicom import write_dicom_series
from recon.fdk import Progress, fdk_reconstruct
from recon.io import write_volume
from recon.preview import save_orthogonal_slices
from recon.volume import Volume, VolumeGrid
from registration.poses import BonePose, write_poses
from scanner.jobs import Status, new_folder, software_version, write_assessment, write_scan
from sim.motion import flexion_extension
from sim.phantoms.knee import KNEE_LABELS, KneePhantomSpec, attenuation_per_mm, rasterize_knee
from sim.scan import simulate_knee_scan
from trajectories.config import ScannerConfig
from trajectories.model import ScannerModel
from trajectories.plan import plan_scan
from trajectories.recording import record_plan

FULL = {"views": 180, "panel": 256, "sim_voxel_mm": 0.75, "recon_voxel_mm": 1.0, "frames": 30}
QUICK = {"views": 90, "panel": 128, "sim_voxel_mm": 1.0, "recon_voxel_mm": 1.5, "frames": 15}
VARUS_DEG = 3.0
"""Varus tilt built into the demo motion (frames 40-60 % of the way through): MLD ~ -2.4 mm."""


def run(
    out: Path,
    configs: Path,
    *,
    quick: bool = False,
    status: Status | None = None,
    progress: Progress | None = None,
) -> str:
    """Run the demo into the new folder ``out``; returns the summary to print."""
    say = status or (lambda _msg: None)
    size = QUICK if quick else FULL
    protocol = load_protocol(configs / "protocols" / "demo_knee.yaml")
    phantom = load_config(configs / "phantoms" / "knee.yaml", KneePhantomSpec)
    if quick:  # same panel and orbit, read out binned 2x more and half the views
        panel = protocol.detector.model_copy(
            update={
                "rows": size["panel"],
                "cols": size["panel"],
                "pixel_pitch_mm": protocol.detector.pixel_pitch_mm * 2,
            }
        )
        orbit = protocol.orbit.model_copy(update={"views": size["views"]})
        protocol = protocol.model_copy(update={"detector": panel, "orbit": orbit})
    scanner = ScannerModel(load_config(configs / "scanner.yaml", ScannerConfig))
    new_folder(out)
    started = time.perf_counter()

    say("stage 1/4: planning the scan on the scanner (IK, clearance, timing)")
    plan = plan_scan(scanner, protocol)
    plan.save(out / "plan")
    record_plan(plan, scanner, out / "plan" / "recording.rrd")

    say("stage 2/4: simulated scan of the standing knee phantom")
    scan = simulate_knee_scan(protocol, phantom, voxel_mm=size["sim_voxel_mm"], status=say)
    scan_dir = new_folder(out / "scan")
    manifest = {
        "software_version": software_version(),
        "protocol": protocol.model_dump(mode="json"),
        "phantom": {"kind": "knee", **phantom.model_dump(mode="json")},
        "voxel_mm": size["sim_voxel_mm"],
        "seed": 0,
        "noise": True,
        "photons_per_pixel": scan.photons_per_pixel,
    }
    volumes = {"phantom.nii.gz": scan.attenuation, "labels.nii.gz": scan.labels}
    write_scan(scan_dir, scan.projections, scan.counts, scan.geometry, manifest, None, volumes)

    say("stage 3/4: weighted FDK reconstruction")
    sim_grid = scan.attenuation.grid
    spacing = size["recon_voxel_mm"]
    extent = np.array(sim_grid.size_xyz) * np.array(sim_grid.spacing_mm)
    grid = VolumeGrid.centered(
        tuple(int(n) for n in np.floor(extent / spacing)), spacing, sim_grid.center_mm
    )
    recon_start = time.perf_counter()
    result = fdk_reconstruct(scan.projections, scan.geometry, grid, progress=progress)
    recon_s = time.perf_counter() - recon_start
    recon_dir = new_folder(out / "recon")
    write_volume(recon_dir / "volume.nii.gz", result.volume)
    write_volume(recon_dir / "volume.mha", result.volume)
    mu = attenuation_per_mm(phantom.effective_energy_kev)
    write_dicom_series(
        recon_dir / "dicom",
        result.volume,
        mu_water_per_mm=mu["water"],
        series_description="dualarm-cbct demo knee",
    )
    save_orthogonal_slices(
        result.volume,
        recon_dir / "slices.png",
        title="cbct demo: weighted FDK of the simulated knee scan",
    )

    say("measuring the reconstruction against the phantom")
    labels, truth = rasterize_knee(phantom, grid, supersample=3)
    inside = result.mask & (labels > 0)
    error = result.volume.data[inside] - truth[inside]
    metrics = {
        "views": len(scan.geometry),
        "plan": plan.summary(),
        "panel": [scan.geometry.rows, scan.geometry.cols],
        "recon_voxels_xyz": list(grid.size_xyz),
        "recon_voxel_mm": spacing,
        "recon_s": round(recon_s, 2),
        "rmse_per_mm": float(np.sqrt(np.mean(error**2))),
        "rmse_relative_to_soft_tissue": float(np.sqrt(np.mean(error**2)) / mu["muscle"]),
        "masked_fraction": float(1 - result.mask.mean()),
    }
    say("stage 4/4: knee kinematics of a simulated flexion-extension (ground-truth poses)")
    kinematics = _assess_motion(out, phantom, size["frames"])
    metrics["total_s"] = round(time.perf_counter() - started, 2)
    metrics["assessment"] = {
        "frames": len(kinematics.frames),
        "max_abs_mld_mm": float(abs(kinematics.mld_mm).max()),
        "flagged_frames": [int(f) for f in kinematics.frames[kinematics.flagged]],
        "ddv_mm2": kinematics.ddv_mm2,
    }
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2), encoding="utf-8")
    return (
        f"[green]demo finished[/] in {metrics['total_s']:.0f} s -> {out}\n"
        f"  plan:    {out}/plan/ ({plan.duration_s:.1f} s of motion, min clearance "
        f"{plan.min_clearance_mm:.1f} mm), recording {out}/plan/recording.rrd\n"
        f"  scan:    {scan_dir}/projections.mha, geometry.xml (RTK), phantom.nii.gz\n"
        f"  volume:  {recon_dir}/volume.nii.gz (+ .mha, dicom/), preview {recon_dir}/slices.png\n"
        f"  report:  {out}/assessment/report.html (max |MLD| "
        f"{metrics['assessment']['max_abs_mld_mm']:.2f} mm, "
        f"{len(metrics['assessment']['flagged_frames'])} frames flagged), 4D series "
        f"{out}/assessment/series.rrd\n"
        f"  recon RMSE vs phantom inside the leg: {metrics['rmse_per_mm']:.5f} /mm "
        f"({100 * metrics['rmse_relative_to_soft_tissue']:.1f} % of soft tissue), "
        f"FDK {recon_s:.1f} s for {len(scan.geometry)} views"
    )


def _assess_motion(out: Path, phantom: KneePhantomSpec, frames: int):
    """Flexion-extension 0-90-0 deg with a varus tilt mid-motion; poses and report to disk."""
    grid = VolumeGrid.centered((140, 140, 320), 1.0, (0.0, -4.0, phantom.joint_line_height_mm + 10))
    labels = Volume(rasterize_knee(phantom, grid, supersample=1)[0], grid, "label")
    first, last = round(0.4 * (frames - 1)), round(0.6 * (frames - 1))
    motion = flexion_extension(phantom, frames, 90.0, VARUS_DEG, (first, last))
    bones = ("femur", "tibia", "patella")
    poses = [
        BonePose(int(f), b, motion.poses[b][i]) for i, f in enumerate(motion.frames) for b in bones
    ]
    fluoro = new_folder(out / "fluoro")
    x, y, z = grid.axes_mm()
    centroids = {}
    for bone in bones:
        kz, ky, kx = np.nonzero(labels.data == KNEE_LABELS[bone])
        centroids[bone] = np.array([x[kx].mean(), y[ky].mean(), z[kz].mean()])
    write_poses(fluoro / "truth_poses.csv", poses, centroids)
    write_volume(fluoro / "labels.nii.gz", labels)
    result = write_assessment(
        labels,
        poses,
        out / "assessment",
        phantom.side,
        title="Demo: simulated weight-bearing flexion-extension",
    )
    return result.kinematics
