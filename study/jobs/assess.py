"""Assess files: a knee's (or its components') poses against its static scan's labels into
the report, plots, metrics and the 4D series; the series exported for other programs."""

from __future__ import annotations

from pathlib import Path

import trimesh

from assessment.components import assess_components
from assessment.handoff import Motion, check_static_volume, write_handoff
from assessment.knee import BONE_LABELS, KneeAssessment, assess_knee
from assessment.report import frame_overlays, write_report
from assessment.series import bone_mesh, export_series, record_series
from assessment.viewer import motion_scene
from recon.io import read_volume
from recon.volume import Volume
from registration.meshes import read_mesh
from registration.poses import BodyPose, read_poses
from registration.roles import KNOWN_ROLES, playing
from scanner.outputs import new_folder


def write_assessment(
    labels: Volume,
    poses: list[BodyPose],
    out: Path,
    side: str,
    *,
    tka: bool = False,
    plateau_offset_mm: float = 0.0,
    title: str = "Knee kinematics",
    volume: Path | None = None,
    overlays: Path | None = None,
    scan_rows: dict[str, str] | None = None,
) -> KneeAssessment:
    """Assess the motion and write the report, metrics.csv, plots, the 4D series (meshes
    per frame and a rerun recording) and the hand-off for other tools (``export/``: ITK
    transforms, Autoscoper .tra, a 3D Slicer scene with the static ``volume`` when given) into
    the new folder ``out``. ``overlays``: the registration's overlays folder, played in the
    report; ``scan_rows``: what the report's summary says of the static scan (e.g. the
    patient's motion during it)."""
    result = assess_knee(labels, poses, side, tka=tka, plateau_offset_mm=plateau_offset_mm)
    motion, meshes = bone_motion(poses, labels, "poses")
    plane = "polyethylene insert" if tka else "fitted tibial plateau"
    extra = {"TP plane": f"{plane}, offset {plateau_offset_mm:g} mm along its normal"}
    extra |= scan_rows or {}
    _write_outputs(result, poses, motion, meshes, out, title, extra, volume, overlays)
    return result


def write_component_assessment(
    components: dict[str, trimesh.Trimesh],
    plateau: trimesh.Trimesh,
    poses: list[BodyPose],
    out: Path,
    side: str,
    *,
    plateau_offset_mm: float = 0.0,
    title: str = "Knee replacement kinematics",
    overlays: Path | None = None,
    insert: bool = True,
) -> KneeAssessment:
    """:func:`write_assessment` of a knee replacement from its tracked components' poses:
    ``components`` by the name of the body their poses are given under (the femoral
    component's plays the femur, the tray's the tibia: registration.roles), ``plateau`` the
    insert (``insert``) or the tray in the tray's frame (assessment.components)."""
    (femoral,) = playing(components, "femur")
    result = assess_components(
        components[femoral],
        plateau,
        poses,
        side,
        plateau_offset_mm=plateau_offset_mm,
        insert=insert,
    )
    tracked = [p for p in poses if p.body in components]
    motion = Motion.of(tracked)
    missing = sorted(set(components) - set(motion.poses))
    if missing:
        raise ValueError(f"poses: no poses of the component(s) {missing}")
    extra = {"TP plane": f"the insert's top, offset {plateau_offset_mm:g} mm along its normal"}
    _write_outputs(result, tracked, motion, components, out, title, extra, None, overlays)
    return result


def _write_outputs(
    result: KneeAssessment,
    poses: list[BodyPose],
    motion: Motion,
    meshes: dict[str, trimesh.Trimesh],
    out: Path,
    title: str,
    extra: dict[str, str],
    volume: Path | None,
    overlays: Path | None,
) -> None:
    """The assessment's files in the new folder ``out`` (see :func:`write_assessment`)."""
    new_folder(out)
    frames = [] if overlays is None else frame_overlays(overlays, result.kinematics, poses)
    scene = motion_scene(result, motion.frames, motion.poses, meshes)
    write_report(
        result.kinematics, out, title=title, extra_rows=extra, overlays=frames, scene=scene
    )
    export_series(meshes, motion.frames, motion.poses, out / "series")
    record_series(meshes, motion.frames, motion.poses, out / "series.rrd")
    write_handoff(out / "export", motion, meshes, volume)


