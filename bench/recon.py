"""Benchmark: our weighted FDK against RTK's CPU FDK on the same projections and machine.

256^3 volume of 0.5 mm voxels from 360 views of 512 x 512 pixels (0.8 mm), SID 600 mm,
SDD 1000 mm, for three orbits about world z: ``circular`` (full turn), ``short`` (180 degrees
plus the fan plus 2 degrees, Parker weights in both toolkits) and ``helix`` (a two-pass
reverse spiral, 360 degrees per pass, +-100 mm of lift travel; RTK runs its plain FDK there).
Two inputs per orbit: RTK's analytic ray-ellipsoid Shepp-Logan projector (an independent
forward model) and our Joseph projector on the knee phantom rasterised at 0.4 mm.

Each toolkit's reconstructions run in a fresh process that loads its inputs from disk, warms up
(our kernels load from numba's cache; RTK has nothing to warm), then times the reconstruction
alone ``--repeats`` times (3): each case's seconds are the median of its runs (the runs are
listed beside it), so that a shared host's passing slow spell moves neither toolkit's figure;
the process's peak resident memory is reported as measured (it includes the interpreter and
the libraries). Both use a plain ramp (Ram-Lak) filter and both threads of this machine.

Then the consoles as a user runs them, start-up and file writing included: ``cbct recon``
against RTK's ``rtkfdk`` on RTK's Shepp-Logan, 240 views of 320 x 320 pixels (1 mm) on a circle
into 160^3 voxels of 1 mm (``CONSOLE``), each command timed twice in a fresh process.

Prints one JSON object ``{"cases": [...], "console": {...}}``; see ``KEYS`` for each case.

Usage: ``python bench/recon.py [--small] [--repeats N] [--out DIR]`` (``--small`` runs a 64^3
version in about a minute to check the harness).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from measures import central_region, peak_resident_mb, ssim  # noqa: E402
from scan_inputs import read_scan, write_scan  # noqa: E402

from recon.geometry import (  # noqa: E402
    DetectorSpec,
    Geometry,
    circular_orbit,
    helical_orbit,
    short_scan_arc_deg,
)
from recon.volume import VolumeGrid  # noqa: E402

KEYS = (
    "case",
    "input",
    "ours_s",
    "rtk_s",
    "speed_ratio",
    "ours_runs_s",
    "rtk_runs_s",
    "ours_rmse",
    "rtk_rmse",
    "ours_ssim",
    "rtk_ssim",
    "ours_peak_mb",
    "rtk_peak_mb",
    "max_abs_diff_vs_rtk",
)
FULL = {
    "size": 256,
    "voxel_mm": 0.5,
    "views": 360,
    "panel": 512,
    "pitch_mm": 0.8,
    "knee_voxel_mm": 0.4,
    "travel_mm": 200.0,
}
SMALL = {
    "size": 64,
    "voxel_mm": 2.0,
    "views": 90,
    "panel": 128,
    "pitch_mm": 3.2,
    "knee_voxel_mm": 1.0,
    "travel_mm": 200.0,
}
CONSOLE = {"views": 240, "panel": 320, "pitch_mm": 1.0, "size": 160, "voxel_mm": 1.0}
"""The console comparison's scan and grid (``--small``: :data:`CONSOLE_SMALL`)."""
CONSOLE_SMALL = {"views": 60, "panel": 80, "pitch_mm": 4.0, "size": 40, "voxel_mm": 4.0}
SID_MM, SDD_MM = 600.0, 1000.0


