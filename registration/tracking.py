"""Track bodies through a fluoroscopy sequence in memory (:func:`track`), and read the
sequence's view (:func:`read_view`: an RTK geometry, a JointTrack or MayaCam calibration).
``cbct register``, the same from files, is study.jobs.register."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from recon.fdk import CORNER_FRACTION
from recon.geometry import View
from recon.rtk_xml import read_rtk_geometry
from registration.autostart import candidate_poses
from registration.drr import SoftTissue
from registration.frames import Frames
from registration.implants import ImplantModel
from registration.jointtrack import read_calibration
from registration.mayacam import is_mayacam, read_mayacam
from registration.objective import BodyModel
from registration.results import FrameResult
from registration.roles import Role
from registration.settings import Settings
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


KNEE_REACH_MM = 120.0
"""How far from a placed component the next one's centre is searched (automatic start), mm."""


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
        raise ValueError(
            "give the fluoroscopy view as one of an RTK geometry or a JointTrack or MayaCam file"
        )
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


def track(
    frames: Frames | np.ndarray | Sequence[Frames | np.ndarray],
    view: View | Sequence[View],
    bodies: dict[str, BodyModel],
    *,
    start: dict[str, np.ndarray] | None = None,
    settings: Settings | None = None,
    soft_tissue: SoftTissue | None = None,
    progress: Callable[[int, int], None] | None = None,
    roles: dict[str, Role] | None = None,
) -> list[FrameResult]:
    """Track bodies through fluoroscopy frames, in memory.

    Args:
        frames: The frames (:func:`registration.read_frames`), or their line integrals
            (frames, rows, cols); with several cameras, one of these per view, paired by index.
        view: The fluoroscopy view (:func:`read_view`), or one per camera in one world (each
            body's pose is scored on every view that sees it: registration.views).
        bodies: The tracked bodies' models by name: a static scan's bones
            (registration.bone_models: femur, tibia_fibula, patella) or implant components
            (registration.implant_body: femoral_component, tibial_tray, patellar_component).
        start: The first frame's poses, 4x4 (mm) by body; None: each bone where the static
            scan has it (the identity) and each component found in the first frame
            (registration.autostart).
        settings: Registration settings; the defaults when None.
        soft_tissue: The static scan's soft tissue (registration.drr.SoftTissue), scored
            with the bones; None leaves it out.
        progress: Called with (frames done, frames in all) after each frame.
        roles: Each body's anatomical role (femur, tibia, patella) by name, for bodies named
            otherwise (registration.roles.roles_of).

    Returns:
        One result per frame, numbered from 0.
    """
    return tracked(frames, view, bodies, start, settings, soft_tissue, progress, roles)[1]


def tracked(
    frames: Frames | np.ndarray | Sequence[Frames | np.ndarray],
    view: View | Sequence[View],
    bodies: dict[str, BodyModel],
    start: dict[str, np.ndarray] | None,
    settings: Settings | None,
    soft_tissue: SoftTissue | None,
    progress: Callable[[int, int], None] | None,
    roles: dict[str, Role] | None = None,
) -> tuple[Tracker, list[FrameResult]]:
    """:func:`track`, and the tracker that tracked: its bodies carry the blurs it matched
    (registration.tracker.Tracker.bodies, frame_blur_mm).

    Args:
        frames: As :func:`track`'s.
        view: As :func:`track`'s.
        bodies: As :func:`track`'s.
        start: As :func:`track`'s.
        settings: As :func:`track`'s.
        soft_tissue: As :func:`track`'s.
        progress: As :func:`track`'s.
        roles: As :func:`track`'s.
    """
    views = [view] if isinstance(view, View) else list(view)
    stacks = [frames] if isinstance(view, View) else list(frames)
    if len(stacks) != len(views):
        raise ValueError(f"{len(stacks)} frame stacks for {len(views)} views: one per camera")
    data, fields, where = [], [], []
    for k, stack in enumerate(stacks, start=1):
        camera = f" of camera {k}" if len(views) > 1 else ""
        if isinstance(stack, Frames):
            data.append(stack.data)
            fields.append(stack.field)
            where.append(f"{stack.header.source} with the view{camera}")
        else:
            data.append(np.asarray(stack, dtype=np.float32))
            fields.append(None)
            where.append(f"the frames with the view{camera}")
            if data[-1].ndim != 3:
                raise ValueError(
                    f"frames{camera} of shape {data[-1].shape}: give a stack (frames, rows, cols)"
                )
    tracker = Tracker(views, data, bodies, settings, soft_tissue, fields, roles)
    given = dict(start or {})
    for name in (b for b in bodies if b not in given and not isinstance(bodies[b], ImplantModel)):
        given[name] = np.eye(4)  # a bone where the static scan has it
    components = [b for b in bodies if b not in given]
    if components:  # found in the first camera's first frame
        found = _automatic_start(
            tracker, bodies, components, views[0], data[0][0], fields[0], given
        )
        given |= found
    for v, w in zip(views, where, strict=True):
        _check_in_view(v, bodies, given, w)
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