def bone_motion(
    poses: list[BodyPose], labels: Volume, where: Path | str
) -> tuple[Motion, dict[str, trimesh.Trimesh]]:
    """Every posed bone's motion, and its surface (world mm) from the label volume;
    ValueError naming ``where`` for a bone name the labels do not know."""
    motion = Motion.of(poses)
    unknown = sorted(set(motion.poses) - set(BONE_LABELS))
    if unknown:
        raise ValueError(f"{where}: unknown bone name(s) {unknown}; known: {sorted(BONE_LABELS)}")
    return motion, {bone: bone_mesh(labels, BONE_LABELS[bone]) for bone in motion.poses}


def assess_files(
    poses_path: Path,
    labels_path: Path | None,
    out: Path,
    side: str,
    *,
    tka: bool = False,
    plateau_offset_mm: float = 0.0,
    volume: Path | None = None,
    overlays: Path | None = None,
    implants: dict[str, Path] | None = None,
    insert: Path | None = None,
    implant_unit: str = "mm",
) -> KneeAssessment:
    """``cbct assess``: read poses.csv and the label volume, then :func:`write_assessment`
    (``overlays``: the registration's overlays folder, for the report's player); or, with
    ``implants`` (role -> mesh: the femoral component's as "femur", the tray's as "tibia", or
    each under its body's name; the poses of the bodies playing those roles move them) and
    ``insert`` (in the tray's frame; else the tray's top is the plateau),
    :func:`write_component_assessment`."""
    if out.exists():
        raise FileExistsError(f"{out} exists: choose a new output folder")
    if volume is not None:
        check_static_volume(volume)
    poses = read_poses(poses_path)
    if implants:
        by_role = {KNOWN_ROLES.get(word): path for word, path in implants.items()}
        if set(by_role) != {"femur", "tibia"}:
            raise ValueError(
                f"--implant: {sorted(implants)}; give femur=FEMORAL_COMPONENT and tibia=TRAY"
            )
        femoral, tibia = playing((p.body for p in poses), "femur", "tibia")
        bodies = {"femur": femoral, "tibia": tibia}
        meshes = {bodies[r]: read_mesh(path, implant_unit)[0] for r, path in by_role.items()}
        plateau = meshes[tibia] if insert is None else read_mesh(insert, implant_unit)[0]
        return write_component_assessment(
            meshes,
            plateau,
            poses,
            out,
            side,
            plateau_offset_mm=plateau_offset_mm,
            title=f"Knee replacement kinematics: {poses_path.name}",
            overlays=overlays,
            insert=insert is not None,
        )
    if labels_path is None:
        raise ValueError("give --labels (the static scan's labels), or the components' meshes")
    labels = read_volume(labels_path, unit="label")
    return write_assessment(
        labels,
        poses,
        out,
        side,
        tka=tka,
        plateau_offset_mm=plateau_offset_mm,
        title=f"Knee kinematics: {poses_path.name}",
        volume=volume,
        overlays=overlays,
    )


def export_files(
    poses_path: Path, labels_path: Path, out: Path, volume: Path | None = None
) -> list[Path]:
    """``cbct export``: the tracked motion of poses.csv for 3D Slicer, ITK and Autoscoper
    (assessment.handoff) in the new folder ``out``; bone models from the label volume."""
    if out.exists():
        raise FileExistsError(f"{out} exists: choose a new output folder")
    if volume is not None:
        check_static_volume(volume)
    poses = read_poses(poses_path)
    labels = read_volume(labels_path, unit="label")
    return write_handoff(out, *bone_motion(poses, labels, poses_path), volume)
