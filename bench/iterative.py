"""Benchmark: iterative reconstruction (OS-SART, OS-SART + TV) against FDK and RTK's CPU
iterative filters, on sparse-view and low-dose scans.

Two objects, each scanned once over a full circular turn (SID 600 mm, SDD 1000 mm) and
reconstructed from all its views and from every 2nd, 4th and 6th (360, 180, 90, 60 views), at
full and at a quarter of the photons per view (Poisson and readout noise, sim.scan.add_noise):

- ``knee``: the digital knee phantom rasterised at half the voxel, projected by our Joseph
  projector, reconstructed on its field of view; RMSE and SSIM over the knee (tissue and
  bone), and the mean Dice of the four bones segmented by registration.segment;
- ``shepp_logan``: RTK's analytic ray-ellipsoid projections of its 3-D Shepp-Logan phantom
  (an independent forward model), densities scaled to water (``SHEPP_LOGAN_MU``); RMSE and
  SSIM over the central 75 % cylinder.

Methods: ours ``fdk`` (Hann), ``sart`` and ``tv`` (recon.iterative, default TV weight), and
RTK 2.7's ``rtk_sart`` (SARTConeBeamReconstructionFilter, as many views per subset as ours
hold, the same relaxation and positivity), ``rtk_cg``
(ConjugateGradientConeBeamReconstructionFilter, unit weights) and
``rtk_tv`` (ADMMTotalVariationConeBeamReconstructionFilter, ``RTK_TV`` settings), all with the
same iterations and started from the same FDK volume. Each reconstruction runs in a fresh
process that warms up first; ``seconds`` is ours from the projections (FDK start and the
iterations' preparation included) and RTK's filter alone; ``seconds_per_iteration`` ours the
iterations' mean alone, RTK's its whole filter over the iterations. A ``speed`` row per
toolkit gives one SART iteration at 256^3 from 360 views of 512^2 (``--speed-only``: those
rows alone).

Prints one JSON object ``{"rows": [...]}``; see ``KEYS``. Usage:
``python bench/iterative.py [--quick] [--out DIR]`` (about an hour; ``--quick``: 3 mm voxels,
90 and 60 views, no speed rows, in about ten minutes).
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from measures import bone_dice, central_region, peak_resident_mb, ssim  # noqa: E402
from scan_inputs import read_scan, write_scan  # noqa: E402

from recon.geometry import DetectorSpec, Geometry, circular_orbit  # noqa: E402
from recon.volume import Volume, VolumeGrid  # noqa: E402

KEYS = (
    "case",
    "method",
    "views",
    "mas_fraction",
    "iterations",
    "rmse",
    "ssim",
    "bone_dice",
    "seconds",
    "seconds_per_iteration",
    "peak_mb",
)
FULL = {
    "voxel_mm": 2.0,  # the knee's field of view at 2 mm: 70 x 70 x 80 voxels
    "shepp_logan_size": 72,
    "panel": 160,
    "pitch_mm": 2.4,
    "scan_views": 360,
    "views": [360, 180, 90, 60],
    "mas_fractions": [1.0, 0.25],
    "photons_full": 2.0e4,  # unattenuated photons per pixel and view at full mAs
    "iterations": 4,
    "subsets": 30,
    "relaxation": 0.8,
    "speed": True,
}
QUICK = {
    **FULL,
    "voxel_mm": 3.0,
    "shepp_logan_size": 48,
    "panel": 96,
    "pitch_mm": 4.0,
    "views": [90, 60],
    "iterations": 3,
    "speed": False,
}
RTK_TV = {"alpha": 0.5, "beta": 200.0, "cg_iterations": 2}
"""ADMM-TV's TV weight (alpha), augmented-Lagrangian penalty (beta) and CG steps per
iteration."""
SPEED = {"size": 256, "voxel_mm": 0.5, "views": 360, "panel": 512, "pitch_mm": 0.8}
SID_MM, SDD_MM = 600.0, 1000.0
SHEPP_LOGAN_MU = 0.02
"""1/mm per unit of RTK's Shepp-Logan densities (its outer ellipsoid, 1, is water), so that
its photons attenuate like a leg's."""
OURS, RTK = ("fdk", "sart", "tv"), ("rtk_sart", "rtk_cg", "rtk_tv")


# -- worker: one reconstruction in its own process ---------------------------------------------


