"""The operator console ``cbct``: its app, built here from every command.

The commands live by what they work on: :mod:`study.commands.acquire` (``plan``,
``simulate-scan``, ``scan``, ``move``, ``detector-calibrate``), :mod:`study.commands.images`
(``calibrate``, ``calibrate-fluoro``, ``recon``, ``segment``), :mod:`study.commands.kinematics`
(``register``, ``assess``, ``export``) and :mod:`study.commands.studies` (``demo``, ``batch``);
what they share is :mod:`study.console`. Every command checks its inputs before long work starts,
never overwrites an existing output, writes its outputs through scanner.outputs (nothing at
``--out`` after a failure), and shows progress on long work. Each command imports what it uses
when it runs (``cbct --help`` and ``cbct scan`` load no registration, cohort or plotting code).
"""

from __future__ import annotations

from typing import Annotated

import typer

from study.commands import acquire, images, kinematics, studies

__all__ = ["app"]

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    rich_markup_mode="markdown",
)


def _version(show: bool) -> None:
    if show:
        from scanner.study_folder import software_version

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


COMMANDS = (
    acquire.plan,
    acquire.simulate_scan,
    images.calibrate,
    images.calibrate_fluoro,
    images.recon,
    acquire.scan,
    acquire.move,
    acquire.detector_calibrate,
    images.segment,
    kinematics.assess,
    kinematics.export,
    kinematics.register,
    studies.demo,
    studies.batch,
)
"""Every command, in the order ``cbct --help`` lists them (each named after its function,
underscores as dashes)."""

for command in COMMANDS:
    app.command(command.__name__.replace("_", "-"))(command)


if __name__ == "__main__":  # pragma: no cover
    app()
