"""Track bodies through a fluoroscopy sequence: in memory (:func:`track`), and from files
(:func:`register_files`, what ``cbct register`` runs).

Inputs are the bodies to track: the static scan's bones (attenuation volume and its labels)
and implant components (their CAD meshes, registration.implants), a component standing for the
bone it replaces; the frames (an RTK projection stack of line integrals, DICOM, or TIFF/PNG
images: registration.frames) and their view (RTK geometry XML: one view, or one identical view
per frame, the scanner holding still during fluoroscopy; or a JointTrack calibration); and,
optionally, the panel's distortion (calibration.distortion: the frames are dewarped before
anything else). Outputs go to a new folder: ``poses.csv`` (registration.poses), one JointTrack
``.jts`` per body (its poses in JointTrack's camera frame of the view: ``femur.jts``,
``tibia.jts``, ``patella.jts``), ``overlays/`` (every frame with each body's outline at its
registered pose), ``registration.json`` (per body and frame: NCC, gradient NCC, seconds,
evaluations, failure flag; the settings; the meshes read; the dewarp's fit),
``distortion.json`` (when dewarped) and, given the true (or reference) poses,
``metrics.json`` (registration.metrics.summarize and per-frame errors).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
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
from registration.autostart import candidate_poses
from registration.drr import SoftTissue, bone_models
from registration.frames import Frames, read_frames
from registration.implants import (
    ATTACHABLE,
    MATERIALS,
    ImplantModel,
    implant_model,
    read_mesh,
    size_range_mm,
)
from registration.jointtrack import camera_frame, read_calibration, read_jointtrack_poses
from registration.jointtrack import write_poses as write_jts
from registration.mayacam import is_mayacam, read_mayacam
from registration.metrics import as_rows, pose_error, summarize
from registration.objective import BodyModel
from registration.overlays import write_overlays
from registration.poses import BodyPose, poses_by_frame, read_poses, write_poses
from registration.results import FrameResult
from registration.settings import TRACK_ORDER, Settings
from registration.tracker import Tracker


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


BODY_NAMES = {
    "femur": "femur",
    "tibia": "tibia_fibula",
    "tibia_fibula": "tibia_fibula",
    "patella": "patella",
}
"""A body's name as given (``--implant tibia=...``) -> the tracker's
(registration.settings.TRACK_ORDER)."""
KNEE_REACH_MM = 120.0
"""How far from a placed component the next one's centre is searched (automatic start), mm."""
FILE_NAMES = {"femur": "femur", "tibia_fibula": "tibia", "patella": "patella"}
"""The tracker's name -> the body's name in file names (``tibia.jts``)."""


@dataclass(frozen=True)
class ImplantSpec:
    """An implant component to track: which body it stands for (femur, tibia or patella), its
    mesh file, the mesh's unit, its material (registration.implants) and the parts fixed to it
    (``attached``: each a mesh file in the component mesh's frame and unit, and its material
    from :data:`registration.implants.ATTACHABLE`: a tray's insert, the bone the component is
    fixed to), rendered with it."""

    body: str
    mesh: Path
    unit: str = "mm"
    material: str = "CoCr"
    attached: tuple[tuple[Path, str], ...] = ()


def body_name(name: str) -> str:
    """The tracker's name of a body given as femur, tibia (tibia_fibula) or patella."""
    if name not in BODY_NAMES:
        raise ValueError(f"body {name!r}: one of femur, tibia, patella")
    return BODY_NAMES[name]


def _poses_by_body(
    given: Path | dict[str, Path], bodies: tuple[str, ...], view: View, what: str
) -> dict[str, np.ndarray]:
    """Each body's poses (F, 4, 4), world: from one poses.csv, or per body from a poses.csv
    or a JointTrack .jts (in the view's camera frame: registration.jointtrack.camera_frame)."""
    if not isinstance(given, dict):
        frames, stacks = poses_by_frame(read_poses(given), bodies)
        if not np.array_equal(frames, np.arange(len(frames))):
            raise ValueError(f"{given}: {what} poses must number the frames from 0 on")
        return stacks
    stacks = {}
    for name, path in given.items():
        if name not in bodies:
            raise ValueError(f"{path}: {what} poses for {name!r}, which is not tracked")
        if Path(path).suffix.lower() == ".jts":
            stacks[name] = read_jointtrack_poses(path, view)
        else:
            _, found = poses_by_frame(read_poses(path), (name,))
            stacks[name] = found[name]
    lacking = [b for b in bodies if b not in stacks]
    if lacking:
        raise ValueError(f"no {what} poses for {', '.join(lacking)}")
    return stacks


