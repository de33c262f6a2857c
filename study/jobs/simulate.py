"""Scan a digital phantom into a new folder (``cbct simulate-scan``).

Everything read is validated before the long work starts; the folder must not exist yet, or
be empty.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np

from calibration.phantom import BBPhantomSpec
from recon.config import load_config, load_protocol
from recon.fdk import Progress
from recon.geometry import Geometry
from recon.io import write_projections, write_volume
from recon.motion import BodyMotion, write_motion_csv
from recon.rtk_xml import write_rtk_geometry
from recon.volume import Volume
from scanner.outputs import new_folder
from scanner.study_folder import sha256, software_version
from sim.phantoms.bb import project_bb
from sim.phantoms.knee import KneePhantomSpec
from sim.scan import add_noise, photons_per_pixel, simulate_knee_scan
from sim.sway import SwaySpec
from sim.vibration import VibrationSpec, vibrate

Status = Callable[[str], None]


def write_scan(
    folder: Path,
    projections: np.ndarray,
    counts: np.ndarray | None,
    planned: Geometry,
    manifest: dict,
    acquired: Geometry | None = None,
    volumes: dict[str, Volume] | None = None,
    times_s: np.ndarray | None = None,
    true_poses: dict[str, np.ndarray] | None = None,
) -> list[Path]:
    """Write a scan: projections (and raw counts) as .mha, the planned views as geometry.xml
    (what the scanner knows), the acquired views as true_geometry.xml when they differ
    (simulation ground truth), each view's time as view_times.csv, the swaying patient's true
    motion as true_motion.csv (recon.motion), phantom volumes, and scan.json with every
    file's sha256."""
    pitch = planned[0].pitch_u_mm
    written = [
        write_projections(folder / "projections.mha", projections, pitch),
        write_rtk_geometry(folder / "geometry.xml", planned),
    ]
    if acquired is not None and acquired != planned:
        written.append(write_rtk_geometry(folder / "true_geometry.xml", acquired))
    if counts is not None:
        written.append(write_projections(folder / "counts.mha", counts, pitch))
    if times_s is not None:
        rows = "".join(f"{i},{t:.6f}\n" for i, t in enumerate(times_s))
        (folder / "view_times.csv").write_text("view,time_s\n" + rows, encoding="utf-8")
        written.append(folder / "view_times.csv")
    if true_poses is not None:
        bodies = tuple(sorted(true_poses))
        motion = BodyMotion(bodies, np.stack([true_poses[b] for b in bodies], axis=1))
        written.append(write_motion_csv(folder / "true_motion.csv", motion))
    for name, volume in (volumes or {}).items():
        written.append(write_volume(folder / name, volume))
    manifest = dict(manifest, files={p.name: sha256(p) for p in written})
    (folder / "scan.json").write_text(json.dumps(manifest, indent=2), encoding="utf-8")
    return [*written, folder / "scan.json"]


def simulate_to_folder(
    protocol_path: Path,
    out: Path,
    phantom: str,
    phantom_path: Path,
    *,
    voxel_mm: float = 0.5,
    seed: int = 0,
    noise: bool = True,
    vibration: VibrationSpec | None = None,
    sway: SwaySpec | None = None,
    status: Status | None = None,
    progress: Progress | None = None,
) -> list[Path]:
    """Scan the knee or BB phantom with a protocol (optionally on vibrating arms, the knee's
    patient optionally swaying) into a new folder; ``progress(done, total)`` counts the
    knee's views projected."""
    protocol = load_protocol(protocol_path)
    if phantom not in ("knee", "bb"):
        raise ValueError(f"phantom must be 'knee' or 'bb', got {phantom!r}")
    spec = load_config(phantom_path, KneePhantomSpec if phantom == "knee" else BBPhantomSpec)
    if not voxel_mm > 0:
        raise ValueError(f"voxel_mm must be > 0, got {voxel_mm!r}")
    new_folder(out)
    planned = protocol.orbit.geometry(protocol.detector)
    acquired = vibrate(planned, vibration) if vibration is not None else planned
    manifest = {
        "software_version": software_version(),
        "protocol": protocol.model_dump(mode="json"),
        "phantom": {"kind": phantom, **spec.model_dump(mode="json")},
        "vibration": vibration.model_dump(mode="json") if vibration else None,
        "sway": sway.model_dump(mode="json") if sway else None,
        "seed": seed,
        "noise": noise,
    }
    if phantom == "knee":
        scan = simulate_knee_scan(
            protocol,
            spec,
            voxel_mm=voxel_mm,
            noise=noise,
            seed=seed,
            geometry=acquired,
            sway=sway,
            status=status,
            progress=progress,
        )
        manifest |= {"voxel_mm": voxel_mm, "photons_per_pixel": scan.photons_per_pixel}
        volumes = {"phantom.nii.gz": scan.attenuation, "labels.nii.gz": scan.labels}
        return write_scan(
            out,
            scan.projections,
            scan.counts,
            planned,
            manifest,
            acquired,
            volumes,
            scan.times_s,
            scan.true_poses,
        )
    if status is not None:
        status(f"projecting the steel-ball phantom into {len(planned)} views")
    line_integrals = project_bb(spec, acquired)
    counts = None
    if noise:
        photons = photons_per_pixel(protocol.exposure, protocol.detector, protocol.orbit.sdd_mm)
        counts, line_integrals = add_noise(line_integrals, photons, np.random.default_rng(seed))
        manifest["photons_per_pixel"] = photons
    return write_scan(out, line_integrals, counts, planned, manifest, acquired)
