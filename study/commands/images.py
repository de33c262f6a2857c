"""The commands that make and read images: ``calibrate`` (per-view geometry from a steel-ball
phantom scan), ``calibrate-fluoro`` (the fluoroscopy panel's distortion from a dewarp grid's
image), ``recon`` (weighted FDK or an iterative method of RTK-format inputs) and ``segment``
(bone labels of a static scan)."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Annotated

import typer

from configs import CONFIGS
from recon.attenuation import DEFAULT_EFFECTIVE_ENERGY_KEV
from study.console import (
    check_range,
    checked_unit,
    console,
    fail,
    tell,
    views_done,
    views_progress,
)


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
    tell(
        f"[green]wrote[/] {study / 'calibration'}: {summary['calibrated_views']} of "
        f"{summary['views']} views calibrated, reprojection RMS median "
        f"{summary['reprojection_rms_px_median']:.3f} px (max "
        f"{summary['reprojection_rms_px_max']:.3f} px, worst views "
        f"{summary['worst_views']}), source deviation from the plan median "
        f"{np.median(deviation):.2f} mm"
    )
    if summary["uncalibrated_views"]:
        console.print(
            f"[yellow]views kept at their plan (too few balls):[/] {summary['uncalibrated_views']}",
            soft_wrap=True,
        )


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
    tell(
        f"[green]wrote[/] {out}: {distortion.balls} balls, residual RMS "
        f"{distortion.rms_mm:.3f} mm (max {distortion.max_mm:.3f}), largest displacement "
        f"{distortion.max_displacement_mm:.2f} mm"
    )


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
    tell(
        f"[green]wrote[/] {out}: {grid.size_xyz} voxels of {grid.spacing_mm[0]:.3g} mm in "
        f"{time.perf_counter() - start:.1f} s; {100 * (1 - result.mask.mean()):.1f} % of voxels "
        f"masked (seen over < {min_coverage_deg:g} deg)"
    )


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

    static_unit = checked_unit(unit, effective_energy_kev)
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
    tell(f"[green]wrote[/] {out}: {found}")
