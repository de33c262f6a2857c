"""What every command of the operator console ``cbct`` shares: the console and what it tells,
progress bars, errors in words with the exit statuses, and the checks of options."""

from __future__ import annotations

from collections.abc import Callable

import typer
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from recon.attenuation import ENERGY_RANGE_KEV

console = Console(stderr=True)


def tell(message: str) -> None:
    """Print ``message`` (rich markup) on the console as written: wrapped softly, so a path
    stays whole, and not highlighted, so numbers and paths keep the colours given."""
    console.print(message, soft_wrap=True, highlight=False)


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
    tell(f"[bold red]error:[/] {message}")
    raise typer.Exit(code)


def check_range(option: str, value: float, low: float, high: float | None, unit: str) -> None:
    """:func:`fail` unless ``low <= value <= high`` (``high`` None: no upper limit; NaN is
    refused), naming the option, the value and the limits."""
    if not (low <= value and (high is None or value <= high)):
        limits = f"{low:g} or more" if high is None else f"{low:g} to {high:g}"
        fail(f"{option} {value:g}: give {limits} {unit}".rstrip())


def confirmation(yes: bool):
    """The operator's yes/no: asked on the console, or answered yes by --yes (and said)."""

    def confirm(question: str) -> bool:
        if yes:
            tell(f"{question} [bold]yes[/] (--yes)")
            return True
        try:
            return typer.confirm(question, default=False, err=True)
        except typer.Abort:  # no answer: end of input, or Ctrl-D
            tell(
                "\n[yellow]no answer[/] (no terminal to answer on?): taken as no; give --yes "
                "to answer yes without a terminal"
            )
            return False

    return confirm


def checked_unit(unit: str | None, effective_energy_kev: float) -> str | None:
    """A static scan's ``--unit`` (hu or 1/mm, any case) as recon.static_volume names it, its
    ``--effective-energy-kev`` checked; the console's error otherwise."""
    units = {"hu": "HU", "1/mm": "1/mm"}
    if unit is not None and unit.lower() not in units:
        fail(f"--unit {unit!r}: give hu (CT numbers) or 1/mm (linear attenuation)")
    check_range("--effective-energy-kev", effective_energy_kev, *ENERGY_RANGE_KEV, "keV")
    return None if unit is None else units[unit.lower()]
