"""Storage of acquired views: files written from memory with the record naming them, and the
scan's rerun recording on its worker thread."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from recon.geometry import DetectorSpec, circular_orbit
from scanner.scan_recording import ScanRecorder
from scanner.storage import ScanStore, ViewRecord
from scanner.study_folder import Study, StudyError, sha256


def test_record_is_written_last_and_names_the_files_it_follows(tmp_path):
    study = Study.create(tmp_path / "s", {})
    image = np.arange(12, dtype=np.float32).reshape(3, 4)
    files = {"scan/views/a.mha": (b"header\n", image), "scan/views/b.bin": (b"counts",)}
    seen = {}

    def content(digests: dict[str, str]) -> bytes:
        seen.update(digests)
        assert not (study.path / "scan/views/a.mha").exists()  # nothing renamed before it
        return json.dumps(digests).encode()

    study.write_with_record(files, "scan/views/a.json", content)
    expected = {
        "scan/views/a.mha": hashlib.sha256(b"header\n" + image.tobytes()).hexdigest(),
        "scan/views/b.bin": hashlib.sha256(b"counts").hexdigest(),
    }
    assert seen == expected
    assert (study.path / "scan/views/a.mha").read_bytes() == b"header\n" + image.tobytes()
    assert json.loads((study.path / "scan/views/a.json").read_text()) == expected
    assert study.verify() == []
    assert sorted(p.name for p in (study.path / "scan/views").iterdir()) == [
        "a.json",
        "a.mha",
        "b.bin",
    ]


def test_a_stored_files_name_is_flushed_before_the_write_returns(tmp_path, monkeypatch):
    """A rename reaches the disk with its folder: the folder is fsynced after the record is
    in place and before the wait returns, else a view reported stored could come back under
    its temporary name after a power loss (and new folders are flushed into their parents)."""
    fsynced = []
    fsync = os.fsync

    def logged(fd: int) -> None:
        path = Path(os.readlink(f"/proc/self/fd/{fd}"))
        fsynced.append((path, path.is_dir() and (path / "a.json").exists()))
        fsync(fd)

    study = Study.create(tmp_path / "s", {})
    monkeypatch.setattr(os, "fsync", logged)
    study.write_with_record({"scan/views/a.mha": (b"a",)}, "scan/views/a.json", lambda _d: b"{}")
    folders = [path for path, _ in fsynced if path.is_dir()]
    assert (study.path / "scan/views", True) in fsynced  # the folder, with the record in it
    assert folders.index(study.path / "scan") < folders.index(study.path / "scan/views")
    assert study.path in folders  # scan/ made in the study's folder


def test_a_failed_record_leaves_nothing_and_nothing_is_rewritten(tmp_path):
    study = Study.create(tmp_path / "s", {})

    def broken(_digests: dict[str, str]) -> bytes:
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        study.write_with_record({"v/a.mha": (b"a",)}, "v/a.json", broken)
    assert list((study.path / "v").iterdir()) == []  # no temporary file, no half view
    study.write_with_record({"v/a.mha": (b"a",)}, "v/a.json", lambda _d: b"{}")
    with pytest.raises(StudyError, match="never rewritten"):
        study.write_with_record({"v/a.mha": (b"b",)}, "v/b.json", lambda _d: b"{}")
    assert (study.path / "v/a.mha").read_bytes() == b"a"


def test_a_failed_hash_leaves_nothing(tmp_path):
    """The files are hashed on the writer threads: a part that cannot be hashed fails the
    write before any file is renamed into place, and leaves no temporary file."""
    study = Study.create(tmp_path / "s", {})
    strided = np.arange(64, dtype=np.float32).reshape(8, 8)[:, ::2]  # not C-contiguous
    with pytest.raises((BufferError, TypeError, ValueError)):
        study.write_with_record({"v/a.mha": (b"a",), "v/b.mha": (strided,)}, "v/a.json", bytes)
    assert list((study.path / "v").iterdir()) == []
    assert not any(key.startswith("v/") for key in study.manifest["files"])


def _record(k: int) -> ViewRecord:
    matrix = np.array([[1000.0, 0, 32, 0], [0, 0, 32, 0], [0, 0, 1, 1000.0]])
    return ViewRecord(k, 0.1 * k, 0.1 * k, 0.1 * k, np.zeros(2), matrix, np.zeros(3), 80, 1, 10, k)


def test_recording_failure_stops_the_scan_at_a_later_view(tmp_path, monkeypatch):
    """The recording runs on a worker; its failure is raised by a later view() (the scan
    goes to SAFE as before) and only once, and the file is still finished on close."""
    study = Study.create(tmp_path / "s", {})
    recorder = ScanRecorder(study, ("rotary", "lift"), 1.0)
    failed = threading.Event()

    def broken(_record, _image):
        failed.set()
        raise ValueError("no space for the recording")

    monkeypatch.setattr(recorder, "_log_view", broken)
    image = np.zeros((64, 64), dtype=np.float32)
    recorder.view(_record(0), image)
    failed.wait(5.0)
    with pytest.raises(RuntimeError, match="recording failed: no space"):
        for k in range(1, 100):  # the worker records its failure right after raising
            recorder.view(_record(k), image)
    assert recorder.close() == study.path / "scan" / "recording.rrd"
    assert "scan/recording.rrd" in study.manifest["files"]


def test_an_image_left_without_its_record_is_set_aside_and_the_view_acquired_again(tmp_path):
    """A process killed between renaming a view's images and its record into place leaves the
    images without a record: not a stored view. Reopening keeps them aside (never overwritten)
    and the view can be stored; before, storing it was refused forever."""
    panel = DetectorSpec(rows=4, cols=4, pixel_pitch_mm=1.0)
    planned = circular_orbit(3, 500.0, 1000.0, panel)
    study = Study.create(tmp_path / "s", {})
    store = ScanStore(study, panel, ("rotary", "lift"), 3, planned)
    image = np.ones((4, 4), dtype=np.float32)
    store.put(_record(0), image, image)
    views = study.path / "scan" / "views"
    for name in ("view_0001.mha", "view_0001_counts.mha"):  # renamed, then killed
        (views / name).write_bytes(b"half a view")
    reopened = ScanStore(Study.open(study.path), panel, ("rotary", "lift"), 3, planned)
    assert reopened.stored == {0}
    assert sorted(p.name for p in (views / "interrupted").iterdir()) == [
        "view_0001.mha",
        "view_0001_counts.mha",
    ]
    reopened.put(_record(1), 2 * image, 2 * image)
    np.testing.assert_array_equal(reopened.image(1), 2 * image)
    again = ScanStore(Study.open(study.path), panel, ("rotary", "lift"), 3, planned)
    assert again.stored == {0, 1}


def test_an_image_set_aside_is_flushed_under_its_new_name(tmp_path, monkeypatch):
    """Setting an image aside renames it across folders: ``interrupted/`` is flushed into
    ``views/``, then both folders once the image is in ``interrupted/``; else a power loss
    after the view is stored again could lose the image set aside ("kept" was the promise)."""
    panel = DetectorSpec(rows=4, cols=4, pixel_pitch_mm=1.0)
    planned = circular_orbit(3, 500.0, 1000.0, panel)
    study = Study.create(tmp_path / "s", {})
    views = study.path / "scan" / "views"
    views.mkdir(parents=True)
    (views / "view_0001.mha").write_bytes(b"half a view")
    fsynced = []
    fsync = os.fsync

    def logged(fd: int) -> None:
        path = Path(os.readlink(f"/proc/self/fd/{fd}"))
        fsynced.append((path, (views / "interrupted" / "view_0001.mha").exists()))
        fsync(fd)

    monkeypatch.setattr(os, "fsync", logged)
    ScanStore(Study.open(study.path), panel, ("rotary", "lift"), 3, planned)
    assert fsynced == [(views, False), (views / "interrupted", True), (views, True)]


def test_a_full_disk_fails_the_recording_instead_of_hanging(tmpfs):
    """The recording on a full filesystem (a 256 kB tmpfs): the failure is raised and the
    process exits; rerun's own file sink blocked its flush, its disconnect and the
    interpreter's exit for ever, so a scan that filled the disk never ended."""
    disk = tmpfs("size=256k")
    script = f"""
from dataclasses import replace
import numpy as np
from recon.geometry import DetectorSpec, circular_orbit
from tests.scanner.test_storage import _record
from scanner.scan_recording import ScanRecorder
from scanner.study_folder import Study
orbit = circular_orbit(100, 500.0, 1000.0, DetectorSpec(rows=64, cols=64, pixel_pitch_mm=1.0))
study = Study.create({str(disk / "s")!r}, {{}})
recorder = ScanRecorder(study, ("rotary", "lift"), 1.0)
rng = np.random.default_rng(0)
try:
    for k in range(100):  # 1.6 MB of noise
        image = rng.random((64, 64), dtype=np.float32)
        recorder.view(replace(_record(k), matrix=orbit[k].matrix), image)
except RuntimeError as err:
    print("view:", err)
try:
    recorder.close()
except RuntimeError as err:
    print("close:", err)
"""
    done = subprocess.run(
        [sys.executable, "-c", script],
        cwd=Path(__file__).resolve().parents[2],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert done.returncode == 0, done.stderr
    # a later view reports it when rerun's batches reach the file during the scan, else close
    assert "[Errno 28] No space left on device" in done.stdout, done.stdout


@pytest.fixture
def small_disk(tmpfs) -> ScanStore:
    """A store of three 64² views in a study on an 8 MB tmpfs of its own (root only)."""
    disk = tmpfs("size=8m")
    panel = DetectorSpec(rows=64, cols=64, pixel_pitch_mm=1.0)
    study = Study.create(disk / "s", {})
    return ScanStore(study, panel, ("rotary", "lift"), 3, circular_orbit(3, 500.0, 1e3, panel))


def _ballast(disk: Path, size: int) -> None:
    """Another program's file taking ``size`` bytes of ``disk``."""
    fd = os.open(disk / "ballast", os.O_WRONLY | os.O_CREAT)
    os.posix_fallocate(fd, 0, size)
    os.close(fd)


def test_a_view_is_not_exposed_when_the_disk_cannot_take_it(small_disk):
    """check_room, called before each pulse, refuses a view the study's disk has no room for
    (the soak's full disk let one more pulse fire per fault, its view then unstorable)."""
    store = small_disk
    store.check_room(0)  # 8 MB free
    _ballast(store.study.path.parent, 5 << 20)  # 3 MB left: less than a view and the margin
    full = r"view 1: the study's disk has 3\.\d\d MiB free, a view needs 4\.\d\d MiB"
    with pytest.raises(StudyError, match=full):
        store.check_room(1)


def test_a_killed_sessions_partial_recording_is_kept(tmp_path):
    study = Study.create(tmp_path / "s", {})
    (study.path / "scan").mkdir()
    killed = study.path / "scan" / "recording.rrd.partial"
    killed.write_bytes(b"what the killed session recorded")
    recorder = ScanRecorder(study, ("rotary", "lift"), 1.0)
    assert recorder.close() == study.path / "scan" / "recording-2.rrd"
    assert killed.read_bytes() == b"what the killed session recorded"


def test_a_reserved_view_is_stored_on_a_disk_filled_after_its_reservation(small_disk):
    """Another program fills the study's disk after view 0's files were reserved: the room
    check before its pulse refuses it; a view exposed all the same is stored whole, within its
    reserved space; view 1, not reserved, can be neither stored nor reserved (nothing left
    behind)."""
    store = small_disk
    reserved = store.reserve(0)
    store.check_room(0, reserved=True)  # the margin is still free
    stat = os.statvfs(store.study.path)
    _ballast(store.study.path.parent, stat.f_bavail * stat.f_frsize)  # the disk is full
    full = r"view 0: .* 0\.00 MiB free, a view needs 4\.\d\d MiB beyond its reserved files"
    with pytest.raises(StudyError, match=full):  # the scan stops before its pulse
        store.check_room(0, reserved=True)
    rng = np.random.default_rng(1)
    images = [rng.random((64, 64), dtype=np.float32) for _ in range(4)]
    store.put(_record(0), images[0], images[1])  # into its reserved space
    assert store.image(0).tobytes() == images[0].tobytes()
    views = store.study.path / "scan" / "views"
    for path in views.glob("view_0000*"):  # cut to what was written, as recorded
        assert sha256(path) == store.study.manifest["files"][f"scan/views/{path.name}"]
    assert not any(path in reserved.paths for path in views.iterdir())
    with pytest.raises(OSError, match="No space left"):
        store.put(_record(1), images[2], images[3])
    with pytest.raises(StudyError, match=r"view 1: .* not exposing"):
        store.reserve(1)
    assert sorted(p.name for p in views.iterdir()) == [
        "view_0000.json",
        "view_0000.mha",
        "view_0000_counts.mha",
    ]


def test_stored_views_name_the_sha256_of_their_files_on_disk(tmp_path):
    """Each view's record, and the manifest, carry the sha256 of the bytes on disk (hashed
    from memory on the writer threads, never read back); images large enough that hashlib
    releases the GIL, several views in a row."""
    panel = DetectorSpec(rows=64, cols=96, pixel_pitch_mm=1.0)
    planned = circular_orbit(4, 500.0, 1000.0, panel)
    study = Study.create(tmp_path / "s", {})
    store = ScanStore(study, panel, ("rotary", "lift"), 4, planned)
    rng = np.random.default_rng(7)
    for k in range(4):
        line_integrals = rng.random((64, 96), dtype=np.float32)
        store.put(_record(k), line_integrals, rng.random((64, 96), dtype=np.float32))
    views = study.path / "scan" / "views"
    for k in range(4):
        record = json.loads((views / f"view_{k:04d}.json").read_text())
        assert sorted(record["files"]) == [
            f"scan/views/view_{k:04d}.mha",
            f"scan/views/view_{k:04d}_counts.mha",
        ]
        for relpath, digest in record["files"].items():
            on_disk = hashlib.sha256((study.path / relpath).read_bytes()).hexdigest()
            assert digest == on_disk == study.manifest["files"][relpath]
        json_path = f"scan/views/view_{k:04d}.json"
        on_disk = hashlib.sha256((study.path / json_path).read_bytes()).hexdigest()
        assert study.manifest["files"][json_path] == on_disk
    assert study.verify() == []
    assert not list(views.glob(".*"))  # no temporary file left
    reopened = ScanStore(Study.open(study.path), panel, ("rotary", "lift"), 4, planned)
    assert reopened.stored == {0, 1, 2, 3}