def orbits(cfg: dict, isocenter) -> dict[str, Geometry]:
    panel = DetectorSpec(rows=cfg["panel"], cols=cfg["panel"], pixel_pitch_mm=cfg["pitch_mm"])
    n = cfg["views"]
    arc = short_scan_arc_deg(SDD_MM, panel) + 2.0
    half = cfg["travel_mm"] / 2
    return {
        "circular": circular_orbit(n, SID_MM, SDD_MM, panel, isocenter_mm=isocenter),
        "short": circular_orbit(n, SID_MM, SDD_MM, panel, arc_deg=arc, isocenter_mm=isocenter),
        "helix": helical_orbit(
            n,
            SID_MM,
            SDD_MM,
            panel,
            arc_deg=360.0,
            z_start_mm=-half,
            z_end_mm=half,
            passes=2,
            isocenter_mm=isocenter,
        ),
    }


# -- worker: one reconstruction in its own process ---------------------------------------------


def worker(toolkit: str, folder: Path, case: str, repeats: int) -> None:
    """Reconstruct ``folder``'s projections with one toolkit ``repeats`` times; print each
    run's seconds and the peak memory."""
    from recon.fdk import fdk_reconstruct
    from recon.rtk_peer import rtk_fdk

    projections, geometry, grid = read_scan(folder)
    tiny = VolumeGrid.centered((8, 8, 8), 4.0, grid.center_mm)
    if toolkit == "ours":
        fdk_reconstruct(
            projections[:8], geometry[:8], tiny, redundancy="none", min_coverage_deg=0
        )  # loads the compiled kernels from numba's cache

        def reconstruct() -> np.ndarray:
            return fdk_reconstruct(projections, geometry, grid, window="ram-lak").volume.data
    else:
        rtk_fdk(projections[:8], geometry[:8], tiny)  # loads RTK's wrapped modules

        def reconstruct() -> np.ndarray:
            return rtk_fdk(projections, geometry, grid, parker=case == "short")

    seconds, volume = [], None
    for _ in range(repeats):
        volume = None  # the last run's volume is freed before the next is made
        start = time.perf_counter()
        volume = reconstruct()
        seconds.append(time.perf_counter() - start)
    np.save(folder / f"{toolkit}.npy", volume)
    print(json.dumps({"seconds": seconds, "peak_mb": peak_resident_mb()}))


