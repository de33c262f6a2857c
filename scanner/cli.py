"""The operator console ``cbct``: its acquisition commands and what every command shares.

Here: ``plan`` (checked, timed robot motion for a protocol) and ``simulate-scan`` (scan a
digital phantom with a protocol). The study pipeline's commands join this app in study.cli,
which is the console's entry point (``cbct scan`` is there: it reconstructs while it
acquires). Every command checks its inputs before long work starts, never
overwrites an existing output, and shows progress on long work. Each command imports what it
uses when it runs: ``cbct --help`` loads none of the science.
"""

from __future__ import annotations

from collections.abc import Callable
from importlib.resources import files
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    rich_markup_mode="markdown",
)
console = Console(stderr=True)

CONFIGS = Path(str(files("configs")))
"""The shipped configs (package data): the defaults of every command's config options."""


def _version(show: bool) -> None:
    if show:
        from scanner.study import software_version

        print(f"dualarm-cbct {software_version()}")
        raise typer.Exit()


@app.callback()
def main(
    version: Annotated[
        bool,
        typer.Option("--version", callback=_version, is_eager=True, help="print the version"),
    ] = False,
) -> None:
    """dualarm-cbct operator console: plan, scan, calibrate, reconstruct, register, assess."""


def views_progress() -> Progress:
    """Progress bars of counted work (views, frames, ...), with elapsed and remaining time, on
    the console."""
    return Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        TextColumn("{task.completed}/{task.total} {task.fields[unit]}"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=console,
        transient=False,
    )


def views_done(bar: Progress, description: str, unit: str = "views") -> Callable[[int, int], None]:
    """A progress callback that shows its bar (``done/total unit``) from the first report on."""
    task = None

    def update(done: int, total: int) -> None:
        nonlocal task
        if task is None:
            task = bar.add_task(description, total=total, unit=unit)
        bar.update(task, completed=done, total=total)

    return update


REFUSED = 2
"""Exit status of a command that refused its input (nothing done, nothing written)."""
FAILED = 1
"""Exit status of a command whose work failed or was interrupted (what is kept is said)."""


def fail(message: str, code: int = REFUSED) -> None:
    """Print an error in words and exit with ``code``: :data:`REFUSED` (the default) or
    :data:`FAILED`."""
    console.print(f"[bold red]error:[/] {message}", soft_wrap=True, highlight=False)
    raise typer.Exit(code)


def check_range(option: str, value: float, low: float, high: float | None, unit: str) -> None:
    """:func:`fail` unless ``low <= value <= high`` (``high`` None: no upper limit; NaN is
    refused), naming the option, the value and the limits."""
    if not (low <= value and (high is None or value <= high)):
        limits = f"{low:g} or more" if high is None else f"{low:g} to {high:g}"
        fail(f"{option} {value:g}: give {limits} {unit}".rstrip())


@app.command()
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
    console.print(
        f"[green]wrote[/] {out / 'plan'} and {out / 'plan' / 'recording.rrd'} "
        f"(open with: rerun {out / 'plan' / 'recording.rrd'}); scan it with: cbct scan "
        f"--study {out} --protocol {protocol}",
        soft_wrap=True,
        highlight=False,
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


@app.command("simulate-scan")
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
    from scanner import scan_files
    from scanner.outputs import Output, new_outputs
    from sim.sway import SwaySpec
    from sim.vibration import VibrationSpec

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
            written = scan_files.simulate_to_folder(
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
    console.print(
        f"[green]wrote[/] {len(written)} files to {out} (projections.mha, geometry.xml, scan.json)",
        soft_wrap=True,
        highlight=False,
    )
