"""The study folder (docs/design.md): one scan session, written stage by stage, never rewritten.

``study.json`` is the manifest: software version, the config snapshot the study was made with,
each stage's status (``complete`` or ``incomplete`` with the reason), and the sha256 of every
file written. Every file goes through :meth:`Study.write`: written to a temporary name in its
folder, flushed to disk, then renamed into place and the folder flushed too (its new name
survives a power loss), so a file either exists whole or not at all; an existing file is never
replaced. The manifest itself is replaced atomically the same way.
Files in memory with a record of them (an acquired view's images and the record naming their
sha256) go through :meth:`Study.write_with_record`: written, fsynced and hashed from memory
concurrently on worker threads, the record renamed into place last.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import os
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor, wait
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

MANIFEST = "study.json"
STAGES = (
    "detector",
    "plan",
    "calibration_scan",
    "calibration",
    "scan",
    "recon",
    "segmentation",
    "placement",
    "fluoro",
    "registration",
    "assessment",
    "recording",
)


_IO = ThreadPoolExecutor(max_workers=4, thread_name_prefix="study-io")
"""Threads that write and fsync files and hash them, a view's two images and their two hashes
at once (hashlib on large buffers, os.write and os.fsync release the GIL)."""


_RECORDS = ThreadPoolExecutor(max_workers=1, thread_name_prefix="study-records")
"""The thread that writes a record once its files' hashes are in and renames them all into
place (apart from the files' own workers, so that it never waits on a busy pool)."""


class StudyError(RuntimeError):
    """A study folder that cannot be created, opened or trusted; the message says why."""


def sha256(path: Path) -> str:
    """The file's SHA-256, hex (read in 1 MiB blocks)."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def software_version() -> str:
    """This package's version (pyproject.toml), "unknown" when it is not installed."""
    try:
        return version("dualarm-cbct")
    except PackageNotFoundError:  # pragma: no cover - running from a bare checkout
        return "unknown"


def _now() -> str:
    return dt.datetime.now(dt.UTC).isoformat(timespec="seconds")


def _temporary(target: Path) -> Path:
    """The name a file of the study is written under before it is renamed to ``target``."""
    return target.with_name(f".{target.stem}.tmp{target.name[len(target.stem) :]}")


def _sha256_of(parts: Sequence) -> str:
    """The sha256 of ``parts`` (bytes-like) one after the other."""
    digest = hashlib.sha256()
    for part in parts:
        digest.update(part)
    return digest.hexdigest()


def _write_synced(path: Path, parts: Sequence) -> None:
    """Write ``parts`` to ``path`` (created, or a file reserved by :meth:`Study.reserve`: its
    allocated space written over, then cut to the length written) and fsync it."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT, 0o644)
    try:
        length = 0
        for part in parts:
            view = memoryview(part).cast("B")
            length += len(view)
            while view:
                view = view[os.write(fd, view) :]
        os.ftruncate(fd, length)
        os.fsync(fd)
    finally:
        os.close(fd)


def fsync_folder(folder: Path) -> None:
    """Flush a folder's entries (names created, renamed or removed in it) to disk."""
    fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def make_folder(folder: Path) -> None:
    """Create ``folder`` and its missing parents, each new name flushed to disk."""
    if folder.is_dir():
        return
    if folder.exists():
        raise NotADirectoryError(f"{folder} is a file, not a folder")
    make_folder(folder.parent)
    folder.mkdir(exist_ok=True)
    fsync_folder(folder.parent)


def _replace_atomically(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
        fsync_folder(path.parent)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


class PendingWrite:
    """Files being written with their record (:meth:`Study.start_write_with_record`)."""

    def __init__(self, study: Study, done: Future) -> None:
        self._study, self._done = study, done
        self._recorded = False

    @property
    def done(self) -> bool:
        """Finished, stored or failed (:meth:`wait` returns or raises at once)."""
        return self._done.done()

    @property
    def failed(self) -> bool:
        """Finished, and failed (:meth:`wait` raises at once)."""
        return self._done.done() and self._done.exception() is not None

    def wait(self) -> None:
        """Return once every file and the record are fsynced and renamed into place, with
        their sha256 in the manifest; raise what failed (nothing of it was left behind).
        Waiting again returns (or raises) the same."""
        digests = self._done.result()  # raises what failed, again on every wait
        if not self._recorded:
            self._study.manifest["files"].update(digests)
            self._recorded = True


class Reservation:
    """New files of a study with their disk space allocated before their content exists
    (:meth:`Study.reserve`): written by :meth:`Study.start_write_with_record`, or released."""

    def __init__(self, paths: list[Path]) -> None:
        self.paths = paths
        """The files' temporary names, where they are written."""

    def release(self) -> None:
        """Remove the reserved files (when nothing will be written to them)."""
        for path in self.paths:
            path.unlink(missing_ok=True)


class Study:
    """An open study folder. Create with :meth:`create`, reopen with :meth:`open`."""

    def __init__(self, path: Path, manifest: dict) -> None:
        self.path = path
        self.manifest = manifest

    @classmethod
    def create(cls, path: str | Path, config: dict) -> Study:
        """A new study at ``path`` (which must not exist, or be an empty folder)."""
        path = Path(path)
        if path.exists() and (not path.is_dir() or any(path.iterdir())):
            raise StudyError(
                f"{path} exists and is not empty: a study is never overwritten "
                "(choose a new folder, or continue it with --resume)"
            )
        make_folder(path)
        manifest = {
            "software_version": software_version(),
            "created": _now(),
            "config": config,
            "stages": {},
            "files": {},
        }
        study = cls(path, manifest)
        study.save()
        return study

    @classmethod
    def open(cls, path: str | Path) -> Study:
        """An existing study; raises StudyError when ``path`` is not one."""
        path = Path(path)
        manifest_path = path / MANIFEST
        if not manifest_path.is_file():
            raise StudyError(f"{path} is not a study folder: no {MANIFEST}")
        try:
            manifest = json.loads(manifest_path.read_text(encoding="utf-8"))
        except (OSError, ValueError) as err:  # JSON and UTF-8 errors are ValueErrors
            raise StudyError(f"{manifest_path} is unreadable: {err}") from err
        if not isinstance(manifest, dict):
            raise StudyError(f"{manifest_path} holds a {type(manifest).__name__}, not an object")
        missing = {"config", "stages", "files"} - set(manifest)
        if missing:
            raise StudyError(f"{manifest_path} lacks {sorted(missing)}")
        for key in ("config", "stages", "files"):
            if not isinstance(manifest[key], dict):
                raise StudyError(f"{manifest_path}: {key!r} is not an object")
        return cls(path, manifest)

    def save(self) -> None:
        """Write the manifest (atomically)."""
        data = json.dumps(self.manifest, indent=2).encode("utf-8")
        _replace_atomically(self.path / MANIFEST, data)

    def _new(self, relpath: str) -> Path:
        """The path of a new file of the study, its folder made; StudyError if it exists."""
        target = self.path / relpath
        if target.exists():
            raise StudyError(f"{target} exists: files of a study are never rewritten")
        make_folder(target.parent)
        return target

    def write(self, relpath: str, writer: Callable[[Path], object]) -> Path:
        """Write one file of the study: ``writer(tmp_path)`` writes it, then it is renamed to
        ``relpath`` and its sha256 recorded. Refuses a file that exists."""
        target = self._new(relpath)
        tmp = _temporary(target)
        tmp.unlink(missing_ok=True)
        try:
            writer(tmp)
            with open(tmp, "rb+") as fh:
                os.fsync(fh.fileno())
            os.replace(tmp, target)
            fsync_folder(target.parent)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        self.manifest["files"][relpath] = sha256(target)
        return target

    def reserve(self, sizes: dict[str, int]) -> Reservation:
        """Allocate the disk space of new files before their content exists (e.g. before the
        pulse that makes it): each created under its temporary name with ``sizes[relpath]``
        bytes allocated; :meth:`start_write_with_record` then writes them within that space.
        Raises StudyError, and leaves nothing, when the disk cannot take them or one exists."""
        reservation = Reservation([_temporary(self._new(relpath)) for relpath in sizes])
        try:
            for path, size in zip(reservation.paths, sizes.values(), strict=True):
                fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
                try:
                    os.posix_fallocate(fd, 0, size)
                finally:
                    os.close(fd)
        except OSError as err:
            reservation.release()
            need = sum(sizes.values()) / 2**20
            raise StudyError(
                f"cannot reserve {need:.2f} MiB for {', '.join(sizes)} on the study's disk: "
                f"{err.strerror or err}"
            ) from err
        except BaseException:
            reservation.release()
            raise
        return reservation

    def write_with_record(
        self,
        files: dict[str, Sequence],
        record: str,
        content: Callable[[dict[str, str]], bytes],
    ) -> None:
        """Write new files from memory and then the record of them, e.g. a view's images and
        the JSON that names their sha256; returns once all are in place
        (:meth:`start_write_with_record`, then :meth:`PendingWrite.wait`)."""
        self.start_write_with_record(files, record, content).wait()

    def start_write_with_record(
        self,
        files: dict[str, Sequence],
        record: str,
        content: Callable[[dict[str, str]], bytes],
    ) -> PendingWrite:
        """Start writing new files from memory and then the record of them; the files exist
        (and are in the manifest) once :meth:`PendingWrite.wait` has returned.

        ``files`` maps each path to its parts (bytes-like, C-contiguous, not changed until the
        wait returns; written one after the other; reserved by :meth:`reserve` or not). Each
        file is written and fsynced under its temporary name on a worker thread, and hashed on
        another at the same time; once the hashes are in, ``content(sha256 of each file)`` is
        written as the ``record``, fsynced too; then the files are renamed into place and the
        record last, so the record exists only once its files do, and their folder is flushed
        (the wait returns once the names would survive a power loss). Every sha256 is recorded
        in the manifest (hashed from memory: nothing is read back). Refuses a file that exists
        (at once); on failure no temporary file is left and the wait raises."""
        targets = {relpath: self._new(relpath) for relpath in (*files, record)}
        tmps = {relpath: _temporary(target) for relpath, target in targets.items()}
        # the files' writes start at once, their hashes alongside on other workers (hashlib
        # and os.write release the GIL); the record follows once the hashes are in
        writing = [_IO.submit(_write_synced, tmps[r], parts) for r, parts in files.items()]
        hashing = {relpath: _IO.submit(_sha256_of, parts) for relpath, parts in files.items()}

        def finish() -> dict[str, str]:
            pending = [*writing, *hashing.values()]
            try:
                digests = {relpath: digest.result() for relpath, digest in hashing.items()}
                data = content(dict(digests))
                _write_synced(tmps[record], (data,))
                for done in writing:
                    done.result()
                for relpath, target in targets.items():
                    os.replace(tmps[relpath], target)
                for folder in {target.parent for target in targets.values()}:
                    fsync_folder(folder)  # the new names on disk: stored means stored
            except BaseException:
                wait(pending)
                for tmp in tmps.values():
                    tmp.unlink(missing_ok=True)
                raise
            digests[record] = _sha256_of((data,))
            return digests

        return PendingWrite(self, _RECORDS.submit(finish))

    def write_json(self, relpath: str, payload: dict) -> Path:
        text = json.dumps(payload, indent=2)
        return self.write(relpath, lambda p: p.write_text(text, encoding="utf-8"))

    def adopt(self, relpath: str) -> None:
        """Record the sha256 of a file (or every file under a folder) written by another
        component with its own atomic write (e.g. a plan saved via a temporary folder)."""
        target = self.path / relpath
        paths = sorted(p for p in target.rglob("*") if p.is_file()) if target.is_dir() else [target]
        for p in paths:
            self.manifest["files"][p.relative_to(self.path).as_posix()] = sha256(p)

    def stage(self, name: str) -> dict:
        """The stage's status record ({} when not started)."""
        return self.manifest["stages"].get(name, {})

    def mark(self, name: str, status: str, **details: object) -> None:
        """Set a stage's status (``complete`` / ``incomplete``) with details, and save."""
        if name not in STAGES:
            raise StudyError(f"unknown stage {name!r}; stages are {STAGES}")
        if status not in ("complete", "incomplete"):
            raise StudyError(f"stage status must be complete or incomplete, got {status!r}")
        self.manifest["stages"][name] = {"status": status, "updated": _now(), **details}
        self.save()

    def verify(self, prefix: str = "") -> list[str]:
        """Files under ``prefix`` whose content no longer matches the manifest (or are gone)."""
        bad = []
        for relpath, digest in self.manifest["files"].items():
            if relpath.startswith(prefix):
                path = self.path / relpath
                if not path.is_file() or sha256(path) != digest:
                    bad.append(relpath)
        return bad