def run_worker(toolkit: str, folder: Path, case: str, repeats: int) -> dict:
    done = subprocess.run(
        [sys.executable, __file__, "--worker", toolkit, str(folder), case, str(repeats)],
        capture_output=True,
        text=True,
        check=False,
    )
    if done.returncode:
        raise RuntimeError(f"{toolkit} on {folder} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


# -- inputs -------------------------------------------------------------------------------------


def write_inputs(
    folder: Path, projections: np.ndarray, geometry: Geometry, grid: VolumeGrid, truth: np.ndarray
) -> None:
    """The scan's files (bench/scan_inputs.py) and the truth to measure against."""
    write_scan(folder, projections, geometry, grid)
    np.save(folder / "truth.npy", truth)


def shepp_logan_inputs(cfg: dict, root: Path, log) -> list[tuple[str, str, Path]]:
    from recon.rtk_peer import rtk_shepp_logan

    grid = VolumeGrid.centered((cfg["size"],) * 3, cfg["voxel_mm"], (0.0, 0.0, 0.0))
    scale = 0.45 * cfg["size"] * cfg["voxel_mm"]  # outer ellipsoid fills ~90 % of the cube
    out = []
    for case, geometry in orbits(cfg, (0.0, 0.0, 0.0)).items():
        log(f"RTK analytic Shepp-Logan projections, {case}")
        projections, truth = rtk_shepp_logan(geometry, grid, scale)
        folder = root / f"shepp_logan-{case}"
        write_inputs(folder, projections, geometry, grid, truth)
        out.append((case, "shepp_logan", folder))
    return out


def knee_inputs(cfg: dict, root: Path, log) -> list[tuple[str, str, Path]]:
    from recon.project import forward_project
    from sim.phantoms.knee import KneePhantomSpec, knee_grid, rasterize_knee

    spec = KneePhantomSpec()
    fine = knee_grid(spec, spacing_mm=cfg["knee_voxel_mm"])
    log(f"rasterising the knee phantom on {fine.size_xyz} voxels")
    _, mu = rasterize_knee(spec, fine, supersample=2)
    grid = VolumeGrid.centered((cfg["size"],) * 3, cfg["voxel_mm"], fine.center_mm)
    _, truth = rasterize_knee(spec, grid, supersample=3)
    out = []
    for case, geometry in orbits(cfg, tuple(fine.center_mm)).items():
        log(f"our Joseph projections of the knee, {case}")
        folder = root / f"knee-{case}"
        write_inputs(folder, forward_project(mu, fine, geometry), geometry, grid, truth)
        out.append((case, "knee", folder))
    return out


# -- metrics ------------------------------------------------------------------------------------
def axial_drop(volume: np.ndarray, truth: np.ndarray, slab: int) -> float:
    """Relative loss of the mean value near the object's ends in z against its middle:
    1 - (recon/truth in the end slabs) / (recon/truth mid-object).

    Means run over the object's interior (non-zero truth eroded by 3 voxels, so partial volume
    at its surface stays out) within the central cylinder; the object's z extent is where that
    interior holds at least a quarter of its largest slice, and the end slabs are its first
    and last ``slab`` slices.
    """
    from scipy.ndimage import binary_erosion

    interior = binary_erosion(truth > 0, iterations=3) & central_region(truth.shape)
    counts = interior.sum(axis=(1, 2))
    body = np.flatnonzero(counts >= 0.25 * counts.max())
    first, last = int(body[0]), int(body[-1])

    def ratio(zs: slice) -> float:
        return float(volume[zs][interior[zs]].mean() / truth[zs][interior[zs]].mean())

    mid = (first + last) // 2
    middle = ratio(slice(mid - slab // 2, mid + slab // 2 + 1))
    ends = 0.5 * (ratio(slice(first, first + slab)) + ratio(slice(last + 1 - slab, last + 1)))
    return 1.0 - ends / middle


def measure(case: str, kind: str, folder: Path, repeats: int, log) -> dict:
    log(f"reconstructing {kind} / {case}: ours x {repeats}")
    ours_run = run_worker("ours", folder, case, repeats)
    log(f"reconstructing {kind} / {case}: RTK x {repeats}")
    rtk_run = run_worker("rtk", folder, case, repeats)
    ours_s, rtk_s = (float(np.median(run["seconds"])) for run in (ours_run, rtk_run))
    truth = np.load(folder / "truth.npy")
    ours, theirs = np.load(folder / "ours.npy"), np.load(folder / "rtk.npy")
    region = central_region(truth.shape)
    entry = {
        "case": case,
        "input": kind,
        "ours_s": round(ours_s, 2),
        "rtk_s": round(rtk_s, 2),
        "speed_ratio": round(rtk_s / ours_s, 3),
        "ours_runs_s": [round(t, 2) for t in ours_run["seconds"]],
        "rtk_runs_s": [round(t, 2) for t in rtk_run["seconds"]],
        "ours_rmse": float(np.sqrt(np.mean((ours - truth)[region] ** 2))),
        "rtk_rmse": float(np.sqrt(np.mean((theirs - truth)[region] ** 2))),
        "ours_ssim": round(ssim(ours, truth, region), 4),
        "rtk_ssim": round(ssim(theirs, truth, region), 4),
        "ours_peak_mb": round(ours_run["peak_mb"], 1),
        "rtk_peak_mb": round(rtk_run["peak_mb"], 1),
        "max_abs_diff_vs_rtk": float(np.abs(ours - theirs)[region].max()),
    }
    if case == "helix":
        slab = max(2, truth.shape[0] // 32)
        entry["ours_axial_drop"] = round(axial_drop(ours, truth, slab), 4)
        entry["rtk_axial_drop"] = round(axial_drop(theirs, truth, slab), 4)
    return entry


def console(cfg: dict, root: Path, log) -> dict:
    """``cbct recon`` and ``rtkfdk`` on the same files, each run twice as a user runs it (a
    fresh process: start-up, reading, reconstruction and writing), wall seconds."""
    from recon.rtk_peer import rtk_shepp_logan

    panel = DetectorSpec(rows=cfg["panel"], cols=cfg["panel"], pixel_pitch_mm=cfg["pitch_mm"])
    geometry = circular_orbit(cfg["views"], SID_MM, SDD_MM, panel)
    grid = VolumeGrid.centered((cfg["size"],) * 3, cfg["voxel_mm"], (0.0, 0.0, 0.0))
    folder = root / "console"
    log(f"RTK analytic Shepp-Logan projections for the consoles: {cfg['views']} views")
    write_scan(
        folder,
        rtk_shepp_logan(geometry, grid, 0.45 * cfg["size"] * cfg["voxel_mm"])[0],
        geometry,
        grid,
    )
    size, voxel = [str(cfg["size"])] * 3, str(cfg["voxel_mm"])
    bin_dir = Path(sys.executable).parent
    commands = {
        "ours": [
            str(bin_dir / "cbct"),
            "recon",
            "--projections",
            str(folder / "projections.mha"),
            "--geometry",
            str(folder / "geometry.xml"),
            "--out",
            "OUT.nii.gz",
            "--size",
            *size,
            "--spacing-mm",
            voxel,
        ],
        "rtk": [
            str(bin_dir / "rtkfdk"),
            "-g",
            str(folder / "geometry.xml"),
            "--path",
            str(folder),
            "--regexp",
            "projections.mha",
            "--nodisplaced",  # a centred panel (its FOV step rejects the panel rotation we write)
            "-o",
            "OUT.mha",
            "--dimension",
            ",".join(size),
            "--spacing",
            ",".join([voxel] * 3),
        ],
    }
    seconds: dict[str, list[float]] = {}
    for run in range(2):
        for name, command in commands.items():
            log(f"console {name}, run {run + 1}")
            out = folder / f"{name}-{run}"
            argv = [a.replace("OUT", str(out)) for a in command]
            start = time.perf_counter()
            subprocess.run(argv, check=True, capture_output=True)
            seconds.setdefault(name, []).append(round(time.perf_counter() - start, 2))
    return {
        **cfg,
        "ours_s": seconds["ours"],
        "rtk_s": seconds["rtk"],
        "speed_ratio": round(min(seconds["rtk"]) / min(seconds["ours"]), 2),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--small", action="store_true", help="64^3 harness check")
    parser.add_argument("--out", type=Path, help="keep inputs and outputs here")
    parser.add_argument(
        "--repeats",
        type=int,
        default=3,
        help="timed runs per toolkit and case, the median reported (default 3)",
    )
    parser.add_argument(
        "--worker",
        nargs=4,
        metavar=("TOOLKIT", "FOLDER", "CASE", "REPEATS"),
        help=argparse.SUPPRESS,
    )
    args = parser.parse_args()
    if args.worker:
        worker(args.worker[0], Path(args.worker[1]), args.worker[2], int(args.worker[3]))
        return
    if args.repeats < 1:
        parser.error(f"--repeats {args.repeats}: at least 1")
    cfg = SMALL if args.small else FULL

    def log(msg: str) -> None:
        print(f"[bench/recon] {msg}", file=sys.stderr, flush=True)

    with tempfile.TemporaryDirectory(prefix="bench-recon-") as tmp:
        root = args.out or Path(tmp)
        jobs = shepp_logan_inputs(cfg, root, log) + knee_inputs(cfg, root, log)
        cases = [measure(case, kind, folder, args.repeats, log) for case, kind, folder in jobs]
        consoles = console(CONSOLE_SMALL if args.small else CONSOLE, root, log)
    result = {
        "benchmark": "recon",
        "config": cfg,
        "repeats": args.repeats,
        "cases": cases,
        "console": consoles,
    }
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