def worker(method: str, folder: Path, cfg: dict) -> None:
    """Reconstruct ``folder``'s projections with ``method``; print timing and peak memory."""
    from recon.fdk import fdk_reconstruct
    from recon.iterative import IterativeSettings, iterative_reconstruct

    projections, geometry, grid = read_scan(folder)
    tiny = VolumeGrid.centered((8, 8, 8), 4.0, grid.center_mm)
    iterations = cfg["iterations"]
    per_iteration = None
    if method in OURS:
        warm = fdk_reconstruct(
            projections[:8], geometry[:8], tiny, redundancy="none", min_coverage_deg=0
        )
        settings = IterativeSettings(
            "tv" if method == "fdk" else method,
            iterations=1,
            subsets=cfg["subsets"],
            relaxation=cfg["relaxation"],
        )
        iterative_reconstruct(
            projections[:8], geometry[:8], tiny, settings, start=warm, redundancy="none"
        )
        start = time.perf_counter()
        fdk = fdk_reconstruct(projections, geometry, grid)
        volume = fdk.volume.data
        if method != "fdk":
            settings = IterativeSettings(
                method,
                iterations=iterations,
                subsets=cfg["subsets"],
                relaxation=cfg["relaxation"],
                tolerance=0.0,
            )
            result = iterative_reconstruct(projections, geometry, grid, settings, start=fdk)
            volume = result.volume.data
            per_iteration = float(np.mean(result.seconds))
        seconds = time.perf_counter() - start
    else:
        from recon import rtk_peer

        start_volume = np.load(folder / "fdk.npy")
        run = {
            "rtk_sart": lambda p, g, v, n: rtk_peer.rtk_sart(
                p, g, v, n, math.ceil(len(p) / cfg["subsets"]), cfg["relaxation"]
            ),
            "rtk_cg": rtk_peer.rtk_cg,
            "rtk_tv": lambda p, g, v, n: rtk_peer.rtk_admm_tv(p, g, v, n, **RTK_TV),
        }[method]
        run(projections[:8], geometry[:8], Volume(np.zeros(tiny.shape, np.float32), tiny), 1)
        start = time.perf_counter()
        volume = run(projections, geometry, Volume(start_volume, grid), iterations)
        seconds = time.perf_counter() - start
        per_iteration = seconds / iterations
    np.save(folder / f"{method}.npy", volume)
    print(
        json.dumps(
            {
                "seconds": seconds,
                "seconds_per_iteration": per_iteration,
                "peak_mb": peak_resident_mb(),
            }
        )
    )


