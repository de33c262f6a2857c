"""Benchmark: geometric calibration with the steel-ball phantom on vibrating arms.

The calibration protocol (360 views of the full-resolution 61 cm panel, a two-pass reverse
spiral) scans the 24-ball helix phantom, placed off its nominal pose (1 mm, 12 deg), on arms
vibrating 0.5 mm (source and panel, RMS) and 0.2 deg (panel tilt). Detected centroids get
0.1 px of extra Gaussian noise per coordinate. Then:

- reprojection of the balls used in the fit;
- hold-out reprojection of a 5 x 5 x 5 grid of points filling +-40 mm around the isocentre
  (not balls, not in the fit), px and mm at the detector, calibrated and planned ("uncalibrated");
- source, panel-centre and panel-angle errors against the true views;
- a knee scan on the same vibrating arms reconstructed (256^3 of 0.5 mm) with the planned,
  calibrated and true geometries: RMSE against the phantom inside the leg.

The calibration's world frame is fixed by the phantom's estimated pose (the gauge): an offset
common to all views is attributed to the phantom. Errors against the truth are measured after
mapping the estimated phantom pose onto the true one (``gauge_offset_mm`` reports that map);
the reconstruction with the calibrated geometry is likewise compared in the gauge frame
(the phantom is moved by the same map).

Prints one JSON object. Usage: ``python bench/calibration.py [--views N]``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from calibration.calibrate import calibrate_balls, find_balls  # noqa: E402
from calibration.fit import dlt, project  # noqa: E402
from calibration.phantom import BBPhantomSpec  # noqa: E402
from recon.config import load_config, load_protocol  # noqa: E402
from recon.fdk import fdk_reconstruct  # noqa: E402
from recon.geometry import Geometry, View  # noqa: E402
from recon.volume import VolumeGrid  # noqa: E402
from sim.phantoms.bb import project_bb  # noqa: E402
from sim.phantoms.knee import KneePhantomSpec, rasterize_knee  # noqa: E402
from sim.scan import simulate_knee_scan  # noqa: E402
from sim.vibration import VibrationSpec, vibrate  # noqa: E402

CENTROID_NOISE_PX = 0.1


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", type=int, default=360)
    args = parser.parse_args()

    def log(msg: str) -> None:
        print(f"[bench/calibration] {msg}", file=sys.stderr, flush=True)

    protocol = load_protocol(ROOT / "configs" / "protocols" / "calibration_spiral.yaml")
    protocol = protocol.model_copy(
        update={"orbit": protocol.orbit.model_copy(update={"views": args.views})}
    )
    planned = protocol.orbit.geometry(protocol.detector)
    true = vibrate(planned, VibrationSpec(source_mm=0.5, detector_mm=0.5, detector_deg=0.2))
    nominal_bb = load_config(ROOT / "configs" / "phantoms" / "bb_helix.yaml", BBPhantomSpec)
    placed = nominal_bb.model_copy(
        update={"center_mm": (0.7, -1.2, 481.0), "rotation_deg": (0.5, 0.3, 12.0)}
    )
    log(f"projecting the BB phantom into {len(planned)} views")
    projections = project_bb(placed, true)

    log("finding and identifying balls")
    start = time.perf_counter()
    found, counts = find_balls(projections, planned, nominal_bb)
    rng = np.random.default_rng(1)
    noisy = [(ids, uv + rng.normal(0.0, CENTROID_NOISE_PX, uv.shape)) for ids, uv in found]
    calibration = calibrate_balls(noisy, counts, planned, nominal_bb, protocol)
    seconds = time.perf_counter() - start
    log(f"calibrated in {seconds:.1f} s")

    gauge = placed.T_world_phantom @ np.linalg.inv(calibration.T_world_phantom)
    aligned = [v.transformed(gauge) for v in calibration.geometry]
    calibrated = [r.view for r in calibration.views if r.status == "calibrated"]
    rms = np.array([r.reprojection_rms_px for r in calibration.views if r.view in calibrated])
    grid = np.stack(np.meshgrid(*[np.linspace(-40, 40, 5)] * 3, indexing="ij"), -1)
    points = grid.reshape(-1, 3) + np.array(protocol.orbit.isocenter_mm)

    def holdout(geometry) -> np.ndarray:
        return np.concatenate(
            [
                np.linalg.norm(g.project(points) - t.project(points), axis=1)
                for g, t in zip(geometry, true, strict=True)
            ]
        )

    held = holdout(aligned)
    uncalibrated = holdout(planned)
    source = np.array(
        [np.linalg.norm(a.source_mm - t.source_mm) for a, t in zip(aligned, true, strict=True)]
    )
    center = np.array(
        [
            np.linalg.norm(a.detector_center_mm - t.detector_center_mm)
            for a, t in zip(aligned, true, strict=True)
        ]
    )
    angle = np.array(
        [
            np.degrees(np.arccos(np.clip(a.normal @ t.normal, -1, 1)))
            for a, t in zip(aligned, true, strict=True)
        ]
    )
    # the free 11-parameter fit, for comparison (source position from its decomposition)
    world = placed.ball_positions_mm()
    free_source = []
    free_held = []
    for (ids, uv), t in zip(noisy, true, strict=True):
        if len(ids) < 8:
            continue
        P = dlt(world[ids], uv)
        free = View.from_matrix(P, t.pitch_u_mm, t.rows, t.cols)
        free_source.append(np.linalg.norm(free.source_mm - t.source_mm))
        free_held.append(np.linalg.norm(project(P, points) - t.project(points), axis=1))

    log("simulating and reconstructing the knee scan on the same vibrating arms")
    spec = KneePhantomSpec()
    scan = simulate_knee_scan(protocol, spec, voxel_mm=0.5, geometry=true, noise=False)
    grid3d = VolumeGrid.centered((256, 256, 256), 0.5, (0.0, -4.0, 480.0))
    labels, truth = rasterize_knee(spec, grid3d, supersample=3)
    inside = labels > 0
    rmse = {}
    for name, geometry in (("nominal", planned), ("calibrated", Geometry(aligned)), ("true", true)):
        volume = fdk_reconstruct(
            scan.projections, Geometry(list(geometry)), grid3d, window="ram-lak"
        ).volume.data
        rmse[name] = float(np.sqrt(np.mean((volume - truth)[inside] ** 2)))
        log(f"recon RMSE with the {name} geometry: {rmse[name]:.6f} /mm")

    pitch = protocol.detector.pixel_pitch_mm
    result = {
        "benchmark": "calibration",
        "views": len(planned),
        "balls": nominal_bb.balls,
        "vibration": {"source_mm": 0.5, "detector_mm": 0.5, "detector_deg": 0.2},
        "centroid_noise_px": CENTROID_NOISE_PX,
        "calibrated_views": len(calibrated),
        "reproj_px_median": float(np.median(rms)),
        "reproj_px_max": float(rms.max()),
        "holdout_reproj_px_mean": float(held.mean()),
        "holdout_reproj_px_p95": float(np.percentile(held, 95)),
        "holdout_reproj_mm_mean": float(held.mean() * pitch),
        "uncalibrated_holdout_px_mean": float(uncalibrated.mean()),
        "free_dlt_holdout_px_mean": float(np.concatenate(free_held).mean()),
        "free_dlt_source_err_mm_median": float(np.median(free_source)),
        "source_err_mm_median": float(np.median(source)),
        "source_err_mm_max": float(source.max()),
        "detector_center_err_mm_median": float(np.median(center)),
        "detector_angle_err_deg_median": float(np.median(angle)),
        "gauge_offset_mm": float(np.linalg.norm(gauge[:3, 3])),
        "s_per_view": seconds / len(planned),
        "recon_rmse_nominal": rmse["nominal"],
        "recon_rmse_calibrated": rmse["calibrated"],
        "recon_rmse_true": rmse["true"],
    }
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
