"""``cbct register``: track bodies through a fluoroscopy sequence from files, and write what was
found (registration.tracking.track does the tracking).

Inputs are the bodies to track: the static scan's bones (attenuation volume and its labels) and
implant components (their CAD meshes, registration.implants), each playing the role of the bone
it replaces (registration.roles); the frames (an RTK projection stack of line integrals, DICOM,
or TIFF/PNG images: registration.frames) and their view (RTK geometry XML: one view, or one
identical view per frame, the scanner holding still during fluoroscopy; or a JointTrack
calibration); and, optionally, the panel's distortion (calibration.dewarp_grid: the frames are
dewarped before anything else). Outputs go to a new folder: ``poses.csv`` (registration.poses),
one JointTrack ``.jts`` per body, named by its role (its poses in JointTrack's camera frame of
the view: ``femur.jts``, ``tibia.jts``, ``patella.jts``), ``overlays/`` (every frame with each
body's outline at its registered pose), ``registration.json`` (per body and frame: NCC, gradient
NCC, seconds, evaluations, failure flag; the settings; the meshes read; the dewarp's fit),
``distortion.json`` (when dewarped), one Autoscoper ``.tra`` per body (its world poses; NaN
where the registration failed) and, given the true (or reference) poses, ``metrics.json``
(registration.metrics.summarize and per-frame errors, depth along the first camera's rays).

Several cameras (biplane and more) each give their frames and their view, in one world (RTK
geometries, XMALab/Autoscoper MayaCam calibrations made on one object, or JointTrack
calibrations each with its camera's pose in that world); frames are paired by
index and every body's pose is scored on all of them (registration.views). Their ``.jts`` files
and overlays go to ``view<K>/`` per camera K (from 1), each in that camera's JointTrack frame;
``overlays/`` holds every camera's side by side (what ``cbct assess`` plays); given ``.jts``
files (initial or true poses) are in the first camera's.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from assessment.handoff import write_tra
from recon.attenuation import DEFAULT_EFFECTIVE_ENERGY_KEV
from recon.distortion import Distortion
from recon.geometry import View
from recon.io import read_volume
from recon.static_volume import StaticSource, StaticUnit, read_attenuation
from recon.volume import Volume
from registration.drr import SoftTissue, bone_models
from registration.frames import Frames, read_frames
from registration.implants import implant_model
from registration.jointtrack import (
    camera_frame,
    read_calibration,
    read_camera_pose,
    read_jointtrack_poses,
)
from registration.jointtrack import write_poses as write_jts
from registration.mayacam import is_mayacam, nominal_pitch_mm
from registration.meshes import ATTACHABLE, MATERIALS, read_mesh, size_range_mm
from registration.metrics import as_rows, pose_error, summarize
from registration.overlays import write_overlays, write_side_by_side
from registration.poses import BodyPose, poses_by_frame, read_poses, write_poses
from registration.results import FrameResult
from registration.roles import (
    COMPONENT_NAMES,
    KNOWN_ROLES,
    Role,
    body_playing,
    first_playing,
    roles_of,
    tracking_order,
)
from registration.settings import Settings
from registration.tracker import Tracker
from registration.tracking import read_view, tracked


@dataclass(frozen=True)
class ImplantSpec:
    """An implant component to track: the role it plays (``body``: femur, tibia or patella;
    it is tracked as registration.roles.COMPONENT_NAMES names it), its mesh file, the mesh's
    unit, its material (registration.implants) and the parts fixed to it (``attached``: each a
    mesh file in the component mesh's frame and unit, and its material from
    :data:`registration.meshes.ATTACHABLE`: a tray's insert, the bone the component is
    fixed to), rendered with it."""

    body: str
    mesh: Path
    unit: str = "mm"
    material: str = "CoCr"
    attached: tuple[tuple[Path, str], ...] = ()


def body_role(word: str) -> Role:
    """The role of a body given by name on the command line: femur, tibia (or tibia_fibula),
    patella, or a component's name (registration.roles.KNOWN_ROLES); ValueError otherwise."""
    role = KNOWN_ROLES.get(word)
    if role is None:
        raise ValueError(f"body {word!r}: one of femur, tibia, patella")
    return role


