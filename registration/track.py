"""Register a fluoroscopy sequence from files: what ``cbct register`` runs.

Inputs are the static scan (attenuation volume and its bone labels), the frames (an RTK
projection stack of line integrals, or DICOM) and their view (RTK geometry XML: one view, or
one identical view per frame; the scanner holds still during fluoroscopy) and, optionally, the
panel's distortion (calibration.distortion: the frames are dewarped before anything else).
Outputs go to a new folder: ``poses.csv`` (registration.poses), ``registration.json`` (per bone
and frame: NCC, gradient NCC, seconds, evaluations, failure flag; the settings; the dewarp's
fit), ``distortion.json`` (when dewarped) and, given the true poses, ``metrics.json``
(registration.metrics.summarize and per-frame errors).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np

from recon.attenuation import DEFAULT_EFFECTIVE_ENERGY_KEV
from recon.distortion import Distortion
from recon.fdk import CORNER_FRACTION
from recon.geometry import View
from recon.io import read_volume
from recon.rtk_xml import read_rtk_geometry
from recon.static_volume import StaticSource, StaticUnit, read_attenuation
from recon.volume import Volume
from registration.boneaxis import TRACK_ORDER, FrameResult, Settings, Tracker
from registration.drr import SoftTissue, bone_models
from registration.frames import Frames, read_frames
from registration.metrics import as_rows, pose_error, summarize
from registration.poses import BonePose, poses_by_frame, read_poses, write_poses


def fluoroscopy_view(geometry_path: Path, frames: Frames, any_count: bool = False) -> View:
    """The one view of a fluoroscopy sequence (ValueError if its views differ, or unless
    ``any_count``, if there are neither one nor one per frame)."""
    count = len(frames.data)
    pitch_u, pitch_v = frames.pixel_pitch_mm
    if abs(pitch_u - pitch_v) > 1e-6 * pitch_u:
        raise ValueError(
            f"{frames.header.source}: pixels must be square for registration, got Spacing "
            f"{pitch_u} x {pitch_v} mm"
        )
    geometry = read_rtk_geometry(geometry_path, frames.header)
    if len(geometry) not in (1, count) and not any_count:
        raise ValueError(
            f"{geometry_path}: {len(geometry)} views for {count} frames; give one view or one "
            "per frame"
        )
    view = geometry[0]
    moved = [k for k, other in enumerate(geometry) if not other.isclose(view)]
    if moved:
        raise ValueError(
            f"{geometry_path}: view {moved[0]} differs from view 0; the fluoroscopy view must "
            "be static"
        )
    return view


def _initial(path: Path | None) -> dict[str, np.ndarray]:
    """Frame-0 starting poses: the reference (CBCT) pose, or frame 0 of ``path``."""
    if path is None:
        return {name: np.eye(4) for name in TRACK_ORDER}
    _, stacks = poses_by_frame(read_poses(path), TRACK_ORDER)
    return {name: stack[0] for name, stack in stacks.items()}


def _truth(path: Path, count: int) -> list[dict[str, np.ndarray]]:
    """True poses of frames 0..count-1 (ValueError if a frame is missing)."""
    frames, stacks = poses_by_frame(read_poses(path), TRACK_ORDER)
    lacking = sorted(set(range(count)) - set(frames.tolist()))
    if lacking:
        raise ValueError(f"{path}: no true poses for frame {lacking[0]}")
    index = {int(f): i for i, f in enumerate(frames)}
    return [{b: stacks[b][index[k]] for b in TRACK_ORDER} for k in range(count)]


def register_files(
    volume_path: Path,
    labels_path: Path,
    frames_path: Path,
    geometry_path: Path,
    out: Path,
    *,
    truth_path: Path | None = None,
    initial_path: Path | None = None,
    pixel_pitch_mm: float | None = None,
    distortion: Distortion | None = None,
    settings: Settings | None = None,
    progress: Callable[[int, int], None] | None = None,
    unit: StaticUnit | None = None,
    effective_energy_kev: float = DEFAULT_EFFECTIVE_ENERGY_KEV,
) -> list[FrameResult]:
    """``cbct register``: track every bone through every frame and write the results.

    Every input is read and checked before the (long) registration starts; ``out`` must not
    exist and is written only at the end. ``distortion``: the panel's warp, the frames are
    dewarped with it first (ValueError if it belongs to a panel of another size). The static
    volume (a file or a DICOM CT series) may be in HU or 1/mm: ``unit`` where the file does
    not say, HU converted at ``effective_energy_kev`` (recon.static_volume).
    """
    if out.exists():
        raise FileExistsError(f"{out} exists: choose a new output folder")
    volume, labels, source = load_inputs(volume_path, labels_path, unit, effective_energy_kev)
    frames = read_frames(frames_path, pixel_pitch_mm)
    view = fluoroscopy_view(geometry_path, frames)
    if distortion is not None:
        field = frames.field
        if field is not None:  # pixels the dewarped field fully covers
            field = distortion.undistort(field.astype(np.float32), view.pitch_u_mm) > 0.99
        data = distortion.undistort(frames.data, view.pitch_u_mm)
        frames = replace(frames, data=data, field=field)
    truth = None if truth_path is None else _truth(truth_path, len(frames.data))
    start = _initial(initial_path)
    models = bone_models(volume, labels)
    _check_in_view(view, models, start, f"{frames.header.source} with {geometry_path}")
    soft = SoftTissue.of(volume, labels)
    tracker = Tracker(view, frames.data, models, settings, soft, frames.field)
    results = tracker.track(start, progress=progress)
    _write(out, results, models, view, tracker, truth, distortion, source, frames)
    return results


def _check_in_view(view: View, models: dict, start: dict, where: str) -> None:
    """ValueError unless the knee (the mean of the bones' centroids at their starting poses)
    projects onto the panel away from its corners (recon.fdk.CORNER_FRACTION): otherwise the
    frames' header (origin, spacing, direction) and the geometry do not belong together, or
    the view does not look at the knee (frames at Origin (0, 0) under a view written for a
    centred panel put the knee on pixel (0, 0))."""
    centroids = [T[:3, :3] @ models[b].centroid_mm + T[:3, 3] for b, T in start.items()]
    u, v = view.project(np.mean(centroids, axis=0))[0]
    on = -0.5 <= u <= view.cols - 0.5 and -0.5 <= v <= view.rows - 0.5
    near_u = min(u, view.cols - 1 - u) < CORNER_FRACTION * view.cols
    near_v = min(v, view.rows - 1 - v) < CORNER_FRACTION * view.rows
    if not on or (near_u and near_v):
        raise ValueError(
            f"{where}: the knee of the static scan projects at pixel ({u:.0f}, {v:.0f}), "
            f"{'in a corner of' if on else 'off'} the {view.cols} x {view.rows} panel: do the "
            "frames' header (Origin, Spacing, Direction) and the geometry belong together, and "
            "does the view look at the knee?"
        )


def _write(
    out,
    results,
    models,
    view,
    tracker: Tracker,
    truth,
    distortion,
    source: StaticSource,
    frames: Frames,
) -> None:
    out.mkdir(parents=True)
    if distortion is not None:
        distortion.write(out / "distortion.json")
    centroids = {name: model.centroid_mm for name, model in models.items()}
    poses = [
        BonePose(r.frame, name, b.pose, b.ncc, b.seconds)
        for r in results
        for name, b in r.bones.items()
    ]
    write_poses(out / "poses.csv", poses, centroids)
    per_frame = [
        {
            "frame": r.frame,
            "bone": name,
            "ncc": b.ncc,
            "gradient_ncc": b.gradient_ncc,
            "seconds": b.seconds,
            "evaluations": b.evaluations,
            "failed": b.failed,
        }
        for r in results
        for name, b in r.bones.items()
    ]
    report = {
        "static_volume": source.summary(),
        "fluoroscopy": {"source": frames.header.source, "values": frames.stand_in},
        "settings": tracker.settings.model_dump(),
        "frame_blur_mm": tracker.frame_blur_mm,
        "dewarp": None if distortion is None else distortion.summary(),
        "frames": per_frame,
    }
    (out / "registration.json").write_text(json.dumps(report, indent=1), encoding="utf-8")
    if truth is None:
        return
    errors = [
        pose_error(name, r.frame, b.pose, truth[r.frame][name], models[name].points_mm, view)
        for r in results
        for name, b in r.bones.items()
    ]
    warm = [sum(b.seconds for b in r.bones.values()) for r in results[1:]]
    first = sum(b.seconds for b in results[0].bones.values())
    metrics = summarize(errors, warm, first) | {"per_frame": as_rows(errors)}
    (out / "metrics.json").write_text(json.dumps(metrics, indent=1), encoding="utf-8")


def load_inputs(
    volume_path: Path,
    labels_path: Path,
    unit: StaticUnit | None = None,
    effective_energy_kev: float = DEFAULT_EFFECTIVE_ENERGY_KEV,
) -> tuple[Volume, Volume, StaticSource]:
    """The static scan as attenuation (1/mm; recon.static_volume.read_attenuation) and its
    labels, checked to share one grid, and where the attenuation's unit came from."""
    volume, source = read_attenuation(volume_path, unit, effective_energy_kev)
    labels = read_volume(labels_path, unit="label")
    if labels.grid != volume.grid:
        raise ValueError(
            f"{labels_path}: label grid {labels.grid} does not match the volume's {volume.grid}"
        )
    return volume, labels, source
