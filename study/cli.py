"""The operator console ``cbct`` (its entry point): the acquisition commands of scanner.cli,
``scan`` and ``move`` (the scanner to a study plan's start or to park), and the study
pipeline's: ``calibrate`` (per-view geometry from a steel-ball phantom scan),
``calibrate-fluoro`` (the fluoroscopy panel's distortion from a dewarp grid's image), ``recon``
(weighted FDK of RTK-format inputs), ``segment`` (bone labels of a static scan), ``register``
(track the bones through a fluoroscopy sequence), ``assess`` (knee kinematics report from bone
poses), ``demo`` (the main job on the simulated scanner) and ``batch`` (the derived stages of
many studies on dask.distributed, and a cohort summary). Every command checks its inputs
before long work starts, never overwrites an existing output, writes its outputs through
scanner.outputs (nothing at ``--out`` after a failure), and shows progress on long work. Each
command imports what it uses when it runs (``cbct --help`` and ``cbct scan`` load no
registration, cohort or plotting code).
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

from recon.attenuation import DEFAULT_EFFECTIVE_ENERGY_KEV, ENERGY_RANGE_KEV
from scanner.cli import (
    CONFIGS,
    FAILED,
    app,
    check_range,
    console,
    fail,
    views_done,
    views_progress,
)

if TYPE_CHECKING:
    from study.batch import BatchReport

__all__ = ["app"]


@app.command()
def calibrate(
    projections: Annotated[Path, typer.Option(help="BB-phantom projection stack .mha")],
    geometry: Annotated[Path, typer.Option(help="the scan's planned geometry (RTK XML)")],
    protocol: Annotated[Path, typer.Option(help="the protocol that acquired it")],
    study: Annotated[Path, typer.Option(help="study folder; writes STUDY/calibration")],
    phantom_config: Annotated[Path, typer.Option(help="BB phantom YAML")] = CONFIGS
    / "phantoms"
    / "bb_helix.yaml",
) -> None:
    """Per-view geometry from a steel-ball phantom scan: the vibration correction later scans of
    the same protocol and plan reconstruct with (cbct recon --calibration)."""
    import numpy as np

    from study import jobs

    try:
        with views_progress() as bar:
            result = jobs.calibrate_to_study(
                projections,
                geometry,
                protocol,
                phantom_config,
                study,
                progress=views_done(bar, "finding balls"),
            )
    except (ValueError, OSError) as err:
        fail(str(err))
    summary = result.summary()
    used = [v for v in result.views if v.status == "calibrated"]
    deviation = np.array([v.source_deviation_mm for v in used])
    console.print(
        f"[green]wrote[/] {study / 'calibration'}: {summary['calibrated_views']} of "
        f"{summary['views']} views calibrated, reprojection RMS median "
        f"{summary['reprojection_rms_px_median']:.3f} px (max "
        f"{summary['reprojection_rms_px_max']:.3f} px, worst views "
        f"{summary['worst_views']}), source deviation from the plan median "
        f"{np.median(deviation):.2f} mm",
        soft_wrap=True,
        highlight=False,
    )
    if summary["uncalibrated_views"]:
        console.print(
            f"[yellow]views kept at their plan (too few balls):[/] {summary['uncalibrated_views']}",
            soft_wrap=True,
        )


@app.command("calibrate-fluoro")
def calibrate_fluoro(
    grid: Annotated[Path, typer.Option(help="one exposure of the dewarp grid (.mha, DICOM)")],
    geometry: Annotated[Path, typer.Option(help="the fluoroscopy view, RTK geometry XML")],
    out: Annotated[Path, typer.Option(help="new distortion file (.json)")],
    grid_config: Annotated[Path, typer.Option(help="dewarp grid YAML")] = CONFIGS
    / "phantoms"
    / "dewarp_grid.yaml",
    degree: Annotated[int, typer.Option(help="degree of the warp polynomial (1-9)")] = 5,
    pixel_pitch_mm: Annotated[
        float | None, typer.Option(help="panel pitch for DICOM images without one, mm")
    ] = None,
) -> None:
    """The fluoroscopy panel's distortion from an image of the dewarp grid alone: the warp
    ``cbct register --distortion`` removes from every frame."""
    from scanner.outputs import Output, new_outputs
    from study import jobs

    try:
        with new_outputs(Output(out, "--out", suffixes=(".json",))) as (written,):
            distortion = jobs.fit_fluoro_distortion(
                grid, geometry, grid_config, degree, pixel_pitch_mm
            )
            distortion.write(written)
    except (ValueError, OSError) as err:
        fail(str(err))
    console.print(
        f"[green]wrote[/] {out}: {distortion.balls} balls, residual RMS "
        f"{distortion.rms_mm:.3f} mm (max {distortion.max_mm:.3f}), largest displacement "
        f"{distortion.max_displacement_mm:.2f} mm",
        soft_wrap=True,
        highlight=False,
    )


@app.command()
def recon(
    projections: Annotated[Path, typer.Option(help="projection stack .mha (line integrals)")],
    geometry: Annotated[Path, typer.Option(help="RTK geometry XML")],
    out: Annotated[Path, typer.Option(help="output volume .nii.gz, .nii, .mha or .mhd")],
    size: Annotated[tuple[int, int, int] | None, typer.Option(help="voxels along x y z")] = None,
    spacing_mm: Annotated[float | None, typer.Option(help="voxel size, mm")] = None,
    origin_mm: Annotated[
        tuple[float, float, float] | None,
        typer.Option(help="world x y z of the centre of the first voxel, mm"),
    ] = None,
    filter: Annotated[str, typer.Option(help="ram-lak, shepp-logan, cosine or hann")] = "hann",
    min_coverage_deg: Annotated[
        float, typer.Option(help="mask voxels seen over less of the orbit, degrees")
    ] = 170.0,
    preview: Annotated[Path | None, typer.Option(help="also write orthogonal slices PNG")] = None,
    calibration: Annotated[
        Path | None, typer.Option(help="STUDY/calibration of the same protocol and plan")
    ] = None,
    protocol: Annotated[
        Path | None, typer.Option(help="the scan's protocol (needed with --calibration)")
    ] = None,
    orbit: Annotated[
        Path | None,
        typer.Option(
            help="RTK geometry XML whose orbit sets the angular weights (a study's "
            "scan/planned_geometry.xml); default: the geometry's own"
        ),
    ] = None,
    mar: Annotated[
        bool,
        typer.Option(
            help="normalised metal artefact reduction (an implant in the scan); the metal "
            "mask is written beside the volume as *_metal"
        ),
    ] = False,
    compensate_motion: Annotated[
        bool,
        typer.Option(
            "--compensate-motion",
            help="estimate the patient's motion from the projections and reconstruct through "
            "it; the motion is written beside the volume as *_motion.csv (view, body, 4x4 "
            "T_world_body row-major) and its QA figure as *_motion.png",
        ),
    ] = False,
    times: Annotated[
        Path | None,
        typer.Option(
            help="with --compensate-motion: a CSV of per-view times (a clock_s or time_s "
            "column, e.g. a study's scan/exposure_log.csv); default: views stand for time"
        ),
    ] = None,
    method: Annotated[
        str,
        typer.Option(
            help="fdk (weighted FDK), sart (OS-SART from FDK) or tv (OS-SART with total "
            "variation: sparse views, low dose)"
        ),
    ] = "fdk",
    iterations: Annotated[
        int | None,
        typer.Option(
            help="sart/tv: most iterations (each visits every view once; fewer when the "
            "volume settles)",
            show_default="12",
        ),
    ] = None,
    tv_weight: Annotated[
        float | None,
        typer.Option(
            help="tv: strength of the TV step, 1/mm (default: a quarter of the FDK volume's noise)"
        ),
    ] = None,
    views_every: Annotated[
        int, typer.Option(help="reconstruct every K-th view only (a sparse scan)")
    ] = 1,
) -> None:
    """Reconstruct RTK-format projections with weighted FDK, OS-SART or OS-SART + TV
    (through the patient's motion with --compensate-motion)."""
    from recon.io import VOLUME_SUFFIXES
    from recon.iterative import METHODS, IterativeSettings
    from scanner.outputs import Output, new_outputs
    from study import jobs

    check_range("--min-coverage-deg", min_coverage_deg, 0.0, 360.0, "degrees")
    if method not in METHODS:
        fail(f"--method {method}: choose one of {', '.join(METHODS)}")
    if iterations is not None and method == "fdk":
        fail("--iterations is for --method sart or tv")
    if iterations is not None and iterations < 1:
        fail(f"--iterations {iterations}: give 1 or more")
    if tv_weight is not None and method != "tv":
        fail("--tv-weight is for --method tv")
    if tv_weight is not None and not tv_weight >= 0.0:
        fail(f"--tv-weight {tv_weight:g}: give 0 or more 1/mm")
    iterative = None
    if method != "fdk":
        given = {} if iterations is None else {"iterations": iterations}
        iterative = IterativeSettings(method, tv_weight=tv_weight, **given)  # type: ignore[arg-type]
    if spacing_mm is not None:
        check_range("--spacing-mm", spacing_mm, 0.01, 100.0, "mm")
    if size is not None and min(size) < 1:
        fail(f"--size {' '.join(map(str, size))}: give three voxel counts of 1 or more (x y z)")
    if times is not None and not compensate_motion:
        fail("--times is for --compensate-motion (the motion's time axis)")
    outputs = [Output(out, "--out", suffixes=VOLUME_SUFFIXES)]
    if preview is not None:
        outputs.append(Output(preview, "--preview", suffixes=(".png",)))
    if compensate_motion:
        suffix = next((s for s in VOLUME_SUFFIXES if out.name.lower().endswith(s)), "")
        base = out.name[: len(out.name) - len(suffix)]
        outputs.append(Output(out.with_name(f"{base}_motion.csv"), "--out (its motion)"))
        outputs.append(Output(out.with_name(f"{base}_motion.png"), "--out (its QA figure)"))
    try:
        with new_outputs(*outputs) as written, views_progress() as bar:
            start = time.perf_counter()
            motion_out = (written[-2], written[-1]) if compensate_motion else None
            bars: dict[str, Callable[[int, int], None]] = {}

            def fitted(stage: str, done: int, total: int) -> None:
                if stage not in bars:
                    bars[stage] = views_done(bar, f"motion, {stage}: views registered")
                bars[stage](done, total)

            result = jobs.reconstruct_files(
                projections,
                geometry,
                written[0],
                size_xyz=size,
                spacing_mm=spacing_mm,
                origin_mm=origin_mm,
                window=filter,
                min_coverage_deg=min_coverage_deg,
                progress=views_done(bar, "weighted FDK"),
                preview=written[1] if preview is not None else None,
                calibration=calibration,
                protocol_path=protocol,
                orbit_path=orbit,
                mar=mar,
                say=lambda m: console.print(
                    f"  {'MAR: ' if mar else 'motion: ' if compensate_motion else ''}{m}",
                    highlight=False,
                ),
                motion_out=motion_out,
                times_path=times,
                fit_progress=fitted,
                iterative=iterative,
                views_every=views_every,
                iteration_progress=views_done(bar, f"{method.upper()}: subsets", "subsets"),
            )
    except (ValueError, OSError) as err:
        fail(str(err))
    grid = result.volume.grid
    console.print(
        f"[green]wrote[/] {out}: {grid.size_xyz} voxels of {grid.spacing_mm[0]:.3g} mm in "
        f"{time.perf_counter() - start:.1f} s; {100 * (1 - result.mask.mean()):.1f} % of voxels "
        f"masked (seen over < {min_coverage_deg:g} deg)",
        soft_wrap=True,
        highlight=False,
    )


@app.command()
def scan(
    study: Annotated[Path, typer.Option(help="study folder: new, or the one to --resume")],
    protocol: Annotated[
        Path | None, typer.Option(help="scan protocol YAML (a new study needs one)")
    ] = None,
    backend: Annotated[str, typer.Option(help="sim or ur")] = "sim",
    backend_config: Annotated[
        Path | None, typer.Option(help="backend YAML (default configs/backends/BACKEND.yaml)")
    ] = None,
    scanner: Annotated[Path, typer.Option(help="scanner hardware YAML")] = CONFIGS / "scanner.yaml",
    phantom: Annotated[Path, typer.Option(help="knee phantom the simulated panel images")] = CONFIGS
    / "phantoms"
    / "knee.yaml",
    phantom_voxel_mm: Annotated[float, typer.Option(help="phantom raster for the panel, mm")] = 1.0,
    recon_voxel_mm: Annotated[
        float, typer.Option(help="voxel of the volume reconstructed during the scan, mm")
    ] = 1.0,
    yes: Annotated[bool, typer.Option("--yes", help="answer yes to every confirmation")] = False,
    resume: Annotated[
        bool, typer.Option("--resume", help="continue STUDY with the views not yet stored")
    ] = False,
    move_to_start: Annotated[
        bool,
        typer.Option(
            "--move-to-start", help="first move the scanner from where it stands to the start"
        ),
    ] = False,
    park: Annotated[
        bool,
        typer.Option("--park", help="park the scanner after the scan, or after a fault's SAFE"),
    ] = False,
) -> None:
    """Scan: preflight, approach, acquire view by view (stored as acquired), retreat; every
    stored view is reconstructed while the scan goes on (weighted FDK), and the volume is the
    study's recon stage when the last view is in.

    Any fault (device error, protective stop, off-pose arm, open interlock, Ctrl-C) switches
    the X-ray off, then stops the arms, and marks the study incomplete; --resume continues it.
    --move-to-start and --park move the scanner as cbct move does, in the same session.
    """
    from scanner.backends import load_backend_spec
    from scanner.scan import OperatorDeclined, ScanFault
    from scanner.scan import Progress as ScanProgress
    from scanner.session import read_inputs, run_session
    from scanner.study import Study, StudyError
    from study.live_recon import LiveRecon
    from study.stages import recon_stage

    config = backend_config or CONFIGS / "backends" / f"{backend}.yaml"
    check_range("--recon-voxel-mm", recon_voxel_mm, 0.1, 4.0, "mm")
    check_range("--phantom-voxel-mm", phantom_voxel_mm, 0.25, 4.0, "mm")
    try:
        if resume:
            if protocol is not None:
                fail("--resume continues the study with its own protocol: drop --protocol")
            scanned = Study.open(study).stage("scan")
            if scanned.get("status") == "complete":
                console.print(
                    f"[green]scan complete already[/]: {scanned.get('views')} views in "
                    f"{study / 'scan'}; nothing to resume",
                    soft_wrap=True,
                    highlight=False,
                )
                raise typer.Exit(0)
            inputs = None
            override = load_backend_spec(backend, config) if backend_config else None
        else:
            if protocol is None:
                fail("a new study needs --protocol")
            inputs = read_inputs(
                protocol, scanner, backend, config, phantom, phantom_voxel_mm=phantom_voxel_mm
            )
            override = None
    except (ValueError, OSError, StudyError) as err:
        fail(str(err))

    confirm = _confirmation(yes)
    bar = Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        TextColumn("{task.completed}/{task.total} views"),
        TextColumn("{task.fields[dose]:.1f} mAs"),
        TextColumn("recon backlog {task.fields[backlog]} views"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=console,
    )
    task = None
    live = LiveRecon(recon_voxel_mm)
    last_view = time.perf_counter()
    backlog_at_end = 0

    def progress(p: ScanProgress) -> None:
        nonlocal task, last_view, backlog_at_end
        if task is None:
            task = bar.add_task("acquiring", total=p.views, dose=0.0, backlog=0)
        bar.update(task, completed=p.views_done, dose=p.dose_mas, backlog=live.backlog)
        last_view, backlog_at_end = time.perf_counter(), live.backlog

    try:
        with bar:
            done = run_session(
                study,
                inputs,
                resume=resume,
                backend_override=override,
                confirm=confirm,
                progress=progress,
                say=lambda msg: console.print(f"  {msg}", highlight=False),
                sink=live,
                move_to_start=move_to_start,
                park=park,
            )
    except ScanFault as err:
        live.close()
        fail(
            f"{err}\n  the study keeps every stored view; continue with: cbct scan --resume "
            f"--study {study}",
            FAILED,
        )
    except OperatorDeclined as err:
        live.close()
        fail(
            f"{err}; the study keeps its plan: start the scan with cbct scan --resume "
            f"--study {study}"
        )
    except (ValueError, OSError, RuntimeError) as err:
        live.close()
        fail(str(err))
    except KeyboardInterrupt as err:  # a stop signal before anything moved, or after the scan
        live.close()
        fail(f"{err or 'interrupted'}; continue with: cbct scan --resume --study {study}", FAILED)
    try:
        with views_progress() as bar:
            recon_stage(
                done,
                recon_voxel_mm,
                result=live.finish(),
                written=live.volume_path,
                say=lambda m: console.print(f"  recon: {m}", highlight=False),
                iteration_progress=views_done(bar, "recon: iterations", "subsets"),
            )
    except (ValueError, OSError, RuntimeError) as err:
        fail(
            f"{err}\n  the scan is complete and kept; reconstruct it offline with: cbct recon "
            f"--projections {study}/scan/projections.mha --geometry {study}/scan/geometry.xml "
            f"--orbit {study}/scan/planned_geometry.xml --out VOLUME.nii.gz",
            FAILED,
        )
    ready = time.perf_counter() - last_view
    stage = done.stage("scan")
    console.print(
        f"[green]scan complete[/]: {stage['views']} views, {stage['dose_mas']:.1f} mAs in "
        f"{study / 'scan'} (projections.mha, geometry.xml; recording: rerun "
        f"{study / 'scan' / 'recording.rrd'})",
        soft_wrap=True,
        highlight=False,
    )
    console.print(
        f"[green]volume[/] reconstructed during the scan (backlog at the last view: "
        f"{backlog_at_end} views; recon stage written {ready:.1f} s after it): "
        f"{study / 'recon' / 'volume.nii.gz'} (+ .mha, dicom/, slices.png)",
        soft_wrap=True,
        highlight=False,
    )


@app.command()
def move(
    study: Annotated[Path, typer.Option(help="study folder whose scan was started")],
    to: Annotated[str, typer.Option(help="start (the plan's first pose) or park")],
    backend_config: Annotated[
        Path | None,
        typer.Option(help="the study's backend YAML given again (default: its snapshot)"),
    ] = None,
    yes: Annotated[bool, typer.Option("--yes", help="answer yes to the confirmation")] = False,
) -> None:
    """Move the scanner from where it stands to the study plan's start or to park, on the
    study's backend: planned from the measured joints, checked (joint limits, clearance along
    the whole motion; straight, else with the arms folded), shown and confirmed; X-ray stays
    off; any fault switches the X-ray off and stops the arms."""
    from scanner.session import move_session

    if to not in ("start", "park"):
        fail(f"--to {to!r}: give start or park")
    try:
        result = move_session(
            study,
            to,
            backend_config=backend_config,
            confirm=_confirmation(yes),
            say=lambda msg: console.print(msg, highlight=False),
        )
    except (ValueError, OSError, RuntimeError) as err:
        fail(str(err))
    except KeyboardInterrupt as err:  # a stop signal before anything moved
        fail(f"{err or 'interrupted'}: nothing moved")
    how = (
        f" after {result.move.duration_s:.1f} s ({result.move.route} route)"
        if result.move
        else " (nothing moved)"
    )
    console.print(
        f"[green]at {result.target}[/]{how}: largest joint error {result.error:.3f} deg (mm)",
        soft_wrap=True,
        highlight=False,
    )


@app.command("detector-calibrate")
def detector_calibrate(
    protocol: Annotated[Path, typer.Option(help="scan protocol YAML: its panel mode and kV")],
    out: Annotated[Path, typer.Option(help="maps folder (maps go to OUT/SERIAL/MODE.npz)")],
    backend: Annotated[str, typer.Option(help="sim or ur")] = "sim",
    backend_config: Annotated[
        Path | None, typer.Option(help="backend YAML (default configs/backends/BACKEND.yaml)")
    ] = None,
    scanner: Annotated[Path, typer.Option(help="scanner hardware YAML")] = CONFIGS / "scanner.yaml",
    frames: Annotated[int, typer.Option(help="dark and flood frames to average, each")] = 16,
    yes: Annotated[bool, typer.Option("--yes", help="answer yes to the confirmation")] = False,
) -> None:
    """Calibrate the flat panel: FRAMES dark frames (X-ray off), FRAMES flood frames (nothing
    in the beam, at the protocol's technique: confirmed first), then darks again; offset,
    gain, defect and lag maps derived and stored with the panel's serial number, mode and date.
    A scan uses them when its backend config's detector_maps names OUT, and refuses maps of
    another panel, mode or kV, or older than max_map_age_days."""
    from scanner.detector_calibration import MAX_FRAMES, MIN_FRAMES, calibrate_session
    from scanner.scan import OperatorDeclined
    from scanner.session import read_inputs

    check_range("--frames", frames, MIN_FRAMES, MAX_FRAMES, "frames")
    config = backend_config or CONFIGS / "backends" / f"{backend}.yaml"
    try:
        inputs = read_inputs(protocol, scanner, backend, config, CONFIGS / "phantoms" / "knee.yaml")
    except (ValueError, OSError) as err:
        fail(str(err))
    with views_progress() as bar:
        try:
            maps, path = calibrate_session(
                inputs,
                out,
                frames,
                confirm=_confirmation(yes),
                progress=views_done(bar, "dark and flood frames", "frames"),
                say=lambda msg: console.print(msg, highlight=False),
            )
        except OperatorDeclined as err:
            fail(str(err))
        except (ValueError, OSError, RuntimeError) as err:
            fail(str(err))
        except KeyboardInterrupt as err:
            fail(f"{err or 'interrupted'}: X-ray off, nothing written")
    s = maps.summary()
    console.print(
        f"[green]maps written[/]: {path}\n  offset {s['offset_adu_median']:.0f} ADU, flood "
        f"{s['flood_adu_median']:.0f} ADU above it, dark noise {s['dark_noise_adu']:.2f} ADU, "
        f"lag {s['lag']:.3f}\n  {s['defective_pixels']} defective pixels; defective rows "
        f"{s['defective_rows']}, columns {s['defective_cols']}",
        soft_wrap=True,
        highlight=False,
    )


def _confirmation(yes: bool):
    """The operator's yes/no: asked on the console, or answered yes by --yes (and said)."""

    def confirm(question: str) -> bool:
        if yes:
            console.print(f"{question} [bold]yes[/] (--yes)", soft_wrap=True, highlight=False)
            return True
        try:
            return typer.confirm(question, default=False, err=True)
        except typer.Abort:  # no answer: end of input, or Ctrl-D
            console.print(
                "\n[yellow]no answer[/] (no terminal to answer on?): taken as no; give --yes "
                "to answer yes without a terminal",
                soft_wrap=True,
                highlight=False,
            )
            return False

    return confirm


@app.command()
def segment(
    volume: Annotated[
        Path,
        typer.Option(help="static knee scan: .nii.gz, .nii, .mha, .mhd, or a DICOM CT folder"),
    ],
    out: Annotated[Path, typer.Option(help="new label volume (.nii.gz, .nii, .mha or .mhd)")],
    unit: Annotated[
        str | None,
        typer.Option(help="the scan's unit where its file does not say: hu or 1/mm"),
    ] = None,
    side: Annotated[
        str | None, typer.Option(help="right or left knee (default: found from the fibula)")
    ] = None,
    meshes: Annotated[
        Path | None, typer.Option(help="also write one bone surface (STL) per bone here")
    ] = None,
    effective_energy_kev: Annotated[
        float, typer.Option(help="effective energy HU are converted to 1/mm at, keV")
    ] = DEFAULT_EFFECTIVE_ENERGY_KEV,
) -> None:
    """Label the bones of a static knee scan as the demo does: air 0, soft tissue 1, femur 2,
    tibia 3, fibula 4, patella 5 (the labels register, assess and export read)."""
    import numpy as np

    from recon.io import VOLUME_SUFFIXES
    from registration.labels import LABELS
    from scanner.outputs import Output, new_outputs
    from study import jobs

    static_unit = _static_unit(unit, effective_energy_kev)
    if side is not None and side not in ("right", "left"):
        fail(f"--side {side!r}: give right or left")
    outputs = [Output(out, "--out", suffixes=VOLUME_SUFFIXES)]
    if meshes is not None:
        outputs.append(Output(meshes, "--meshes"))
    try:
        with new_outputs(*outputs) as staged:
            labels = jobs.segment_files(
                volume,
                staged[0],
                unit=static_unit,
                side=side,
                effective_energy_kev=effective_energy_kev,
                meshes=staged[1] if meshes is not None else None,
            )
    except (ValueError, OSError) as err:
        fail(str(err))
    voxel_ml = float(np.prod(labels.grid.spacing_mm)) / 1000.0
    found = ", ".join(
        f"{name} {np.count_nonzero(labels.data == value) * voxel_ml:.0f} ml"
        for name, value in LABELS.items()
        if name not in ("air", "soft_tissue")
    )
    console.print(f"[green]wrote[/] {out}: {found}", soft_wrap=True, highlight=False)


@app.command()
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
        console.print(
            f"[bold red]{insufficient_text(kin)}[/] The report, marked so, is at "
            f"{out / 'report.html'}.",
            soft_wrap=True,
            highlight=False,
        )
        raise typer.Exit(1)
    console.print(
        f"[green]wrote[/] {out / 'report.html'}: {measured_text(kin)}, flexion "
        f"{np.nanmin(kin.flexion_deg):.0f}..{np.nanmax(kin.flexion_deg):.0f} deg, max |MLD| "
        f"{np.nanmax(np.abs(kin.mld_mm)):.2f} mm, {int(kin.flagged.sum())} frame(s) flagged",
        soft_wrap=True,
        highlight=False,
    )


@app.command()
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
    console.print(
        f"[green]wrote[/] {len(written)} files to {out}: 3D Slicer scene {out / 'scene.mrml'}, "
        f"ITK transforms in {out / 'itk'}, Autoscoper tracks in {out / 'autoscoper'}",
        soft_wrap=True,
        highlight=False,
    )


@app.command()
def register(
    frames: Annotated[
        list[str],
        typer.Option(
            help="fluoroscopy: .mha stack, DICOM file or folder, TIFF/PNG images "
            "(a file, a folder, a quoted glob, or one --frames per image, in order)"
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
            help="BODY=MESH: an implant component standing for the femur, tibia or "
            "patella (STL, OBJ or PLY); repeatable"
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
        Path | None, typer.Option(help="the fluoroscopy view, RTK geometry XML")
    ] = None,
    calibration: Annotated[
        Path | None,
        typer.Option(
            help="the fluoroscopy view as a JointTrack calibration (JT_INTCALIB) or an "
            "XMALab/Autoscoper MayaCam 2.0 file (with --pixel-pitch-mm)"
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
        Path | None, typer.Option(help="the panel's distortion (cbct calibrate-fluoro)")
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
    from study.jobs import ImplantSpec, RegisterInputs, RegisterOptions, register_files

    static_unit = _static_unit(unit, effective_energy_kev)
    frame_range = None if frames_range is None else _frame_range(frames_range)
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
        warp = None if distortion is None else Distortion.read(distortion)
        with new_outputs(Output(out, "--out")) as (staged,), views_progress() as bar:
            inputs = RegisterInputs(
                frames,
                geometry=geometry,
                calibration=calibration,
                volume=volume,
                labels=labels,
                implants=implants,
                truth=_poses_given("--truth", truth),
                initial=_poses_given("--initial", initial),
            )
            options = RegisterOptions(
                polarity=polarity,
                pixel_pitch_mm=pixel_pitch_mm,
                distortion=warp,
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
    console.print(line, soft_wrap=True, highlight=False)
    console.print(
        f"  JointTrack poses beside it ({', '.join(sorted(p.name for p in out.glob('*.jts')))}), "
        f"overlays in {out / 'overlays'}",
        soft_wrap=True,
        highlight=False,
    )


def _static_unit(unit: str | None, effective_energy_kev: float) -> str | None:
    """A static scan's ``--unit`` (hu or 1/mm, any case) as recon.static_volume names it, its
    ``--effective-energy-kev`` checked; the console's error otherwise."""
    units = {"hu": "HU", "1/mm": "1/mm"}
    if unit is not None and unit.lower() not in units:
        fail(f"--unit {unit!r}: give hu (CT numbers) or 1/mm (linear attenuation)")
    check_range("--effective-energy-kev", effective_energy_kev, *ENERGY_RANGE_KEV, "keV")
    return None if unit is None else units[unit.lower()]


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
    """``BODY=VALUE`` options as the tracker's body name -> value; ValueError naming the
    option and the value otherwise."""
    from study.jobs.register import body_name

    out: dict[str, str] = {}
    for item in given or ():
        body, sep, value = item.partition("=")
        if not sep or not value:
            raise ValueError(f"{option} {item!r}: give BODY=VALUE, e.g. femur=...")
        name = body_name(body.strip())
        if name in out:
            raise ValueError(f"{option}: {body} given twice")
        out[name] = value.strip()
    return out


def _attachments(given: list[str] | None) -> dict[str, tuple[tuple[Path, str], ...]]:
    """``--attach BODY=MESH:MATERIAL`` options as the tracker's body name -> its parts (mesh,
    material); ValueError naming the value otherwise."""
    from registration.implants import ATTACHABLE
    from study.jobs.register import body_name

    out: dict[str, tuple[tuple[Path, str], ...]] = {}
    for item in given or ():
        body, _, value = item.partition("=")
        mesh, _, material = value.rpartition(":")
        if not body or not mesh or material not in ATTACHABLE:
            raise ValueError(
                f"--attach {item!r}: give BODY=MESH:MATERIAL, MATERIAL one of {sorted(ATTACHABLE)}"
            )
        name = body_name(body.strip())
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


@app.command()
def demo(
    out: Annotated[Path, typer.Option(help="output folder; must not exist or be empty")] = Path(
        "demo-output"
    ),
    quick: Annotated[bool, typer.Option(help="smaller grids, fewer views and frames")] = False,
    resume: Annotated[
        bool, typer.Option("--resume", help="continue OUT: redo only the incomplete stages")
    ] = False,
    seed: Annotated[
        int, typer.Option(help="draws the simulated noise (arms, panels, fluoroscopy)")
    ] = 0,
    tka: Annotated[
        bool,
        typer.Option(
            help="a knee replacement (../shared/data/grand-challenge-tka): metal artefact "
            "reduction, the components placed on the metal and tracked through the gait"
        ),
    ] = False,
    sway_mm: Annotated[
        float,
        typer.Option(
            help="how far the standing patient sways at the knee during the static scan, mm "
            "(0: perfectly still; ~1-2 standing, ~3-5 semi-flexed); the recon stage estimates "
            "and compensates it"
        ),
    ] = 1.5,
    protocol: Annotated[
        Path | None,
        typer.Option(
            help="a scan protocol whose exposure, reconstruction (fdk, sart, tv) and share of "
            "a full protocol's 360 views the knee scan takes, of the full demo's 180 views, on "
            "the demo's panel (e.g. configs/protocols/knee_reverse_spiral_360_sparse90.yaml: "
            "44 views)"
        ),
    ] = None,
) -> None:
    """Run the main job on the simulated scanner, into one study folder: plan, calibrate,
    scan, reconstruct, segment, simulate fluoroscopy, track the bones, assess, record."""
    from scanner.scan import ScanFault
    from scanner.study import StudyError
    from study import demo as demo_job

    check_range("--sway-mm", sway_mm, 0.0, demo_job.MAX_SWAY_MM, "mm (0: still)")
    try:
        prepared = demo_job.open_demo(
            out,
            CONFIGS,
            quick=quick,
            resume=resume,
            seed=seed,
            tka=tka,
            sway_mm=sway_mm,
            protocol=protocol,
        )
    except (ValueError, OSError, StudyError) as err:
        fail(str(err))
    try:
        with views_progress() as bar:
            summary = demo_job.run(
                prepared,
                CONFIGS,
                status=lambda msg: console.print(f"  {msg}", highlight=False),
                bars=lambda description, unit: views_done(bar, description, unit),
            )
    except ScanFault as err:
        fail(f"{err}\n  continue with: cbct demo --resume --out {out}", FAILED)
    except (ValueError, OSError, RuntimeError) as err:
        fail(
            f"{err}\n  what was written is kept; continue with: cbct demo --resume --out {out}",
            FAILED,
        )
    except KeyboardInterrupt:
        fail(f"interrupted; continue with: cbct demo --resume --out {out}", FAILED)
    console.print(summary, soft_wrap=True, highlight=False)


@app.command()
def batch(
    action: Annotated[str, typer.Argument(help="recon, register, assess or all")],
    studies: Annotated[
        list[str], typer.Argument(help="study folders or globs (quoted globs; ** recurses)")
    ],
    scheduler: Annotated[
        str | None,
        typer.Option(help="address of a running dask scheduler (default: a local cluster)"),
    ] = None,
    workers: Annotated[
        int | None,
        typer.Option(
            help="worker processes of the local cluster, one thread each (default: one per core)"
        ),
    ] = None,
    out: Annotated[
        Path | None, typer.Option(help="new cohort folder (default: cohort-<UTC time>)")
    ] = None,
    settings: Annotated[Path, typer.Option(help="registration settings YAML")] = CONFIGS
    / "registration.yaml",
    voxel_mm: Annotated[
        float | None, typer.Option(help="recon voxel, mm (default: the study's own, else 1.0)")
    ] = None,
    timeout_s: Annotated[
        float | None,
        typer.Option(
            "--timeout",
            help="seconds to reach --scheduler and a worker on it (default: study.batch's "
            "CONNECT_TIMEOUT_S, 10 s)",
        ),
    ] = None,
) -> None:
    """Run ACTION on many studies as dask.distributed tasks, then write the cohort summary.

    recon = reconstruction + segmentation, register = registration, assess = assessment,
    all = the three in order per study (studies in parallel). Complete stages whose files
    still match their sha256 are skipped; a failed study is reported and the others go on;
    rerun the same command to finish what is missing. Writes OUT/cohort.csv, cohort.parquet
    and cohort.html (one row per study and bone). Exit status 1 when a study failed.
    """
    from scanner.study import StudyError
    from study import batch as batch_job

    if action not in batch_job.ACTIONS:
        fail(f"unknown action {action!r}: choose one of {', '.join(batch_job.ACTIONS)}")
    if scheduler is not None and workers is not None:
        fail("--workers sizes the local cluster: with --scheduler the scheduler's workers run")
    try:
        paths = batch_job.find_studies(studies)
        cohort = batch_job.new_output_folder(out)
        options = batch_job.TaskOptions(voxel_mm, batch_job.load_settings(settings))
        n = workers if workers is not None else os.cpu_count() or 1
        if scheduler is None:
            console.print(f"starting a local cluster of {n} worker process(es)", highlight=False)
        wait_s = batch_job.CONNECT_TIMEOUT_S if timeout_s is None else timeout_s
        client, cluster = batch_job.open_client(scheduler, n, wait_s)
    except (StudyError, ValueError, OSError) as err:
        fail(str(err))
    tasks = batch_job.ACTIONS[action]
    bar = Progress(
        TextColumn("{task.description:>9}"),
        BarColumn(),
        TextColumn("{task.completed}/{task.total} studies"),
        TextColumn("[red]{task.fields[failed]} failed[/]"),
        TimeElapsedColumn(),
        console=console,
    )
    bars = {t: bar.add_task(t, total=len(paths), failed=0) for t in tasks}

    def heard(outcome: batch_job.Outcome) -> None:
        failed = bar.tasks[bars[outcome.task]].fields["failed"]
        if outcome.status in ("failed", "blocked"):
            failed += 1
        bar.update(bars[outcome.task], advance=1, failed=failed)
        if outcome.status == "failed":
            bar.console.print(
                f"[bold red]failed[/] {outcome.study} ({outcome.task}): {outcome.error}",
                soft_wrap=True,
                highlight=False,
            )

    try:
        console.print(
            f"{len(paths)} studies, action {action}, scheduler {client.scheduler.address}",
            highlight=False,
        )
        link = batch_job.dashboard(client)
        console.print(
            f"dask dashboard: {link}" if link else "dask dashboard: none (needs bokeh)",
            highlight=False,
        )
        with bar:
            report = batch_job.run(client, paths, action, options, on_outcome=heard)
    except KeyboardInterrupt:
        fail("interrupted: finished stages are kept; rerun the same command to continue", FAILED)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    files = batch_job.write_cohort(cohort, paths, report, action)
    console.print(_batch_table(report, len(paths)), soft_wrap=True)
    console.print(
        f"[green]wrote[/] {files.csv}, {files.parquet.name}, {files.html.name} "
        f"in {files.html.parent}",
        soft_wrap=True,
        highlight=False,
    )
    failures = report.failures()
    if failures:
        lines = "\n".join(f"  {s}: {o.task}: {o.error}" for s, o in failures.items())
        console.print(
            f"[bold red]{len(failures)} of {len(paths)} studies failed[/] (the others are "
            f"done; fix these and rerun):\n{lines}",
            soft_wrap=True,
            highlight=False,
        )
        raise typer.Exit(FAILED)


def _batch_table(report: BatchReport, studies: int) -> Table:
    table = Table(title=f"batch: {studies} studies in {report.seconds:.1f} s")
    tasks = list(dict.fromkeys(o.task for o in report.outcomes))
    for column in ("study", *tasks):
        table.add_column(column)
    by_study: dict[str, dict[str, str]] = {}
    for o in report.outcomes:
        cell = f"{o.status} {o.seconds:.1f} s" if o.status in ("ran", "skipped") else o.status
        by_study.setdefault(o.study, {})[o.task] = cell
    for study, cells in by_study.items():
        table.add_row(Path(study).name, *(cells.get(t, "") for t in tasks))
    return table


if __name__ == "__main__":  # pragma: no cover
    app()
