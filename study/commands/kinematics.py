"""The commands from fluoroscopy to a report: ``register`` (track the bodies through a
fluoroscopy sequence), ``assess`` (the knee kinematics report from body poses) and ``export``
(a study's results for other programs)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import typer

from configs import CONFIGS
from recon.attenuation import DEFAULT_EFFECTIVE_ENERGY_KEV
from study.console import (
    checked_unit,
    fail,
    tell,
    views_done,
    views_progress,
)


def register(
    frames: Annotated[
        list[str],
        typer.Option(
            help="fluoroscopy: .mha stack, DICOM file or folder, TIFF/PNG images "
            "(a file, a folder, a quoted glob, or one --frames per image, in order); with "
            "several cameras, one --frames per camera in the order of their views"
        ),
    ],
    out: Annotated[Path, typer.Option(help="new output folder")],
    volume: Annotated[
        Path | None,
        typer.Option(help="static scan: .nii.gz, .nii, .mha, or a DICOM CT series folder"),
    ] = None,
    labels: Annotated[Path | None, typer.Option(help="its bone labels on the same grid")] = None,
    implant: Annotated[
        list[str] | None,
        typer.Option(
            help="ROLE=MESH: an implant component playing the femur, tibia or patella "
            "(STL, OBJ or PLY), tracked as femoral_component, tibial_tray or "
            "patellar_component; repeatable"
        ),
    ] = None,
    material: Annotated[
        list[str] | None,
        typer.Option(help="BODY=MATERIAL of an implant: CoCr (default), Ti6Al4V; repeatable"),
    ] = None,
    attach: Annotated[
        list[str] | None,
        typer.Option(
            help="BODY=MESH:MATERIAL: a part fixed to BODY's implant, in its mesh's frame "
            "(an insert: UHMWPE; the bone it is fixed to: bone), tracked with it; repeatable"
        ),
    ] = None,
    implant_unit: Annotated[str, typer.Option(help="the meshes' unit: mm, cm, m or in")] = "mm",
    geometry: Annotated[
        list[Path] | None,
        typer.Option(
            help="the fluoroscopy view, RTK geometry XML; repeat it for each further camera "
            "(biplane), every view in one world"
        ),
    ] = None,
    calibration: Annotated[
        list[Path] | None,
        typer.Option(
            "--view-file",
            "--calibration",
            help="the fluoroscopy view as a JointTrack JT_INTCALIB file or an XMALab/Autoscoper "
            "MayaCam 2.0 file (without --pixel-pitch-mm its panel is put 1000 mm from the "
            "focal spot: the pixels project the same); repeat it for each further camera "
            "(MayaCam files made on one calibration object); --calibration is those programs' "
            "word",
        ),
    ] = None,
    camera_pose: Annotated[
        list[Path] | None,
        typer.Option(
            help="a JointTrack camera's pose in the cameras' common world: a text file of the "
            "4 x 4 T_world_camera (mm; rows of numbers), one per --calibration in order; "
            "needed for several JointTrack cameras"
        ),
    ] = None,
    polarity: Annotated[
        str, typer.Option(help="images: attenuation dark (fluoroscopy's display) or bright")
    ] = "dark",
    truth: Annotated[
        list[str] | None,
        typer.Option(
            help="true poses: a poses.csv, or BODY=FILE (poses.csv or JointTrack "
            ".jts) per body; also write metrics.json"
        ),
    ] = None,
    initial: Annotated[
        list[str] | None,
        typer.Option(
            help="the first frame's start: a poses.csv, or BODY=FILE (poses.csv or "
            ".jts whose first row is frame 0) per body"
        ),
    ] = None,
    pixel_pitch_mm: Annotated[
        float | None, typer.Option(help="panel pitch for frames without one, mm")
    ] = None,
    distortion: Annotated[
        list[Path] | None,
        typer.Option(
            help="the panel's distortion (cbct calibrate-fluoro); with several cameras, one "
            "per camera in order"
        ),
    ] = None,
    settings: Annotated[
        Path | None,
        typer.Option(
            help="registration settings YAML [default: configs/registration.yaml, or "
            "configs/registration_implants.yaml for implants without a static scan]"
        ),
    ] = None,
    unit: Annotated[
        str | None,
        typer.Option(help="the static scan's unit where its file does not say: hu or 1/mm"),
    ] = None,
    effective_energy_kev: Annotated[
        float, typer.Option(help="effective energy HU are converted to 1/mm at, keV")
    ] = DEFAULT_EFFECTIVE_ENERGY_KEV,
    frames_range: Annotated[
        str | None,
        typer.Option(
            help="track only frames FIRST:LAST[:STEP] (numbered from 0, LAST included); "
            "poses keep the sequence's frame numbers"
        ),
    ] = None,
) -> None:
    """Track the knee's bones (from a static scan) or its implant components (from their
    meshes) through a fluoroscopy sequence (BoneAxis-Reg)."""
    from recon.config import load_config
    from recon.distortion import Distortion
    from registration.settings import Settings
    from scanner.outputs import Output, new_outputs
    from study.jobs import (
        CameraFiles,
        ImplantSpec,
        RegisterInputs,
        RegisterOptions,
        register_files,
    )

    static_unit = checked_unit(unit, effective_energy_kev)
    frame_range = None if frames_range is None else _frame_range(frames_range)
    views = _camera_views(
        frames, geometry or [], calibration or [], distortion or [], camera_pose or []
    )
    try:
        meshes = _body_files("--implant", implant)
        materials = _body_words("--material", material)
        lacking = sorted(set(materials) - set(meshes))
        if lacking:
            fail(f"--material {lacking[0]}=...: {lacking[0]} has no --implant")
        attached = _attachments(attach)
        lacking = sorted(set(attached) - set(meshes))
        if lacking:
            fail(f"--attach {lacking[0]}=...: {lacking[0]} has no --implant")
        implants = tuple(
            ImplantSpec(
                body, path, implant_unit, materials.get(body, "CoCr"), attached.get(body, ())
            )
            for body, path in meshes.items()
        )
        if settings is None:
            from study.stages import registration_settings_file

            settings = registration_settings_file(CONFIGS, bool(implants) and volume is None)
        chosen = load_config(settings, Settings)
        warps = [None if path is None else Distortion.read(path) for path in views.distortions]
        cameras = tuple(
            CameraFiles(*camera, warp, pose)
            for camera, warp, pose in zip(views.files[1:], warps[1:], views.poses[1:], strict=True)
        )
        with new_outputs(Output(out, "--out")) as (staged,), views_progress() as bar:
            inputs = RegisterInputs(
                *views.files[0],
                volume=volume,
                labels=labels,
                implants=implants,
                truth=_poses_given("--truth", truth),
                initial=_poses_given("--initial", initial),
                cameras=cameras,
                camera_pose=views.poses[0],
            )
            options = RegisterOptions(
                polarity=polarity,
                pixel_pitch_mm=pixel_pitch_mm,
                distortion=warps[0],
                settings=chosen,
                unit=static_unit,
                effective_energy_kev=effective_energy_kev,
                frame_range=frame_range,
            )
            progress = views_done(bar, "BoneAxis-Reg", "frames")
            results = register_files(inputs, staged, options, progress)
    except (ValueError, OSError) as err:
        fail(str(err))
    failed = sum(b.failed for r in results for b in r.bodies.values())
    line = f"[green]wrote[/] {out / 'poses.csv'}: {len(results)} frames, {failed} flagged"
    if truth:
        metrics = json.loads((out / "metrics.json").read_text(encoding="utf-8"))
        line += (
            f"; TRE mean {metrics['tre_mm']:.2f} mm (median {metrics['tre_mm_median']:.2f}), "
            f"RSR {metrics['rsr_pct']:.1f} %"
        )
    tell(line)
    if len(views.files) == 1:
        tell(
            f"  JointTrack poses beside it ({', '.join(sorted(p.name for p in out.glob('*.jts')))}"
            f"), Autoscoper .tra per body, overlays in {out / 'overlays'}"
        )
    else:
        tell(
            f"  per camera K, its JointTrack poses and overlays in {out}/view<K>/ (1 to "
            f"{len(views.files)}); Autoscoper .tra per body beside poses.csv"
        )


@dataclass(frozen=True)
class _Views:
    """The cameras given on the command line: each one's (frames, geometry, calibration),
    its distortion file and its camera pose file."""

    files: list[tuple[list[str], Path | None, Path | None]]
    distortions: list[Path | None]
    poses: list[Path | None]


def _camera_views(
    frames: list[str],
    geometry: list[Path],
    calibration: list[Path],
    distortion: list[Path],
    camera_pose: list[Path],
) -> _Views:
    """The cameras of ``--frames``, ``--geometry`` or ``--calibration``, ``--distortion`` and
    ``--camera-pose``; the console's error for counts that do not pair (one camera: --frames
    may repeat, one per image)."""
    if geometry and calibration:
        fail(
            "give every camera's view as --geometry or every one as --calibration, not both "
            "(their order could not be told apart)"
        )
    given = geometry or calibration
    option = "--geometry" if geometry else "--calibration"
    if not given:
        fail("give the fluoroscopy view: --geometry (RTK) or --calibration (JointTrack, MayaCam)")
    if len(distortion) not in (0, len(given)):
        fail(f"--distortion given {len(distortion)} times for {len(given)} cameras: one each")
    warps: list[Path | None] = list(distortion) or [None] * len(given)
    if len(camera_pose) not in (0, len(given)):
        fail(f"--camera-pose given {len(camera_pose)} times for {len(given)} cameras: one each")
    poses: list[Path | None] = list(camera_pose) or [None] * len(given)
    if len(given) == 1:
        files = [(frames, *((given[0], None) if geometry else (None, given[0])))]
        return _Views(files, warps, poses)
    if len(frames) != len(given):
        fail(
            f"--frames given {len(frames)} times for {len(given)} cameras ({option} "
            f"{len(given)} times): with several cameras give one --frames per camera (a "
            "stack, a folder or a quoted glob), in the order of their views"
        )
    files = [
        ([stack], *((view, None) if geometry else (None, view)))
        for stack, view in zip(frames, given, strict=True)
    ]
    return _Views(files, warps, poses)


def _frame_range(text: str) -> tuple[int, int, int]:
    """``FIRST:LAST[:STEP]`` as three integers; the console's error otherwise."""
    parts = text.split(":")
    try:
        numbers = [int(p) for p in parts]
    except ValueError:
        numbers = []
    if len(numbers) not in (2, 3):
        fail(f"--frames-range {text!r}: give FIRST:LAST or FIRST:LAST:STEP, e.g. 0:9 or 0:29:2")
    return (numbers[0], numbers[1], numbers[2] if len(numbers) == 3 else 1)