def _initial(
    given: Path | dict[str, Path] | None,
    bodies: tuple[str, ...],
    view: View,
    first: int = 0,
) -> dict[str, np.ndarray]:
    """Starting poses of frame ``first``: the reference (CBCT or mesh) pose, or that frame's
    row of ``given``."""
    if given is None:
        return {name: np.eye(4) for name in bodies}
    stacks = _poses_by_body(given, bodies, view, "initial")
    for name, stack in stacks.items():
        if len(stack) <= first:
            raise ValueError(
                f"initial poses of {name} for {len(stack)} frames: none for frame {first}, "
                "the first one tracked"
            )
    return {name: stack[first] for name, stack in stacks.items()}


def _truth(
    given: Path | dict[str, Path], count: int, bodies: tuple[str, ...], view: View
) -> list[dict[str, np.ndarray]]:
    """True (or reference) poses of frames 0..count-1 (ValueError if one is missing)."""
    stacks = _poses_by_body(given, bodies, view, "true")
    for name, stack in stacks.items():
        if len(stack) < count:
            raise ValueError(f"true poses of {name} for {len(stack)} frames, not {count}")
    return [{b: stacks[b][k] for b in bodies} for k in range(count)]


def read_view(
    frames: Frames, geometry_path: Path | None = None, calibration_path: Path | None = None
) -> View:
    """The fluoroscopy view of ``frames``, from one of two files.

    Args:
        frames: The frames the view sees (registration.read_frames).
        geometry_path: An RTK geometry (:func:`fluoroscopy_view`), or None.
        calibration_path: A JointTrack calibration (its pixel size must be the frames') or an
            XMALab/Autoscoper MayaCam 2.0 (its image size must be the frames'), or None.
    """
    if (geometry_path is None) == (calibration_path is None):
        raise ValueError("give the fluoroscopy view as one of an RTK geometry or a calibration")
    if geometry_path is not None:
        return fluoroscopy_view(geometry_path, frames)
    rows, cols = frames.data.shape[1:]
    pitch = frames.pixel_pitch_mm[0]
    if is_mayacam(calibration_path):
        view = read_mayacam(calibration_path, pitch)
        if (view.rows, view.cols) != (rows, cols):
            raise ValueError(
                f"{calibration_path}: image size {view.rows} x {view.cols}, the frames' "
                f"({frames.header.source}) {rows} x {cols}"
            )
        return view
    view = read_calibration(calibration_path, rows, cols)
    if abs(pitch - view.pitch_u_mm) > 1e-6 * pitch:
        raise ValueError(
            f"{calibration_path}: pixel size {view.pitch_u_mm} mm, the frames' "
            f"({frames.header.source}) {pitch} mm"
        )
    return view


def _named_paths(what: str, given: Path | dict[str, Path] | None) -> dict[str, Path | None]:
    """One poses file, or one per body, each under a name for messages."""
    if isinstance(given, dict):
        return {f"{what} of {body}": path for body, path in given.items()}
    return {what: given}


def frame_numbers(count: int, frame_range: tuple[int, int, int] | None) -> np.ndarray:
    """The numbers of the frames tracked out of ``count``, or ValueError naming --frames-range.

    Args:
        count: Frames in the sequence.
        frame_range: (first, last, step), ``last`` included; every frame when ``None``.
    """
    if frame_range is None:
        return np.arange(count)
    first, last, step = frame_range
    if not (0 <= first <= last < count and step >= 1):
        raise ValueError(
            f"--frames-range {first}:{last}:{step}: the sequence has frames 0 to {count - 1}; "
            "give FIRST:LAST[:STEP] with 0 <= FIRST <= LAST <= "
            f"{count - 1} and STEP >= 1"
        )
    return np.arange(first, last + 1, step)


