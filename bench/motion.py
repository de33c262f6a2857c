"""Benchmark: a standing patient's sway, estimated from the projections and compensated.

Two phantoms: the demo knee (rasterised at 1 mm over 480 mm of leg, so the leg leaves the
reconstructed field as a real one does) and the grand-challenge knee replacement (its meshes
projected polychromatically, sim.tka_ct; left out where its data are missing). Each is scanned
through the demo protocol's two-pass
reverse spiral (180 views of 256 x 256 pixels of 2.4 mm, SID 600, SDD 1000 mm, quantum and
readout noise) over 18 s while the patient sways (sim.sway) by 0, 1, 2 and 4 mm peak at the
knee, per seed; the same scan of the still patient is the reference. Each scan is
reconstructed on the study pipeline's 140 x 140 x 320 mm box of 1 mm voxels plainly and
through the motion estimated from its own projections (registration.scan_motion).

Per scan (``rows``): RMSE against the phantom in the leg (the knee replacement's outside its
metal; still scan, moving scan, compensated),
``recovered`` = (moving - compensated) / (moving - still) (null at 0 mm), SSIM against the
phantom (still, compensated), the motion's error per view at the bone surface (mean over a
body's surface points of the distance between where the estimate and the truth put them;
median and 95th percentile over views and bodies; ``..._inplane`` the same across each view's
rays, what the view itself can see), ``refused`` (why the estimate would not run, e.g. metal
in the field: the compensated volume is then the moving one), the bones' mean Dice of the
segmentation of the still and the compensated volume, the seconds of the estimate and the
compensated FDK, and the peak resident memory. ``timing`` (``--timing``): one scan of 360
views of 512 x 512 pixels (1.2 mm; ``--timing-pixels 1024``: the clinical panel's 0.6 mm)
into 256^3 voxels with 2 mm of sway: seconds, peak memory, the motion's error. ``demo_tre``
(``--demos STILL SWAYING``): the tracking TRE of two ``cbct demo --quick`` studies, made with
``--sway-mm 0`` and with the default sway.

Usage: ``python bench/motion.py [--phantoms knee tka] [--sizes 0 1 2 4] [--seeds 1 2 3]
[--timing] [--timing-pixels 1024] [--demos STILL SWAYING]``; ``--small`` runs 90 views of
128 x 128 on 2 mm voxels to check the harness in a minute.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from measures import bone_dice, peak_resident_mb, ssim  # noqa: E402

from recon.config import load_protocol  # noqa: E402
from recon.fdk import fdk_reconstruct  # noqa: E402
from recon.geometry import Geometry  # noqa: E402
from recon.volume import Volume, VolumeGrid  # noqa: E402
from registration.labels import LABELS  # noqa: E402
from registration.scan_motion import (  # noqa: E402
    MotionSettings,
    estimate_motion,
    surface_errors_mm,
)
from registration.segment import segment_bones_with_metal  # noqa: E402
from sim.phantoms.knee import KneePhantomSpec, knee_grid, rasterize_knee  # noqa: E402
from sim.phantoms.tka import DEFAULT_DATA, TkaPhantomSpec  # noqa: E402
from sim.scan import add_noise, photons_per_pixel, simulate_knee_scan  # noqa: E402
from sim.sway import Sway, SwaySpec  # noqa: E402

LEG_MM = 480.0
SCAN_S = 18.0
BOX_MM = (140.0, 140.0, 320.0)
BOX_OFFSET_MM = (0.0, 0.0, 40.0)
BONES = ("femur", "tibia", "fibula", "patella")
SURFACE_LABELS = {
    "thigh": (LABELS["femur"], LABELS["patella"]),
    "shank": (LABELS["tibia"], LABELS["fibula"]),
}


def protocol(views: int, pixels: int):
    base = load_protocol(ROOT / "configs" / "protocols" / "demo_knee.yaml")
    width = base.detector.width_mm
    detector = base.detector.model_copy(
        update={"rows": pixels, "cols": pixels, "pixel_pitch_mm": width / pixels}
    )
    return base.model_copy(
        update={"detector": detector, "orbit": base.orbit.model_copy(update={"views": views})}
    )


def box(voxel_mm: float, isocenter) -> VolumeGrid:
    size = tuple(round(e / voxel_mm) for e in BOX_MM)
    return VolumeGrid.centered(size, voxel_mm, tuple(np.asarray(isocenter) + BOX_OFFSET_MM))


def surface(labels: np.ndarray, grid: VolumeGrid, values, count: int = 400) -> np.ndarray:
    from scipy import ndimage

    mask = np.isin(labels, values)
    edge = np.argwhere(mask & ~ndimage.binary_erosion(mask))
    edge = edge[np.linspace(0, len(edge) - 1, min(count, len(edge))).astype(int)]
    return grid.index_to_world(edge[:, ::-1].astype(float))


@dataclass
class Phantom:
    """One phantom on the bench: how it is scanned, and its truth on the bench's box.

    ``scan(sway_mm, seed)`` gives the projections, the views, their times and the bodies' true
    poses (None when still); ``region`` is where RMSE and SSIM are scored (with the FDK's mask);
    ``cap`` the attenuation SSIM is clipped at (the metal's would swamp its range); ``dice`` the
    bones' mean Dice of a volume's segmentation (None where it fails)."""

    name: str
    grid: VolumeGrid
    mu: np.ndarray
    labels: np.ndarray
    region: np.ndarray
    cap: float
    scan: Callable[[float, int], tuple[np.ndarray, Geometry, np.ndarray, dict | None]]
    dice: Callable[[Volume], float | None]


def knee_phantom(size: dict) -> Phantom:
    spec = KneePhantomSpec()
    prot = protocol(size["views"], size["pixels"])
    sim_grid = knee_grid(spec, spacing_mm=size["phantom_mm"], height_mm=LEG_MM, below_mm=LEG_MM / 2)
    grid = box(size["voxel_mm"], prot.orbit.isocenter_mm)
    labels, mu = rasterize_knee(spec, grid)

    def scan(sway_mm: float, seed: int):
        sway = SwaySpec(peak_mm=sway_mm, seed=seed)
        done = simulate_knee_scan(prot, spec, seed=seed, grid=sim_grid, sway=sway, scan_s=SCAN_S)
        return done.projections, done.geometry, done.times_s, done.true_poses

    return Phantom(
        "knee", grid, mu, labels, labels > 0, float(mu.max()), scan, lambda v: bone_dice(v, labels)
    )


def tka_phantom(size: dict) -> Phantom:
    """The grand-challenge knee replacement, polychromatic, every part with its body."""
    from sim.tka_ct import METAL_LABEL, tka_pivots, tka_scene, tka_subject, tka_truth

    scene = tka_scene(TkaPhantomSpec())
    prot = protocol(size["views"], size["pixels"])
    kv = prot.exposure.tube_kv
    geometry = prot.orbit.geometry(prot.detector)
    times = np.linspace(0.0, SCAN_S, len(geometry))
    grid = box(size["voxel_mm"], prot.orbit.isocenter_mm)
    truth = tka_truth(scene, grid, kv)
    region = (truth.labels != LABELS["air"]) & ~truth.metal_zone
    photons = photons_per_pixel(prot.exposure, prot.detector, prot.orbit.sdd_mm)

    def scan(sway_mm: float, seed: int):
        sway = Sway(SwaySpec(peak_mm=sway_mm, seed=seed), tka_pivots(scene), SCAN_S)
        subject = tka_subject(scene, kv, sway)
        clean = np.stack([subject(v, float(t)) for v, t in zip(geometry, times, strict=True)])
        noisy = add_noise(clean.astype(np.float32), photons, np.random.default_rng(seed))[1]
        return noisy, geometry, times, sway.poses(times) if sway_mm > 0 else None

    def segment(volume: Volume) -> Volume:
        return segment_bones_with_metal(volume, truth.metal_share > 0.5, METAL_LABEL)

    def dice(volume: Volume) -> float | None:
        return bone_dice(volume, truth.labels, segment, ~truth.metal_zone)

    cap = float(truth.mu[region].max())
    return Phantom("tka", grid, truth.mu, truth.labels, region, cap, scan, dice)


def run_case(phantom: Phantom, size: dict, sway_mm: float, seed: int, still_cache: dict) -> dict:
    grid, mu, labels = phantom.grid, phantom.mu, phantom.labels
    if seed not in still_cache:
        projections, geometry, _times, _poses = phantom.scan(0.0, seed)
        still_cache[seed] = fdk_reconstruct(projections, geometry, grid)
    plain = still_cache[seed]
    mask = plain.mask & phantom.region
    projections, geometry, times, true_poses = phantom.scan(sway_mm, seed)
    moving = fdk_reconstruct(projections, geometry, grid)
    started = time.perf_counter()
    estimate, refused, compensated = None, None, moving
    try:
        estimate = estimate_motion(
            projections,
            geometry,
            grid,
            times_s=times,
            settings=MotionSettings(voxel_mm=size["voxel_mm"]),
        )
    except ValueError as err:  # refused (metal in the field): the volume stays plain FDK's
        refused = str(err)
    else:
        compensated = fdk_reconstruct(projections, geometry, grid, motion=estimate.motion)
    seconds = time.perf_counter() - started

    def rmse(volume: np.ndarray) -> float:
        return float(np.sqrt(np.mean((volume - mu)[mask] ** 2)))

    def similarity(volume: np.ndarray) -> float:
        cap = phantom.cap
        return round(ssim(np.minimum(volume, cap), np.minimum(mu, cap), mask), 4)

    def median(values) -> float | None:
        return None if values is None else round(float(np.median(values)), 3)

    def p95(values) -> float | None:
        return None if values is None else round(float(np.percentile(values, 95)), 3)

    r_still, r_moving, r_comp = (rmse(v.volume.data) for v in (plain, moving, compensated))
    full = across = None
    if estimate is not None:
        truth = true_poses or {b: np.tile(np.eye(4), (len(geometry), 1, 1)) for b in SURFACE_LABELS}
        sources = np.asarray(geometry.sources_mm)
        points = {b: surface(labels, grid, SURFACE_LABELS[b]) for b in truth}
        full, across = surface_errors_mm(estimate.motion, points, truth, sources)
    return {
        "phantom": phantom.name,
        "sway_mm": sway_mm,
        "seed": seed,
        "rmse_still": round(r_still, 6),
        "rmse_moving": round(r_moving, 6),
        "rmse_compensated": round(r_comp, 6),
        "recovered": None if sway_mm == 0 else round((r_moving - r_comp) / (r_moving - r_still), 3),
        "ssim_still": similarity(plain.volume.data),
        "ssim_moving": similarity(moving.volume.data),
        "ssim_compensated": similarity(compensated.volume.data),
        "motion_error_mm_median": median(full),
        "motion_error_mm_p95": p95(full),
        "motion_error_inplane_mm_median": median(across),
        "motion_error_inplane_mm_p95": p95(across),
        "refused": refused,
        "estimated_peak_mm": estimate and {b: round(v, 2) for b, v in estimate.peak_mm.items()},
        "bodies": estimate and list(estimate.motion.bodies),
        "notes": estimate and list(estimate.notes),
        "reprojection_rms": estimate and estimate.reprojection_rms,
        "bone_dice_still": _round(phantom.dice(plain.volume)),
        "bone_dice_moving": _round(phantom.dice(moving.volume)),
        "bone_dice_compensated": _round(phantom.dice(compensated.volume)),
        "seconds": round(seconds, 1),
        "stage_seconds": estimate and estimate.seconds,
        "peak_mb": round(peak_resident_mb(), 1),
    }


def _round(value: float | None) -> float | None:
    return None if value is None else round(value, 4)


def timing(pixels: int = 512) -> dict:
    """360 views of ``pixels`` x ``pixels`` (the panel's width kept) into 256^3 (0.55 mm) with
    2 mm of sway: estimate + compensated FDK."""
    spec = KneePhantomSpec()
    prot = protocol(360, pixels)
    sim_grid = knee_grid(spec, spacing_mm=0.75, height_mm=LEG_MM, below_mm=LEG_MM / 2)
    scan = simulate_knee_scan(prot, spec, seed=0, grid=sim_grid, sway=SwaySpec(peak_mm=2.0))
    grid = VolumeGrid.centered(
        (256, 256, 256), 140.0 / 256, tuple(np.asarray(prot.orbit.isocenter_mm) + BOX_OFFSET_MM)
    )
    started = time.perf_counter()
    estimate = estimate_motion(scan.projections, scan.geometry, grid, times_s=scan.times_s)
    fdk_reconstruct(scan.projections, scan.geometry, grid, motion=estimate.motion)
    seconds = time.perf_counter() - started
    labels, _mu = rasterize_knee(spec, grid)
    points = {b: surface(labels, grid, SURFACE_LABELS[b]) for b in scan.true_poses}
    sources = np.asarray(scan.geometry.sources_mm)
    full, across = surface_errors_mm(estimate.motion, points, scan.true_poses, sources)
    return {
        "views": 360,
        "pixels": pixels,
        "voxels": 256,
        "seconds": round(seconds, 1),
        "motion_error_mm_median": round(float(np.median(full)), 3),
        "motion_error_inplane_mm_median": round(float(np.median(across)), 3),
        "stage_seconds": estimate.seconds,
        "peak_mb": round(peak_resident_mb(), 1),
    }


def demo_tre(still: Path, swaying: Path) -> dict:
    out = {}
    for name, folder in (("still", still), ("swaying", swaying)):
        manifest = json.loads((folder / "study.json").read_text(encoding="utf-8"))
        stages = manifest["stages"]
        out[name] = {
            "tre_mean_mm": stages["registration"].get("tre_mm"),
            "tre_median_mm": stages["registration"].get("tre_mm_median"),
            "sway_mm": manifest["config"]["demo"]["size"].get("sway_mm"),
            "recon_motion": stages["recon"].get("motion"),
        }
    return out


PHANTOMS: dict[str, Callable[[dict], Phantom]] = {"knee": knee_phantom, "tka": tka_phantom}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=float, nargs="*", default=[0.0, 1.0, 2.0, 4.0])
    parser.add_argument("--seeds", type=int, nargs="*", default=[1, 2, 3])
    parser.add_argument("--phantoms", nargs="*", choices=list(PHANTOMS), default=list(PHANTOMS))
    parser.add_argument("--small", action="store_true")
    parser.add_argument("--timing", action="store_true")
    parser.add_argument(
        "--timing-pixels", type=int, default=512, help="--timing's panel: 512, or 1024 (clinical)"
    )
    parser.add_argument("--demos", type=Path, nargs=2, metavar=("STILL", "SWAYING"))
    args = parser.parse_args()
    size = (
        {"views": 90, "pixels": 128, "voxel_mm": 2.0, "phantom_mm": 1.0}
        if args.small
        else {"views": 180, "pixels": 256, "voxel_mm": 1.0, "phantom_mm": 1.0}
    )
    rows = []
    for name in args.phantoms:
        if name == "tka" and not DEFAULT_DATA.is_dir():
            print(f"tka: no grand-challenge data at {DEFAULT_DATA}: left out", file=sys.stderr)
            continue
        phantom, cache = PHANTOMS[name](size), {}
        for seed in args.seeds:
            for sway_mm in args.sizes:
                rows.append(run_case(phantom, size, sway_mm, seed, cache))
                print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    report = {
        "meta": {"size": size, "cpu_count": __import__("os").cpu_count()},
        "rows": rows,
        "timing": timing(args.timing_pixels) if args.timing else None,
        "demo_tre": demo_tre(*args.demos) if args.demos else None,
    }
    print(json.dumps(report))


if __name__ == "__main__":
    main()