def _body_words(option: str, given: list[str] | None) -> dict[str, str]:
    """``BODY=VALUE`` options as the body's role (femur, tibia, patella) -> value; ValueError
    naming the option and the value otherwise."""
    from study.jobs.register import body_role

    out: dict[str, str] = {}
    for item in given or ():
        body, sep, value = item.partition("=")
        if not sep or not value:
            raise ValueError(f"{option} {item!r}: give BODY=VALUE, e.g. femur=...")
        name = body_role(body.strip())
        if name in out:
            raise ValueError(f"{option}: {body} given twice")
        out[name] = value.strip()
    return out


def _attachments(given: list[str] | None) -> dict[str, tuple[tuple[Path, str], ...]]:
    """``--attach BODY=MESH:MATERIAL`` options as the body's role -> its parts (mesh,
    material); ValueError naming the value otherwise."""
    from registration.meshes import ATTACHABLE
    from study.jobs.register import body_role

    out: dict[str, tuple[tuple[Path, str], ...]] = {}
    for item in given or ():
        body, _, value = item.partition("=")
        mesh, _, material = value.rpartition(":")
        if not body or not mesh or material not in ATTACHABLE:
            raise ValueError(
                f"--attach {item!r}: give BODY=MESH:MATERIAL, MATERIAL one of {sorted(ATTACHABLE)}"
            )
        name = body_role(body.strip())
        out[name] = (*out.get(name, ()), (Path(mesh.strip()), material))
    return out