def _tracked(word: str, roles: dict[str, Role]) -> str | None:
    """The tracked body a name stands for: itself when tracked, else the body playing its role
    (``tibia`` for the tracked ``tibia_fibula`` or ``tibial_tray``), else None."""
    if word in roles:
        return word
    role = KNOWN_ROLES.get(word)
    return None if role is None else body_playing(role, roles)


def _file_rows(poses: list[BodyPose], roles: dict[str, Role]) -> list[BodyPose]:
    """The rows of a poses.csv for the tracked bodies: each body's own, else those of the
    first name of its role the file has (registration.roles.KNOWN_ROLES's order: an older
    run's ``tibia_fibula`` rows for the tracked ``tibial_tray``)."""
    named = {p.body for p in poses}
    source = {}
    for body, role in roles.items():
        source[body if body in named else first_playing(role, named) or body] = body
    return [replace(p, body=source[p.body]) for p in poses if p.body in source]


def _poses_by_body(
    given: Path | dict[str, Path], roles: dict[str, Role], view: View, what: str
) -> dict[str, np.ndarray]:
    """Each tracked body's poses (F, 4, 4), world: from one poses.csv, or per body (by its
    name or its role) from a poses.csv or a JointTrack .jts (in the view's camera frame:
    registration.jointtrack.camera_frame). A poses.csv row names its body or a body of the
    same role (an implant component written under its bone's name)."""
    bodies = tuple(roles)
    if not isinstance(given, dict):
        frames, stacks = poses_by_frame(_file_rows(read_poses(given), roles), bodies)
        if not np.array_equal(frames, np.arange(len(frames))):
            raise ValueError(f"{given}: {what} poses must number the frames from 0 on")
        return stacks
    stacks = {}
    for word, path in given.items():
        name = _tracked(word, roles)
        if name is None:
            raise ValueError(f"{path}: {what} poses for {word!r}, which is not tracked")
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
    roles: dict[str, Role],
    view: View,
    first: int = 0,
) -> dict[str, np.ndarray]:
    """Starting poses of frame ``first``: the reference (CBCT or mesh) pose, or that frame's
    row of ``given``."""
    if given is None:
        return {name: np.eye(4) for name in roles}
    stacks = _poses_by_body(given, roles, view, "initial")
    for name, stack in stacks.items():
        if len(stack) <= first:
            raise ValueError(
                f"initial poses of {name} for {len(stack)} frames: none for frame {first}, "
                "the first one tracked"
            )
    return {name: stack[first] for name, stack in stacks.items()}


def _truth(
    given: Path | dict[str, Path], count: int, roles: dict[str, Role], view: View
) -> list[dict[str, np.ndarray]]:
    """True (or reference) poses of frames 0..count-1 (ValueError if one is missing)."""
    stacks = _poses_by_body(given, roles, view, "true")
    for name, stack in stacks.items():
        if len(stack) < count:
            raise ValueError(f"true poses of {name} for {len(stack)} frames, not {count}")
    return [{b: stacks[b][k] for b in roles} for k in range(count)]


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


@dataclass(frozen=True)
class CameraFiles:
    """A further camera's files: its frames (the forms of :class:`RegisterInputs`'s), its view
    in the first camera's world (an RTK geometry, a MayaCam calibration made on the same
    object as the first camera's, or a JointTrack calibration with its camera pose), its
    panel's warp (None: not dewarped) and its JointTrack camera's pose in that world (a file
    for registration.jointtrack.read_camera_pose; None for other views)."""

    frames: Path | list[str | Path]
    geometry: Path | None = None
    calibration: Path | None = None
    distortion: Distortion | None = None
    camera_pose: Path | None = None