def register_files(
    volume_path: Path | None,
    labels_path: Path | None,
    frames_path: Path | list[str | Path],
    geometry_path: Path | None,
    out: Path,
    *,
    implants: tuple[ImplantSpec, ...] = (),
    calibration_path: Path | None = None,
    polarity: str = "dark",
    truth_path: Path | dict[str, Path] | None = None,
    initial_path: Path | dict[str, Path] | None = None,
    pixel_pitch_mm: float | None = None,
    distortion: Distortion | None = None,
    settings: Settings | None = None,
    progress: Callable[[int, int], None] | None = None,
    unit: StaticUnit | None = None,
    effective_energy_kev: float = DEFAULT_EFFECTIVE_ENERGY_KEV,
    frame_range: tuple[int, int, int] | None = None,
) -> list[FrameResult]:
    """``cbct register``: track every body through every frame and write the results.

    The bodies: the static scan's bones (a volume and its labels) and implant components
    (``implants``: their meshes), a component standing for the bone it replaces. The view: an
    RTK geometry (``geometry_path``) or a JointTrack calibration (``calibration_path``; its
    pixel size is the frames'). Every input is read and checked before the (long)
    registration starts; ``out`` must not exist and is written only at the end.
    ``distortion``: the panel's warp, the frames are dewarped with it first (ValueError if it
    belongs to a panel of another size). The static volume (a file or a DICOM CT series) may be
    in HU or 1/mm: ``unit`` where the file does not say, HU converted at
    ``effective_energy_kev`` (recon.static_volume). ``initial_path`` and ``truth_path``: one
    poses.csv, or per body a poses.csv or a JointTrack .jts.

    Args:
        volume_path: The static volume (a file or a DICOM CT series), or ``None``.
        labels_path: Its bone labels, or ``None`` (with ``volume_path``).
        frames_path: The frames: a stack, DICOM, images, a glob, or a list of image files.
        geometry_path: RTK geometry of the frames, or ``None`` with ``calibration_path``.
        out: Output folder; must not exist.
        implants: Implant components to track.
        calibration_path: JointTrack or MayaCam calibration, or ``None``.
        polarity: How attenuation shows in the frames: "dark" or "bright".
        truth_path: Reference poses, for the metrics; or ``None``.
        initial_path: Starting poses of the first frame; or ``None`` (automatic start).
        pixel_pitch_mm: Pixel size (mm) of frames whose files do not give one.
        distortion: The panel's warp, or ``None``.
        settings: Registration settings; the defaults when ``None``.
        progress: Called with (frames done, frames in all).
        unit: Unit of the static volume where its file does not say.
        effective_energy_kev: Effective energy (keV) converting HU to 1/mm.
        frame_range: (first, last, step) of the frames tracked, numbered from 0, ``last``
            included; every frame when ``None``. Poses keep the sequence's frame numbers.

    Returns:
        One result per frame.
    """
    if out.exists():
        raise FileExistsError(f"{out} exists: choose a new output folder")
    if (volume_path is None) != (labels_path is None):
        raise ValueError("a static scan needs both its volume and its labels")
    if volume_path is None and not implants:
        raise ValueError("nothing to track: give a static scan (volume and labels) or implants")
    given = {
        "static volume": volume_path,
        "labels": labels_path,
        "geometry": geometry_path,
        "calibration": calibration_path,
        **{f"{spec.body} mesh": spec.mesh for spec in implants},
        **_named_paths("true poses", truth_path),
        **_named_paths("initial poses", initial_path),
    }
    for what, path in given.items():
        if path is not None and not Path(path).exists():
            raise FileNotFoundError(f"{path}: no such file or folder ({what})")
    if calibration_path is not None and pixel_pitch_mm is None:
        if is_mayacam(calibration_path):
            raise ValueError(
                f"{calibration_path}: a MayaCam calibration does not give the panel's pixel "
                "pitch: give it (--pixel-pitch-mm)"
            )
        pixel_pitch_mm = read_calibration(calibration_path, 1, 1).pitch_u_mm
    frames = read_frames(frames_path, pixel_pitch_mm, polarity)
    numbers = frame_numbers(len(frames.data), frame_range)
    view = read_view(frames, geometry_path, calibration_path)
    if frame_range is not None:
        frames = replace(frames, data=frames.data[numbers])
    if distortion is not None:
        field = frames.field
        if field is not None:  # pixels the dewarped field fully covers
            field = distortion.undistort(field.astype(np.float32), view.pitch_u_mm) > 0.99
        data = distortion.undistort(frames.data, view.pitch_u_mm)
        frames = replace(frames, data=data, field=field)
    models, soft, source, meshes = {}, None, None, {}
    if volume_path is not None:
        volume, labels, source = load_inputs(volume_path, labels_path, unit, effective_energy_kev)
        models = bone_models(volume, labels)
        soft = SoftTissue.of(volume, labels)
    for spec in implants:
        name = body_name(spec.body)
        if spec.material not in MATERIALS:
            raise ValueError(f"{spec.mesh}: material {spec.material!r}; one of {sorted(MATERIALS)}")
        mesh, report = read_mesh(spec.mesh, spec.unit)
        attached = []
        for path, material in spec.attached:
            if material not in ATTACHABLE:
                raise ValueError(
                    f"{path}: material {material!r} of a part fixed to {spec.mesh.name}; one of "
                    f"{sorted(ATTACHABLE)}"
                )
            part = read_mesh(path, spec.unit, size_range_mm(material))[0]
            attached.append((part, ATTACHABLE[material]))
        models[name] = implant_model(name, mesh, MATERIALS[spec.material], attached=attached)
        meshes[name] = {**asdict(report), "material": spec.material}
        if spec.attached:
            meshes[name]["attached"] = [[str(path), m] for path, m in spec.attached]
    bodies = tuple(b for b in TRACK_ORDER if b in models)
    count = int(numbers[-1]) + 1
    truth = None if truth_path is None else _truth(truth_path, count, bodies, view)
    start = None  # implants alone: searched
    if initial_path is not None or not meshes or volume_path is not None:
        start = _initial(initial_path, bodies, view, int(numbers[0]))
    tracker, tracked = _tracked(frames, view, models, start, settings, soft, progress)
    results = [replace(r, frame=int(numbers[r.frame])) for r in tracked]  # the sequence's numbers
    _write(out, results, models, view, tracker, truth, distortion, source, frames, meshes)
    return results