def _body_files(option: str, given: list[str] | None) -> dict[str, Path]:
    return {body: Path(value) for body, value in _body_words(option, given).items()}


def _poses_given(option: str, given: list[str] | None) -> Path | dict[str, Path] | None:
    """One poses file, or ``BODY=FILE`` per body."""
    if not given:
        return None
    if len(given) == 1 and "=" not in given[0]:
        return Path(given[0])
    return _body_files(option, given)


def assess(
    poses: Annotated[Path, typer.Option(help="poses.csv (frame, bone, 4x4, ...)")],
    out: Annotated[Path, typer.Option(help="new output folder")],
    labels: Annotated[
        Path | None, typer.Option(help="label volume of the static scan (bones tracked)")
    ] = None,
    implant: Annotated[
        list[str] | None,
        typer.Option(
            help="BODY=MESH of a tracked component (femur=FEMORAL, tibia=TRAY), in the "
            "frame its poses move, anatomical axes (x anterior, y up, z right): a knee "
            "replacement assessed from its components; repeatable"
        ),
    ] = None,
    insert: Annotated[
        Path | None,
        typer.Option(help="the polyethylene insert's mesh in the tray's frame: the TP plane"),
    ] = None,
    implant_unit: Annotated[str, typer.Option(help="the meshes' unit: mm, cm, m or in")] = "mm",
    side: Annotated[str, typer.Option(help="right or left knee")] = "right",
    tka: Annotated[bool, typer.Option(help="fit the TP plane to the polyethylene insert")] = False,
    plateau_offset_mm: Annotated[
        float, typer.Option(help="shift of the TP plane along its normal, mm")
    ] = 0.0,
    volume: Annotated[
        Path | None, typer.Option(help="static scan for the 3D Slicer scene (file or DICOM)")
    ] = None,
    overlays: Annotated[
        Path | None,
        typer.Option(
            help="the registration's overlays/ to play in the report (default: the one "
            "beside --poses, if there is one)"
        ),
    ] = None,
) -> None:
    """Knee kinematics, TP-condyle distances and flags: report.html (the registered frames
    and the motion in 3D played), metrics.csv, plots, 4D, and export/ (ITK transforms,
    Autoscoper .tra, a 3D Slicer scene); of bones (--labels) or of a knee replacement's
    components (--implant, --insert). Frames whose registration failed or is implausible are
    not measured; with fewer than half measured the report gives no clinical flag and the
    command exits 1."""
    import numpy as np

    from assessment.flags import insufficient_text, measured_text
    from scanner.outputs import Output, new_outputs
    from study import jobs

    if side not in ("right", "left"):
        fail(f"--side {side!r}: give right or left")
    if (labels is None) == (not implant):
        fail("give --labels (bones tracked from a static scan) or --implant (components)")
    if insert is not None and not implant:
        fail("--insert needs the components (--implant femur=... --implant tibia=...)")
    try:
        implants = _body_files("--implant", implant)
    except ValueError as err:
        fail(str(err))
    if overlays is None and (poses.parent / "overlays").is_dir():
        overlays = poses.parent / "overlays"
    elif overlays is not None and not overlays.is_dir():
        fail(f"--overlays {overlays}: no such folder (a registration's overlays/)")
    try:
        with new_outputs(Output(out, "--out")) as (written,):
            result = jobs.assess_files(
                poses,
                labels,
                written,
                side,
                tka=tka,
                plateau_offset_mm=plateau_offset_mm,
                volume=volume,
                overlays=overlays,
                implants=implants,
                insert=insert,
                implant_unit=implant_unit,
            )
    except (ValueError, OSError) as err:
        fail(str(err))
    kin = result.kinematics
    if not kin.sufficient:
        tell(
            f"[bold red]{insufficient_text(kin)}[/] The report, marked so, is at "
            f"{out / 'report.html'}."
        )
        raise typer.Exit(1)
    tell(
        f"[green]wrote[/] {out / 'report.html'}: {measured_text(kin)}, flexion "
        f"{np.nanmin(kin.flexion_deg):.0f}..{np.nanmax(kin.flexion_deg):.0f} deg, max |MLD| "
        f"{np.nanmax(np.abs(kin.mld_mm)):.2f} mm, {int(kin.flagged.sum())} frame(s) flagged"
    )


