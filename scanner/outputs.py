"""A command's new outputs: checked before the work, written in a temporary folder beside
their place, moved into place only when the work succeeds.

A failure (an error, Ctrl-C, a stop signal) leaves nothing at the output paths and removes
what was written; a killed process leaves its temporary folder (``.partial-PID-NAME``), which
is never taken for an output. Every console command that writes new files or folders outside
a study goes through :func:`new_outputs`.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

TEMP_PREFIX = ".partial-"
"""Start of a temporary output's name (then the process id and the output's own name)."""


@dataclass(frozen=True)
class Output:
    """One new output of a command.

    Args:
        path: Where the output goes (a file or a folder).
        option: The option that named it, for messages (e.g. ``--out``).
        suffixes: The file name endings allowed (lower case, with the dot); empty: any.
        empty_ok: An existing empty folder may take the output's place.
    """

    path: Path
    option: str
    suffixes: tuple[str, ...] = ()
    empty_ok: bool = False

    def check(self) -> Path:
        """Refuse an output that exists, has a wrong suffix or cannot be written; return the
        nearest existing folder above it (where the temporary output is made).

        Raises:
            FileExistsError: the output exists (a non-empty folder where ``empty_ok``).
            ValueError: a wrong suffix, or a file where a folder is needed above it.
            PermissionError: the folder above it cannot be written.
        """
        path = self.path
        name = path.name.lower()
        if self.suffixes and not name.endswith(self.suffixes):
            raise ValueError(
                f"{self.option} {path}: the name must end with {' or '.join(self.suffixes)}"
            )
        if path.exists() or path.is_symlink():
            empty_folder = path.is_dir() and not any(path.iterdir())
            if not (self.empty_ok and empty_folder):
                kind = "folder" if path.is_dir() else "file"
                kind += " exists and is not empty" if self.empty_ok and path.is_dir() else " exists"
                raise FileExistsError(
                    f"{self.option} {path}: the {kind}; choose a new name (nothing is overwritten)"
                )
        above = path.absolute().parent
        while not above.exists():
            above = above.parent
        if not above.is_dir():
            raise ValueError(f"{self.option} {path}: {above} is a file, not a folder")
        if not os.access(above, os.W_OK | os.X_OK):
            why = "a read-only file system" if _read_only(above) else "no permission"
            raise PermissionError(f"{self.option} {path}: cannot write in {above} ({why})")
        return above

    def staging(self, above: Path) -> Path:
        """The temporary folder of this output in ``above``; the output is written inside it
        under its own name (with any companion file, e.g. an .mhd's .raw)."""
        return above / f"{TEMP_PREFIX}{os.getpid()}-{self.path.name}"


def _read_only(folder: Path) -> bool:
    return bool(os.statvfs(folder).f_flag & os.ST_RDONLY)


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


def _move_into_place(out: Output, staging: Path) -> None:
    """Every entry the command wrote in ``staging`` to the output's folder."""
    entries = sorted(staging.iterdir())
    if not entries:
        return
    out.path.parent.mkdir(parents=True, exist_ok=True)
    for entry in entries:
        target = out.path.parent / entry.name
        replaceable = out.empty_ok and target == out.path and target.is_dir()
        if (target.exists() or target.is_symlink()) and not replaceable:
            raise FileExistsError(
                f"{out.option}: {target} appeared while the command ran; the result is kept "
                f"in {staging}"
            )
        os.replace(entry, target)
    staging.rmdir()


@contextmanager
def new_outputs(*outputs: Output) -> Iterator[list[Path]]:
    """Check every output, yield the paths to write them at, and move what was written into
    place if the block succeeds; remove it if the block fails.

    Each yielded path has its output's name, in a temporary folder beside the output. An
    output the block did not write is skipped (optional outputs). Missing folders above an
    output are made only when it is moved into place.

    Args:
        outputs: The command's new outputs.

    Raises:
        FileExistsError: an output exists (from :meth:`Output.check`, before the block).
        ValueError: a wrong suffix or a file in the way (likewise).
        PermissionError: a folder that cannot be written (likewise).
    """
    stagings = [out.staging(out.check()) for out in outputs]
    kept: list[Path] = []
    try:
        for out, staging in zip(outputs, stagings, strict=True):
            _remove(staging)  # left by an earlier process with the same id
            try:
                staging.mkdir()
            except OSError as err:  # a read-only filesystem, whatever the permissions say
                raise PermissionError(
                    f"{out.option} {out.path}: cannot write in {staging.parent} "
                    f"({err.strerror or err})"
                ) from None
        yield [staging / out.path.name for out, staging in zip(outputs, stagings, strict=True)]
        for out, staging in zip(outputs, stagings, strict=True):
            try:
                _move_into_place(out, staging)
            except OSError:
                kept.append(staging)
                raise
    finally:
        for staging in stagings:
            if staging not in kept:
                _remove(staging)


def new_folder(path: Path) -> Path:
    """Create ``path`` for output; refuse one that exists with anything in it."""
    if path.exists() and (not path.is_dir() or any(path.iterdir())):
        raise FileExistsError(f"{path} exists and is not empty: nothing is overwritten")
    path.mkdir(parents=True, exist_ok=True)
    return path