def track(
    frames: Frames | np.ndarray,
    view: View,
    bodies: dict[str, BodyModel],
    *,
    start: dict[str, np.ndarray] | None = None,
    settings: Settings | None = None,
    soft_tissue: SoftTissue | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> list[FrameResult]:
    """Track bodies through fluoroscopy frames, in memory.

    Args:
        frames: The frames (:func:`registration.read_frames`), or their line integrals
            (frames, rows, cols).
        view: The fluoroscopy view (:func:`read_view`).
        bodies: The tracked bodies' models by name (registration.settings.TRACK_ORDER): a
            static scan's bones (registration.bone_models) or implant components
            (registration.implant_body), a component named by the bone it replaces.
        start: The first frame's poses, 4x4 (mm) by body; None: each bone where the static
            scan has it (the identity) and each component found in the first frame
            (registration.autostart).
        settings: Registration settings; the defaults when None.
        soft_tissue: The static scan's soft tissue (registration.drr.SoftTissue), scored
            with the bones; None leaves it out.
        progress: Called with (frames done, frames in all) after each frame.

    Returns:
        One result per frame, numbered from 0.
    """
    return _tracked(frames, view, bodies, start, settings, soft_tissue, progress)[1]


def _tracked(
    frames: Frames | np.ndarray,
    view: View,
    bodies: dict[str, BodyModel],
    start: dict[str, np.ndarray] | None,
    settings: Settings | None,
    soft_tissue: SoftTissue | None,
    progress: Callable[[int, int], None] | None,
) -> tuple[Tracker, list[FrameResult]]:
    """:func:`track`, and the tracker that tracked (its matched blurs)."""
    if isinstance(frames, Frames):
        data, field, where = frames.data, frames.field, f"{frames.header.source} with the view"
    else:
        data, field, where = np.asarray(frames, dtype=np.float32), None, "the frames with the view"
        if data.ndim != 3:
            raise ValueError(f"frames of shape {data.shape}: give a stack (frames, rows, cols)")
    tracker = Tracker(view, data, bodies, settings, soft_tissue, field)
    given = dict(start or {})
    for name in (b for b in bodies if b not in given and not isinstance(bodies[b], ImplantModel)):
        given[name] = np.eye(4)  # a bone where the static scan has it
    components = [b for b in bodies if b not in given]
    if components:
        given |= _automatic_start(tracker, bodies, components, view, data[0], field, given)
    _check_in_view(view, bodies, given, where)
    return tracker, tracker.track(given, progress=progress)


def _automatic_start(
    tracker: Tracker,
    models: dict[str, BodyModel],
    names: list[str],
    view: View,
    frame: np.ndarray,
    field: np.ndarray | None,
    placed: dict[str, np.ndarray],
) -> dict[str, np.ndarray]:
    """The components ``names``' starts on the first ``frame`` (registration.autostart),
    the largest first, each next one searched within :data:`KNEE_REACH_MM` of those placed
    (``placed``, then each found)."""
    start = dict(placed)
    for name in sorted(names, key=lambda b: -len(models[b].points_mm)):
        near = (_knee_centre(models, start), KNEE_REACH_MM) if start else None
        beside = [(models[b], T) for b, T in start.items()]
        found = candidate_poses(models[name], view, frame, field, near, beside)
        start[name] = tracker.best_start(0, name, found, start)
    return {name: start[name] for name in names}


def _knee_centre(models: dict, poses: dict[str, np.ndarray]) -> np.ndarray:
    """The mean of the bodies' centroids at ``poses`` (those given), world mm (3,)."""
    return np.mean([T[:3, :3] @ models[b].centroid_mm + T[:3, 3] for b, T in poses.items()], axis=0)


def _check_in_view(view: View, models: dict, start: dict, where: str) -> None:
    """ValueError unless the knee (the mean of the bones' centroids at their starting poses)
    projects onto the panel away from its corners (recon.fdk.CORNER_FRACTION): otherwise the
    frames' header (origin, spacing, direction) and the geometry do not belong together, or
    the view does not look at the knee (frames at Origin (0, 0) under a view written for a
    centred panel put the knee on pixel (0, 0))."""
    u, v = view.project(_knee_centre(models, start))[0]
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
    source: StaticSource | None,
    frames: Frames,
    meshes: dict[str, dict],
) -> None:
    out.mkdir(parents=True)
    if distortion is not None:
        distortion.write(out / "distortion.json")
    centroids = {name: model.centroid_mm for name, model in models.items()}
    poses = [
        BodyPose(r.frame, name, b.T_world_body, b.ncc, b.seconds, b.failed, b.reason)
        for r in results
        for name, b in r.bodies.items()
    ]
    write_poses(out / "poses.csv", poses, centroids)
    T_camera_world = np.linalg.inv(camera_frame(view))
    for name in models:  # JointTrack's poses, in its camera frame of the view
        stack = [T_camera_world @ r.bodies[name].T_world_body for r in results]
        write_jts(out / f"{FILE_NAMES[name]}.jts", stack)
    write_overlays(out / "overlays", frames.data, view, models, results)
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
        for name, b in r.bodies.items()
    ]
    report = {
        "static_volume": None if source is None else source.summary(),
        "implants": meshes,
        "fluoroscopy": {"source": frames.header.source, "values": frames.stand_in},
        "settings": tracker.settings.model_dump(),
        "frame_blur_mm": tracker.frame_blur_mm,
        "model_blur_mm": {
            name: body.blur_mm for name, body in tracker.bodies.items() if hasattr(body, "blur_mm")
        },
        "dewarp": None if distortion is None else distortion.summary(),
        "frames": per_frame,
    }
    (out / "registration.json").write_text(json.dumps(report, indent=1), encoding="utf-8")
    if truth is None:
        return
    errors = [
        pose_error(
            name, r.frame, b.T_world_body, truth[r.frame][name], models[name].points_mm, view
        )
        for r in results
        for name, b in r.bodies.items()
    ]
    warm = [sum(b.seconds for b in r.bodies.values()) for r in results[1:]]
    first = sum(b.seconds for b in results[0].bodies.values())
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
