"""The commands over whole studies: ``demo`` (the main job on the simulated scanner) and
``batch`` (the derived stages of many studies on dask.distributed, and a cohort summary)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from configs import CONFIGS
from study.console import (
    FAILED,
    check_range,
    console,
    fail,
    tell,
    views_done,
    views_progress,
)

if TYPE_CHECKING:
    from study.batch import BatchReport


def demo(
    out: Annotated[Path, typer.Option(help="output folder; must not exist or be empty")] = Path(
        "demo-output"
    ),
    size: Annotated[
        str,
        typer.Option(
            help="full; quick (smaller grids, fewer views and frames); smoke (the smallest run "
            "of every stage, to check an installation: its figures mean nothing)"
        ),
    ] = "full",
    quick: Annotated[bool, typer.Option(help="the same as --size quick")] = False,
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
    from scanner.study_folder import StudyError
    from study import demo as demo_job

    check_range("--sway-mm", sway_mm, 0.0, demo_job.MAX_SWAY_MM, "mm (0: still)")
    if size not in demo_job.SIZES:
        fail(f"--size {size}: choose one of {', '.join(demo_job.SIZES)}")
    if quick and size not in ("full", "quick"):
        fail(f"--quick is --size quick; it contradicts --size {size}")
    try:
        prepared = demo_job.open_demo(
            out,
            CONFIGS,
            size="quick" if quick else size,
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
    tell(summary)


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
    from scanner.study_folder import StudyError
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
    tell(
        f"[green]wrote[/] {files.csv}, {files.parquet.name}, {files.html.name} "
        f"in {files.html.parent}"
    )
    failures = report.failures()
    if failures:
        lines = "\n".join(f"  {s}: {o.task}: {o.error}" for s, o in failures.items())
        tell(
            f"[bold red]{len(failures)} of {len(paths)} studies failed[/] (the others are "
            f"done; fix these and rerun):\n{lines}"
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