def export(
    out: Annotated[Path, typer.Option(help="new output folder")],
    study: Annotated[
        Path | None,
        typer.Option(help="a study folder: its poses, labels and volume (instead of the three)"),
    ] = None,
    poses: Annotated[Path | None, typer.Option(help="poses.csv (frame, bone, 4x4, ...)")] = None,
    labels: Annotated[Path | None, typer.Option(help="label volume of the static scan")] = None,
    volume: Annotated[
        Path | None, typer.Option(help="static scan for the 3D Slicer scene (file or DICOM)")
    ] = None,
) -> None:
    """The tracked bones for other tools: per-frame ITK transforms (SimpleITK, ITK-SNAP, 3D
    Slicer), Autoscoper .tra files, and a 3D Slicer scene (scene.mrml) that plays the motion."""
    from scanner.outputs import Output, new_outputs
    from study import jobs

    if study is not None:
        if poses is not None or labels is not None:
            fail("--study names the poses and labels: drop --poses and --labels")
        poses = study / "registration" / "poses.csv"
        labels = study / "segmentation" / "labels.nii.gz"
        volume = volume or study / "recon" / "volume.nii.gz"
    elif poses is None or labels is None:
        fail("give --study, or --poses and --labels (and --volume for the Slicer scene)")
    try:
        with new_outputs(Output(out, "--out")) as (staged,):
            written = jobs.export_files(poses, labels, staged, volume)
    except (ValueError, OSError) as err:
        fail(str(err))
    tell(
        f"[green]wrote[/] {len(written)} files to {out}: 3D Slicer scene {out / 'scene.mrml'}, "
        f"ITK transforms in {out / 'itk'}, Autoscoper tracks in {out / 'autoscoper'}"
    )
