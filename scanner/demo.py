"""``cbct demo``: the main job on the simulated scanner, as far as the stack reaches today.

Plan the demo protocol on the scanner (robot motion, clearance, timing, a rerun recording),
scan the standing knee phantom with it (quantum and readout noise), reconstruct it with
weighted FDK, write the volume (NIfTI, MetaImage, DICOM series) and a preview, and measure the
reconstruction against the phantom. Calibration, registration and the clinical report join as
their packages land.
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
from recon.volume import VolumeGrid
from scanner.jobs import Status, new_folder, software_version, write_scan
from sim.phantoms.knee import KneePhantomSpec, attenuation_per_mm, rasterize_knee
from sim.scan import simulate_knee_scan
from trajectories.config import ScannerConfig
from trajectories.model import ScannerModel
from trajectories.plan import plan_scan
from trajectories.recording import record_plan

FULL = {"views": 180, "panel": 256, "sim_voxel_mm": 0.75, "recon_voxel_mm": 1.0}
QUICK = {"views": 90, "panel": 128, "sim_voxel_mm": 1.0, "recon_voxel_mm": 1.5}


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

    say("stage 1/3: planning the scan on the scanner (IK, clearance, timing)")
    plan = plan_scan(scanner, protocol)
    plan.save(out / "plan")
    record_plan(plan, scanner, out / "plan" / "recording.rrd")

    say("stage 2/3: simulated scan of the standing knee phantom")
    scan = simulate_knee_scan(protocol, phantom, voxel_mm=size["sim_voxel_mm"], status=say)
    scan_dir = new_folder(out / "scan")
    write_scan(
        scan_dir,
        scan,
        {
            "software_version": software_version(),
            "protocol": protocol.model_dump(mode="json"),
            "phantom": phantom.model_dump(mode="json"),
            "voxel_mm": size["sim_voxel_mm"],
            "seed": 0,
            "noise": True,
            "photons_per_pixel": scan.photons_per_pixel,
        },
    )

    say("stage 3/3: weighted FDK reconstruction")
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
        "total_s": round(time.perf_counter() - started, 2),
        "rmse_per_mm": float(np.sqrt(np.mean(error**2))),
        "rmse_relative_to_soft_tissue": float(np.sqrt(np.mean(error**2)) / mu["muscle"]),
        "masked_fraction": float(1 - result.mask.mean()),
    }
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    return (
        f"[green]demo finished[/] in {metrics['total_s']:.0f} s -> {out}\n"
        f"  plan:    {out}/plan/ ({plan.duration_s:.1f} s of motion, min clearance "
        f"{plan.min_clearance_mm:.1f} mm), recording {out}/plan/recording.rrd\n"
        f"  scan:    {scan_dir}/projections.mha, geometry.xml (RTK), phantom.nii.gz\n"
        f"  volume:  {recon_dir}/volume.nii.gz (+ .mha, dicom/), preview {recon_dir}/slices.png\n"
        f"  recon RMSE vs phantom inside the leg: {metrics['rmse_per_mm']:.5f} /mm "
        f"({100 * metrics['rmse_relative_to_soft_tissue']:.1f} % of soft tissue), "
        f"FDK {recon_s:.1f} s for {len(scan.geometry)} views"
    )