def run_worker(method: str, folder: Path, cfg: dict) -> dict:
    done = subprocess.run(
        [sys.executable, __file__, "--worker", method, str(folder), json.dumps(cfg)],
        capture_output=True,
        text=True,
        check=False,
    )
    if done.returncode:
        raise RuntimeError(f"{method} on {folder} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


# -- inputs -------------------------------------------------------------------------------------


def scan_views(cfg: dict, grid: VolumeGrid) -> Geometry:
    """The full scan's views (``scan_views``, a whole turn) about the grid's centre."""
    panel = DetectorSpec(rows=cfg["panel"], cols=cfg["panel"], pixel_pitch_mm=cfg["pitch_mm"])
    return circular_orbit(
        cfg["scan_views"], SID_MM, SDD_MM, panel, isocenter_mm=tuple(grid.center_mm)
    )


def knee_scan(cfg: dict, log) -> tuple[np.ndarray, Geometry, VolumeGrid, np.ndarray, np.ndarray]:
    """Noiseless line integrals of the knee phantom, its views, grid, attenuation and labels."""
    from recon.project import forward_project
    from sim.phantoms.knee import KneePhantomSpec, knee_grid, rasterize_knee

    spec = KneePhantomSpec()
    fine = knee_grid(spec, spacing_mm=cfg["voxel_mm"] / 2)
    grid = knee_grid(spec, spacing_mm=cfg["voxel_mm"])
    log(f"knee phantom: {fine.size_xyz} voxels projected, reconstructed on {grid.size_xyz}")
    _, mu = rasterize_knee(spec, fine, supersample=2)
    geometry = scan_views(cfg, grid)
    labels, truth = rasterize_knee(spec, grid, supersample=3)
    return forward_project(mu, fine, geometry), geometry, grid, truth, labels


def shepp_logan_scan(cfg: dict, log) -> tuple[np.ndarray, Geometry, VolumeGrid, np.ndarray]:
    from recon.rtk_peer import rtk_shepp_logan

    n = cfg["shepp_logan_size"]
    grid = VolumeGrid.centered((n, n, n), cfg["voxel_mm"], (0.0, 0.0, 0.0))
    geometry = scan_views(cfg, grid)
    log(f"RTK's analytic Shepp-Logan projections, {len(geometry)} views")
    projections, truth = rtk_shepp_logan(geometry, grid, 0.45 * n * cfg["voxel_mm"])
    return projections * SHEPP_LOGAN_MU, geometry, grid, truth * SHEPP_LOGAN_MU


def write_inputs(
    folder: Path, projections: np.ndarray, geometry: Geometry, grid: VolumeGrid
) -> None:
    """The scan's files (bench/scan_inputs.py) and the FDK volume every method starts from."""
    from recon.fdk import fdk_reconstruct

    write_scan(folder, projections, geometry, grid)
    np.save(folder / "fdk.npy", fdk_reconstruct(projections, geometry, grid).volume.data)


# -- measuring ------------------------------------------------------------------------------------


def measure_scan(
    case: str,
    folder: Path,
    views: int,
    fraction: float,
    truth: np.ndarray,
    region: np.ndarray,
    labels: np.ndarray | None,
    grid: VolumeGrid,
    cfg: dict,
    log,
) -> list[dict]:
    rows = []
    for method in OURS + RTK:
        log(f"{case}, {views} views, {fraction:g} mAs: {method}")
        run = run_worker(method, folder, cfg)
        volume = np.load(folder / f"{method}.npy")
        error = volume[region] - truth[region]
        rows.append(
            {
                "case": case,
                "method": method,
                "views": views,
                "mas_fraction": fraction,
                "iterations": 0 if method == "fdk" else cfg["iterations"],
                "rmse": float(np.sqrt(np.mean(error**2))),
                "ssim": ssim(volume, truth, region),
                "bone_dice": None
                if labels is None
                else bone_dice(Volume(volume, grid, "1/mm"), labels),
                "seconds": run["seconds"],
                "seconds_per_iteration": run["seconds_per_iteration"],
                "peak_mb": run["peak_mb"],
            }
        )
        log(f"  RMSE {rows[-1]['rmse']:.5f}, {run['seconds']:.1f} s")
    return rows


def measure_case(case: str, cfg: dict, root: Path, log) -> list[dict]:
    from sim.scan import add_noise

    if case == "knee":
        clean, geometry, grid, truth, labels = knee_scan(cfg, log)
        region = truth > 0.0
    else:
        clean, geometry, grid, truth = shepp_logan_scan(cfg, log)
        labels, region = None, central_region(truth.shape)
    rows = []
    for f_index, fraction in enumerate(cfg["mas_fractions"]):
        photons = cfg["photons_full"] * fraction
        _, noisy = add_noise(clean, photons, np.random.default_rng(100 + f_index))
        for views in cfg["views"]:
            every = cfg["scan_views"] // views
            subset = geometry[::every]
            folder = root / f"{case}-{views}-{fraction:g}"
            write_inputs(folder, noisy[::every], subset, grid)
            rows += measure_scan(
                case, folder, views, fraction, truth, region, labels, grid, cfg, log
            )
    return rows


def speed_rows(cfg: dict, root: Path, log) -> list[dict]:
    """One SART iteration each at 256^3 from 360 views of 512^2 (RTK's Shepp-Logan)."""
    size = {**cfg, **SPEED, "shepp_logan_size": SPEED["size"], "scan_views": SPEED["views"]}
    projections, geometry, grid, truth = shepp_logan_scan(size, log)
    folder = root / "speed"
    write_inputs(folder, projections, geometry, grid)
    one = {**cfg, "iterations": 1}
    rows = []
    for method in ("sart", "rtk_sart"):
        log(f"speed: one {method} iteration at {SPEED['size']}^3")
        run = run_worker(method, folder, one)
        volume = np.load(folder / f"{method}.npy")
        region = central_region(truth.shape)
        rows.append(
            {
                "case": "speed",
                "method": method,
                "views": SPEED["views"],
                "mas_fraction": None,
                "iterations": 1,
                "rmse": float(np.sqrt(np.mean((volume[region] - truth[region]) ** 2))),
                "ssim": None,
                "bone_dice": None,
                **run,
            }
        )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="48^3, 90 and 60 views")
    parser.add_argument("--out", type=Path, help="keep inputs and outputs here")
    parser.add_argument(
        "--speed-only", action="store_true", help="only the one-iteration rows at 256^3"
    )
    parser.add_argument("--worker", nargs=3, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        worker(args.worker[0], Path(args.worker[1]), json.loads(args.worker[2]))
        return
    cfg = QUICK if args.quick else FULL

    def log(msg: str) -> None:
        print(f"[bench/iterative] {msg}", file=sys.stderr, flush=True)

    started = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench-iterative-") as tmp:
        root = args.out or Path(tmp)
        rows = []
        if not args.speed_only:
            rows = measure_case("knee", cfg, root, log) + measure_case(
                "shepp_logan", cfg, root, log
            )
        if cfg["speed"]:
            rows += speed_rows(cfg, root, log)
    print(
        json.dumps(
            {
                "benchmark": "iterative",
                "config": {**cfg, "rtk_tv": RTK_TV},
                "minutes": (time.perf_counter() - started) / 60.0,
                "rows": rows,
            },
            indent=1,
        )
    )


if __name__ == "__main__":
    main()