@dataclass(frozen=True)
class RegisterInputs:
    """The files ``cbct register`` reads.

    Attributes:
        frames: The frames: a stack, DICOM, images, a glob, or a list of image files.
        geometry: RTK geometry of the frames, or None with ``calibration``.
        calibration: JointTrack or MayaCam calibration, or None with ``geometry``.
        volume: The static volume (a file or a DICOM CT series), or None.
        labels: Its bone labels, or None (with ``volume``).
        implants: Implant components to track.
        truth: Reference poses, for the metrics (one poses.csv, or per body a poses.csv or a
            JointTrack .jts), or None.
        initial: Starting poses of the first frame (the same forms), or None: the static
            scan's bones where it has them, components found in the first frame.
        cameras: Further cameras, in order (none: one camera), their frames paired with the
            first camera's by index.
        camera_pose: The pose of the first camera's JointTrack frame in the cameras' common
            world (registration.jointtrack.read_camera_pose), or None: its own frame is the
            world (one JointTrack camera; other views carry their world).
    """

    frames: Path | list[str | Path]
    geometry: Path | None = None
    calibration: Path | None = None
    volume: Path | None = None
    labels: Path | None = None
    implants: tuple[ImplantSpec, ...] = ()
    truth: Path | dict[str, Path] | None = None
    initial: Path | dict[str, Path] | None = None
    cameras: tuple[CameraFiles, ...] = ()
    camera_pose: Path | None = None


@dataclass(frozen=True)
class RegisterOptions:
    """How ``cbct register`` reads its inputs and tracks.

    Attributes:
        polarity: How attenuation shows in the frames: "dark" or "bright".
        pixel_pitch_mm: Pixel size (mm) of frames whose files do not give one.
        distortion: The first camera's panel's warp (its frames are dewarped with it first;
            ValueError if it belongs to a panel of another size), or None.
        settings: Registration settings; the defaults when None.
        unit: Unit of the static volume where its file does not say (recon.static_volume).
        effective_energy_kev: Effective energy (keV) converting HU to 1/mm.
        frame_range: (first, last, step) of the frames tracked, numbered from 0, ``last``
            included; every frame when None. Poses keep the sequence's frame numbers.
    """

    polarity: str = "dark"
    pixel_pitch_mm: float | None = None
    distortion: Distortion | None = None
    settings: Settings | None = None
    unit: StaticUnit | None = None
    effective_energy_kev: float = DEFAULT_EFFECTIVE_ENERGY_KEV
    frame_range: tuple[int, int, int] | None = None


