"""The acquisition commands: ``plan`` (checked, timed robot motion for a protocol),
``simulate-scan`` (a digital phantom scanned into files), ``scan`` (a study's scan, reconstructed
while it is acquired), ``move`` (the scanner to a study plan's start or to park) and
``detector-calibrate`` (the panel's darks and floods)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated

import typer
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

from configs import CONFIGS
from study.console import (
    FAILED,
    check_range,
    confirmation,
    console,
    fail,
    tell,
    views_done,
    views_progress,
)


def plan(
    protocol: Annotated[Path, typer.Option(help="scan protocol YAML (configs/protocols/)")],
    out: Annotated[Path, typer.Option(help="study folder; the plan goes to OUT/plan")],
    scanner: Annotated[Path, typer.Option(help="scanner hardware YAML")] = CONFIGS / "scanner.yaml",
) -> None:
    """Plan a protocol on the scanner: IK, collision and limit checks, timing, a recording.

    OUT becomes a study folder holding the plan: cbct scan --study OUT scans it."""
    from scanner.outputs import Output, new_outputs
    from scanner.session import plan_study

    try:
        with new_outputs(Output(out, "--out", empty_ok=True)) as (staged,):
            with views_progress() as bar:
                result = plan_study(
                    protocol, staged, scanner, progress=views_done(bar, "inverse kinematics")
                )
    except (ValueError, OSError) as err:
        fail(str(err))
    console.print(_plan_table(result), soft_wrap=True)
    tell(
        f"[green]wrote[/] {out / 'plan'} and {out / 'plan' / 'recording.rrd'} "
        f"(open with: rerun {out / 'plan' / 'recording.rrd'}); scan it with: cbct scan "
        f"--study {out} --protocol {protocol}"
    )


def _plan_table(result) -> Table:
    summary = result.summary()
    table = Table(title=f"plan: {summary['protocol']}", show_header=False)
    where = summary["min_clearance_at"]
    rows = [
        ("views", str(summary["views"])),
        (
            "duration",
            f"{summary['duration_s']:.1f} s (scan {summary['scan_duration_s']:.1f} s, "
            f"{summary['duration_ratio']:.3f} x the slowest axis' bound)",
        ),
        (
            "min clearance",
            f"{summary['min_clearance_mm']:.1f} mm (margin "
            f"{summary['clearance_margin_mm']:g} mm): {' / '.join(where['pair'])}, "
            f"{where['phase']} at {where['time_s']:.2f} s",
        ),
        (
            "max joint speed",
            f"{100 * summary['max_speed_share']:.0f} % of the limit ({summary['max_speed_joint']})",
        ),
        (
            "max pose error",
            f"{summary['max_pose_error_mm']:.2e} mm, {summary['max_pose_error_deg']:.2e} deg",
        ),
        ("planning time", f"{summary['plan_s']:.2f} s"),
    ]
    for name, value in rows:
        table.add_row(name, value)
    return table


def simulate_scan(
    protocol: Annotated[Path, typer.Option(help="scan protocol YAML (configs/protocols/)")],
    out: Annotated[Path, typer.Option(help="output folder; must not exist or be empty")],
    phantom: Annotated[str, typer.Option(help="knee, or bb (steel-ball calibration)")] = "knee",
    phantom_config: Annotated[
        Path | None, typer.Option(help="phantom YAML (default configs/phantoms/<phantom>)")
    ] = None,
    voxel_mm: Annotated[float, typer.Option(help="knee simulation voxel size, mm")] = 0.5,
    seed: Annotated[int, typer.Option(help="noise seed")] = 0,
    noise: Annotated[bool, typer.Option(help="quantum and readout noise")] = True,
    vibration_mm: Annotated[
        float, typer.Option(help="RMS arm vibration of source and panel, mm (0: none)")
    ] = 0.0,
    vibration_deg: Annotated[float, typer.Option(help="RMS panel tilt, degrees")] = 0.0,
    vibration_seed: Annotated[int, typer.Option(help="vibration pattern (repeats per seed)")] = 0,
    sway_mm: Annotated[
        float,
        typer.Option(
            help="knee: how far the standing patient sways at the knee during the scan, mm "
            "(0: still; ~1-2 standing, ~3-5 semi-flexed); the truth goes to true_motion.csv"
        ),
    ] = 0.0,
    sway_seed: Annotated[int, typer.Option(help="sway pattern (repeats per seed)")] = 0,
) -> None:
    """Scan a digital phantom: projections .mha, the planned geometry .xml (and the acquired
    one, true_geometry.xml, on vibrating arms), phantom volumes for the knee."""
    from scanner.outputs import Output, new_outputs
    from sim.sway import SwaySpec
    from sim.vibration import VibrationSpec
    from study.jobs.simulate import simulate_to_folder

    if phantom_config is None:
        phantom_config = (
            CONFIGS / "phantoms" / ("knee.yaml" if phantom == "knee" else "bb_helix.yaml")
        )
    check_range("--voxel-mm", voxel_mm, 0.05, 10.0, "mm")
    check_range("--vibration-mm", vibration_mm, 0.0, None, "mm (0: no vibration)")
    check_range("--vibration-deg", vibration_deg, 0.0, None, "degrees (0: no vibration)")
    check_range("--sway-mm", sway_mm, 0.0, 20.0, "mm (0: still)")
    if sway_mm > 0 and phantom != "knee":
        fail(f"--sway-mm {sway_mm:g}: only the knee phantom's patient sways")
    vibration = None
    if vibration_mm > 0 or vibration_deg > 0:
        try:
            vibration = VibrationSpec(
                source_mm=vibration_mm,
                detector_mm=vibration_mm,
                detector_deg=vibration_deg,
                seed=vibration_seed,
            )
        except ValueError as err:
            fail(str(err))
    try:
        staging = new_outputs(Output(out, "--out", empty_ok=True))
        with staging as (staged,), views_progress() as bar:
            written = simulate_to_folder(
                protocol,
                staged,
                phantom,
                phantom_config,
                voxel_mm=voxel_mm,
                seed=seed,
                noise=noise,
                vibration=vibration,
                sway=SwaySpec(peak_mm=sway_mm, seed=sway_seed) if sway_mm > 0 else None,
                status=lambda msg: bar.console.print(f"  {msg}"),
                progress=views_done(bar, "projecting the phantom"),
            )
    except (ValueError, OSError) as err:
        fail(str(err))
    tell(
        f"[green]wrote[/] {len(written)} files to {out} (projections.mha, geometry.xml, scan.json)"
    )


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
    from scanner.inputs import load_backend_spec, read_inputs
    from scanner.scan import OperatorDeclined, ScanFault
    from scanner.scan import Progress as ScanProgress
    from scanner.session import run_session
    from scanner.study_folder import Study, StudyError
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
                tell(
                    f"[green]scan complete already[/]: {scanned.get('views')} views in "
                    f"{study / 'scan'}; nothing to resume"
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

    confirm = confirmation(yes)
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
    tell(
        f"[green]scan complete[/]: {stage['views']} views, {stage['dose_mas']:.1f} mAs in "
        f"{study / 'scan'} (projections.mha, geometry.xml; recording: rerun "
        f"{study / 'scan' / 'recording.rrd'})"
    )
    tell(
        f"[green]volume[/] reconstructed during the scan (backlog at the last view: "
        f"{backlog_at_end} views; recon stage written {ready:.1f} s after it): "
        f"{study / 'recon' / 'volume.nii.gz'} (+ .mha, dicom/, slices.png)"
    )


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
            confirm=confirmation(yes),
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
    tell(f"[green]at {result.target}[/]{how}: largest joint error {result.error:.3f} deg (mm)")


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
    from scanner.inputs import read_inputs
    from scanner.scan import OperatorDeclined

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
                confirm=confirmation(yes),
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
    tell(
        f"[green]maps written[/]: {path}\n  offset {s['offset_adu_median']:.0f} ADU, flood "
        f"{s['flood_adu_median']:.0f} ADU above it, dark noise {s['dark_noise_adu']:.2f} ADU, "
        f"lag {s['lag']:.3f}\n  {s['defective_pixels']} defective pixels; defective rows "
        f"{s['defective_rows']}, columns {s['defective_cols']}"
    )