def register_files(
    inputs: RegisterInputs,
    out: Path,
    options: RegisterOptions | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> list[FrameResult]:
    """``cbct register``: track every body through every frame and write the results.

    The bodies: the static scan's bones (a volume and its labels) and implant components
    (their meshes), each component playing the role of the bone it replaces. Every input is read and
    checked before the (long) registration starts; ``out`` must not exist and is written only
    at the end.

    Args:
        inputs: The files read.
        out: Output folder; must not exist.
        options: How the inputs are read and the bodies tracked; the defaults when None.
        progress: Called with (frames done, frames in all).

    Returns:
        One result per frame, numbered as the sequence numbers its frames.
    """
    options = options or RegisterOptions()
    _check(inputs, out)
    frames, numbers, views = _cameras(inputs, options)
    view = views[0]
    models, soft, source, meshes = _bodies(inputs, options)
    found_roles = roles_of(models)
    roles = {name: found_roles[name] for name in tracking_order(found_roles)}
    count = int(numbers[-1]) + 1
    truth = None if inputs.truth is None else _truth(inputs.truth, count, roles, view)
    start = None  # implants alone: searched
    if inputs.initial is not None or inputs.volume is not None or not meshes:
        start = _initial(inputs.initial, roles, view, int(numbers[0]))
        if len(views) > 1:
            _check_seen(start, models, views, frames)
    tracker, found = tracked(frames, views, models, start, options.settings, soft, progress)
    results = [replace(r, frame=int(numbers[r.frame])) for r in found]
    _write(out, results, models, views, tracker, truth, options.distortion, source, frames, meshes)
    return results


def _check(inputs: RegisterInputs, out: Path) -> None:
    """ValueError or FileNotFoundError, before anything is read, for inputs that cannot
    register: an output folder that exists, a volume without labels, nothing to track, a
    file that is not there."""
    if out.exists():
        raise FileExistsError(f"{out} exists: choose a new output folder")
    if (inputs.volume is None) != (inputs.labels is None):
        raise ValueError("a static scan needs both its volume and its labels")
    if inputs.volume is None and not inputs.implants:
        raise ValueError("nothing to track: give a static scan (volume and labels) or implants")
    given = {
        "static volume": inputs.volume,
        "labels": inputs.labels,
        "geometry": inputs.geometry,
        "calibration": inputs.calibration,
        **{f"geometry of camera {k}": c.geometry for k, c in enumerate(inputs.cameras, 2)},
        **{f"calibration of camera {k}": c.calibration for k, c in enumerate(inputs.cameras, 2)},
        **{f"{spec.body} mesh": spec.mesh for spec in inputs.implants},
        **_named_paths("true poses", inputs.truth),
        **_named_paths("initial poses", inputs.initial),
    }
    for what, path in given.items():
        if path is not None and not Path(path).exists():
            raise FileNotFoundError(f"{path}: no such file or folder ({what})")


def _cameras(
    inputs: RegisterInputs, options: RegisterOptions
) -> tuple[list[Frames], np.ndarray, list[View]]:
    """Each camera's frames tracked (those of ``frame_range``, dewarped) and its view, and the
    frames' numbers in the sequence; ValueError for cameras in no common world or whose frames
    number differently (unless ``frame_range`` keeps to the frames they share)."""
    files = [
        CameraFiles(
            inputs.frames,
            inputs.geometry,
            inputs.calibration,
            options.distortion,
            inputs.camera_pose,
        ),
        *inputs.cameras,
    ]
    poses = _camera_poses(files)
    pitch = options.pixel_pitch_mm
    calibration = files[0].calibration
    if calibration is not None and pitch is None:  # the first camera's, for every camera
        if is_mayacam(calibration):
            pitch = nominal_pitch_mm(calibration)
        else:
            pitch = read_calibration(calibration, 1, 1).pitch_u_mm
    stacks = [read_frames(camera.frames, pitch, options.polarity) for camera in files]
    counts = [len(stack.data) for stack in stacks]
    common = min(counts)
    if len(set(counts)) > 1 and (options.frame_range is None or options.frame_range[1] >= common):
        each = ", ".join(f"camera {k}'s {n}" for k, n in enumerate(counts, 1))
        raise ValueError(
            f"the cameras' frames number differently ({each}): give --frames-range "
            f"0:{common - 1} (or a range within it) to track the frames they share"
        )
    numbers = frame_numbers(common, options.frame_range)
    frames, views = [], []
    for stack, camera, pose in zip(stacks, files, poses, strict=True):
        view = read_view(stack, camera.geometry, camera.calibration)
        views.append(view if pose is None else view.transformed(pose))
        if options.frame_range is not None:
            stack = replace(stack, data=stack.data[numbers])
        frames.append(_dewarped(stack, views[-1], camera.distortion))
    return frames, numbers, views


def _camera_poses(files: list[CameraFiles]) -> list[np.ndarray | None]:
    """Each camera's JointTrack frame's pose in the common world (None: not moved); ValueError
    unless several cameras' views share one world: all RTK geometries, all MayaCam
    calibrations (made on one object), or all JointTrack calibrations each with its pose."""
    kinds, poses = set(), []
    for k, camera in enumerate(files, 1):
        jointtrack = camera.calibration is not None and not is_mayacam(camera.calibration)
        if camera.camera_pose is not None and not jointtrack:
            raise ValueError(
                f"--camera-pose {camera.camera_pose} (camera {k}): a camera pose places a "
                "JointTrack calibration's camera; this camera's view "
                f"({camera.geometry or camera.calibration}) carries its own world"
            )
        if camera.geometry is not None:
            kinds.add("RTK geometry")
        elif not jointtrack:
            kinds.add("MayaCam calibration")
        elif camera.camera_pose is not None:
            kinds.add("JointTrack calibration with its camera pose")
        elif len(files) > 1:
            raise ValueError(
                f"{camera.calibration} (camera {k}): a JointTrack calibration places its camera "
                f"in a frame of its own; {len(files)} cameras need their poses in one world, "
                "which is missing: give each JointTrack camera's pose (--camera-pose, the 4 x 4 "
                "T_world_camera), or RTK geometries, or XMALab/Autoscoper (MayaCam 2.0) "
                "calibrations made on one calibration object"
            )
        poses.append(None if camera.camera_pose is None else read_camera_pose(camera.camera_pose))
    if len(kinds) > 1:
        raise ValueError(
            f"the cameras' views mix {' and '.join(sorted(kinds))}, whose worlds are not known "
            "to be one: give every camera's view in one kind of file"
        )
    return poses


def _dewarped(frames: Frames, view: View, distortion: Distortion | None) -> Frames:
    """``frames`` dewarped by their panel's ``distortion`` (as they are when None)."""
    if distortion is None:
        return frames
    field = frames.field
    if field is not None:  # pixels the dewarped field fully covers
        field = distortion.undistort(field.astype(np.float32), view.pitch_u_mm) > 0.99
    data = distortion.undistort(frames.data, view.pitch_u_mm)
    return replace(frames, data=data, field=field)


def _check_seen(
    start: dict[str, np.ndarray], models: dict, views: list[View], frames: list[Frames]
) -> None:
    """ValueError naming the camera and the body when a camera sees none of a body's points
    at its starting pose (the wrong view file, or a camera aimed elsewhere)."""
    for k, (view, stack) in enumerate(zip(views, frames, strict=True), 1):
        for name, T in start.items():
            points = models[name].points_mm @ T[:3, :3].T + T[:3, 3]
            u, v = view.project(points).T
            inside = (u >= -0.5) & (u <= view.cols - 0.5) & (v >= -0.5) & (v <= view.rows - 0.5)
            if not inside.any():
                raise ValueError(
                    f"camera {k} ({stack.header.source}) does not see {name}: at its start "
                    f"every point falls outside the {view.rows} x {view.cols} image; check "
                    "that camera's view file"
                )


def _bodies(
    inputs: RegisterInputs, options: RegisterOptions
) -> tuple[dict, SoftTissue | None, StaticSource | None, dict[str, dict]]:
    """The tracked bodies' models by name, the static scan's soft tissue and source (None
    without one), and what was read of each mesh."""
    models, soft, source, meshes = {}, None, None, {}
    if inputs.volume is not None:
        volume, labels, source = load_inputs(
            inputs.volume, inputs.labels, options.unit, options.effective_energy_kev
        )
        models = bone_models(volume, labels)
        soft = SoftTissue.of(volume, labels)
    for spec in inputs.implants:
        name = COMPONENT_NAMES[body_role(spec.body)]
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
    return models, soft, source, meshes


def _write(
    out,
    results,
    models,
    views: list[View],
    tracker: Tracker,
    truth,
    distortion,
    source: StaticSource | None,
    frames: list[Frames],
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
    for name in models:  # Autoscoper's, in the world; its untracked rows where one failed
        kept = [r for r in results if not r.bodies[name].failed]
        stack = np.array([r.bodies[name].T_world_body for r in kept]).reshape(-1, 4, 4)
        write_tra(out / f"{name}.tra", np.array([r.frame for r in kept], int), stack)
    for k, (view, stack) in enumerate(zip(views, frames, strict=True), 1):
        folder = out if len(views) == 1 else out / f"view{k}"
        folder.mkdir(exist_ok=True)
        T_camera_world = np.linalg.inv(camera_frame(view))
        for name, role in tracker.roles.items():  # JointTrack's, in its camera frame; by role
            in_camera = [T_camera_world @ r.bodies[name].T_world_body for r in results]
            write_jts(folder / f"{role}.jts", in_camera)
        write_overlays(folder / "overlays", stack.data, view, models, results)
    if len(views) > 1:  # every camera's side by side, for the report (cbct assess)
        write_side_by_side(
            out / "overlays", [out / f"view{k}" / "overlays" for k in range(1, len(views) + 1)]
        )
    view = views[0]
    per_frame = [
        {
            "frame": r.frame,
            "body": name,
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
        "fluoroscopy": {"source": frames[0].header.source, "values": frames[0].stand_in},
        "cameras": [{"source": stack.header.source, "values": stack.stand_in} for stack in frames],
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
