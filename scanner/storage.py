"""A scan's views in the study folder, stored one by one as they are acquired.

Layout under ``scan/`` (``calibration_scan/`` for the steel-ball phantom's scan)::

    views/view_0007.mha          line integrals -ln(I/I0) of view 7, float32 (1, rows, cols)
    views/view_0007_counts.mha   its raw counts
    views/view_0007.json         the record: joints at exposure, the realised 3x4 matrix,
                                 technique, clock times, sha256 of both images
    projections.mha, counts.mha  the stacks, assembled when every view is in (RTK-readable)
    geometry.xml                 the views as recorded (the arms' measured joints), RTK XML
    planned_geometry.xml         the plan's views
    true_geometry.xml            simulation only: the views the structure really realised
    true_motion.csv              simulation only: the patient's bodies per view (recon.motion)
    joint_states.csv             joints at every exposure (plan joint units)
    exposure_log.csv             view, clock time, kV, mA, ms, generator sequence

A view counts as stored once its .json exists (written last, atomically, after both images,
with their sha256); on reopening, every stored view is checked against its checksums (the
manifest's, or the record's for views stored after the manifest's last save), and an altered or
missing file is an error, never skipped silently. An image without its record (the process
killed between renaming the images and the record into place) was never stored: it is moved
to ``views/interrupted/`` (kept, never overwritten) and the view is acquired again.
"""

from __future__ import annotations

import itertools
import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from recon.geometry import DetectorSpec, Geometry, View
from recon.io import encode_projections, read_projections, write_projections
from recon.motion import BodyMotion, write_motion_csv
from recon.rtk_xml import write_rtk_geometry
from scanner.study_folder import (
    PendingWrite,
    Reservation,
    Study,
    StudyError,
    fsync_folder,
    make_folder,
    sha256,
)

SCAN_FOLDERS = {"scan": "scan", "calibration_scan": "calibration_scan"}
"""Folder of each scan stage in the study."""
ROOM_MARGIN_BYTES = 4 << 20
"""Free space a view must leave on the study's disk before it is exposed (the recording, the
device log and the stage's status still need some), bytes."""
_HEADER_BYTES = 4096
"""Upper bound of a view image's MetaImage header, bytes."""
_RECORD_BYTES = 16384
"""Upper bound of a view's JSON record, bytes."""


@dataclass(frozen=True)
class ViewRecord:
    """What is known about one acquired view (units in the names; q in plan joint units)."""

    view: int
    planned_time_s: float
    clock_s: float
    frame_clock_s: float
    q: np.ndarray
    matrix: np.ndarray
    source_mm: np.ndarray
    kv: float
    ma: float
    ms: float
    exposure_sequence: int
    true_matrix: np.ndarray | None = None
    true_poses: dict[str, np.ndarray] | None = None

    @property
    def mas(self) -> float:
        return self.ma * self.ms * 1e-3

    def to_json(self) -> dict:
        out = asdict(self)
        for key in ("q", "matrix", "source_mm", "true_matrix"):
            if out[key] is not None:
                out[key] = np.asarray(out[key]).tolist()
        if self.true_poses is not None:
            out["true_poses"] = {b: np.asarray(T).tolist() for b, T in self.true_poses.items()}
        return out

    @classmethod
    def from_json(cls, data: dict) -> ViewRecord:
        """The record :meth:`to_json` wrote; ValueError or TypeError for missing or unknown
        fields, numbers that are not finite, arrays of the wrong shape."""
        data = dict(data)
        data.pop("files", None)
        poses = data.pop("true_poses", None)
        if poses is not None:
            if not isinstance(poses, dict):
                raise ValueError("true_poses is not an object of 4x4 poses")
            poses = {str(b): np.asarray(T, dtype=np.float64) for b, T in poses.items()}
            for body, T in poses.items():
                if T.shape != (4, 4) or not np.isfinite(T).all():
                    raise ValueError(f"true_poses of {body} is not a finite 4x4 pose")
        data["true_poses"] = poses
        shapes = {"q": (None,), "matrix": (3, 4), "source_mm": (3,), "true_matrix": (3, 4)}
        for key, value in data.items():
            if key == "true_poses" or (value is None and key == "true_matrix"):
                continue
            array = np.asarray(value, dtype=np.float64)
            if not np.isfinite(array).all():
                raise ValueError(f"{key} is not finite")
            shape = shapes.get(key, ())
            if array.ndim != len(shape) or any(
                n not in (None, m) for n, m in zip(shape, array.shape, strict=True)
            ):
                raise ValueError(f"{key} has shape {array.shape}, not {shape}")
            if key in shapes:
                data[key] = array
        return cls(**data)


def _view_record(path: Path) -> dict:
    """A view record's JSON: an object with a whole ``view`` number and a ``files`` object;
    StudyError naming ``path`` otherwise."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except ValueError as err:  # JSON and UTF-8 errors
        raise StudyError(f"{path}: not a view record ({err})") from None
    if not (
        isinstance(data, dict)
        and isinstance(data.get("view"), int)
        and not isinstance(data["view"], bool)
        and isinstance(data.get("files"), dict)
    ):
        raise StudyError(f"{path}: not a view record (no whole 'view' number and 'files' object)")
    if path.name != f"view_{data['view']:04d}.json":
        raise StudyError(f"{path}: records view {data['view']}, not the view its name says")
    return data


class PendingView:
    """A view being stored (:meth:`ScanStore.start_put`)."""

    def __init__(self, store: ScanStore, record: ViewRecord, writing: PendingWrite) -> None:
        self.store, self.record, self._writing = store, record, writing

    @property
    def failed(self) -> bool:
        """Its storage has failed already (:meth:`wait` raises at once)."""
        return self._writing.failed

    def wait(self) -> None:
        """Return once the view is stored (its files fsynced and in place, the view in the
        store's records); raise what failed (the view is then not stored, nothing of it left
        behind). Waiting again returns (or raises) the same."""
        k = self.record.view
        try:
            self._writing.wait()
        except BaseException:
            if self._writing.done:  # failed (not an interrupted wait): the view may be retried
                self.store._storing.discard(k)
            raise
        self.store._storing.discard(k)
        self.store.records[k] = self.record


class ScanStore:
    """A scan stage of a study (``scan``, or ``calibration_scan`` of the steel-ball phantom)
    for a plan of ``n_views`` views on ``panel``."""

    def __init__(
        self,
        study: Study,
        panel: DetectorSpec,
        joint_names: tuple[str, ...],
        n_views: int,
        planned: Geometry,
        stage: str = "scan",
    ) -> None:
        self.study, self.panel, self.joint_names = study, panel, joint_names
        self.stage, self.folder = stage, SCAN_FOLDERS[stage]
        self.n_views, self.planned = n_views, planned
        self.records: dict[int, ViewRecord] = {}
        self._storing: set[int] = set()  # views whose files are being written
        self._load()

    @property
    def stored(self) -> set[int]:
        return set(self.records)

    @property
    def dose_mas(self) -> float:
        return sum(r.mas for r in self.records.values())

    def _name(self, k: int) -> str:
        return f"{self.folder}/views/view_{k:04d}"

    def _load(self) -> None:
        folder = self.study.path / self.folder / "views"
        if not folder.is_dir():
            return
        for path in sorted(folder.glob("view_*.json")):
            recorded = self.study.manifest["files"].get(f"{self.folder}/views/{path.name}")
            if recorded is not None and sha256(path) != recorded:
                raise StudyError(f"{path}: the view record was altered (sha256 mismatch)")
            data = _view_record(path)
            k = data["view"]
            base = self._name(k)
            for suffix in (".json", ".mha", "_counts.mha"):
                relpath = base + suffix
                recorded = self.study.manifest["files"].get(relpath)
                if recorded is None and suffix == ".json":
                    continue  # manifest saved just before the crash: the view's files decide
                target = self.study.path / relpath
                if not target.is_file():
                    raise StudyError(f"view {k}: {target} is missing")
                digest = sha256(target)
                expected = recorded or data["files"].get(relpath)
                if digest != expected:
                    raise StudyError(f"view {k}: {target} was altered (sha256 mismatch)")
                self.study.manifest["files"][relpath] = digest
            try:
                self.records[k] = ViewRecord.from_json(data)
            except (TypeError, ValueError) as err:
                raise StudyError(f"{path}: not a view record ({err})") from None
        for path in sorted(folder.glob("view_*.mha")):
            k = int(path.name[len("view_") :].split("_")[0].split(".")[0])
            if k not in self.records:
                self._set_aside(path)

    def _set_aside(self, path: Path) -> None:
        """Move an image whose view has no record to ``interrupted/`` under a new name, both
        folders flushed (its new name survives a power loss, whatever is stored after it)."""
        aside = path.parent / "interrupted"
        make_folder(aside)
        for n in itertools.count():
            target = aside / (path.name if n == 0 else f"{path.stem}.{n}{path.suffix}")
            if not target.exists():
                os.rename(path, target)
                fsync_folder(aside)
                fsync_folder(path.parent)
                return

    def _file_bytes(self, k: int) -> dict[str, int]:
        """View ``k``'s files (both images and the record) and the most each takes, bytes."""
        image = self.panel.rows * self.panel.cols * 4 + _HEADER_BYTES
        base = self._name(k)
        return {base + ".mha": image, base + "_counts.mha": image, base + ".json": _RECORD_BYTES}

    def check_room(self, k: int, reserved: bool = False) -> None:
        """Raise StudyError unless the study's filesystem can take view ``k``: both images,
        its record and a save of the manifest, with :data:`ROOM_MARGIN_BYTES` to spare;
        ``reserved``: the view's files are allocated already (:meth:`reserve`), the rest must
        still fit (a disk another program filled since: no more pulses)."""
        stat = os.statvfs(self.study.path)
        free = stat.f_bavail * stat.f_frsize
        manifest = (self.study.path / "study.json").stat().st_size
        files = 0 if reserved else sum(self._file_bytes(k).values())
        need = files + manifest + ROOM_MARGIN_BYTES
        if free < need:
            what = "beyond its reserved files (" if reserved else "(images, record, "
            raise StudyError(
                f"view {k}: the study's disk has {free / 2**20:.2f} MiB free, a view needs "
                f"{need / 2**20:.2f} MiB {what}manifest, margin): not exposing"
            )

    def _refuse_stored(self, k: int) -> None:
        """StudyError when view ``k`` is stored or being stored (never replaced)."""
        if k in self.records or k in self._storing:
            raise StudyError(f"view {k} is already stored: acquired views are never replaced")

    def reserve(self, k: int) -> Reservation:
        """Before view ``k``'s pulse: check the room for it (:meth:`check_room`) and allocate
        its files' space (:meth:`scanner.study_folder.Study.reserve`), so that a disk another
        program fills after the check cannot refuse a view already exposed. :meth:`start_put` writes
        the reserved files; release the reservation when the view is not acquired after all.
        Raises StudyError (not exposing) when the disk cannot take the view."""
        self.check_room(k)
        self._refuse_stored(k)
        try:
            return self.study.reserve(self._file_bytes(k))
        except StudyError as err:
            raise StudyError(f"view {k}: {err}: not exposing") from None

    def image(self, k: int) -> np.ndarray:
        """The stored line integrals of view ``k``, float32 (rows, cols)."""
        if k not in self.records:
            raise StudyError(f"view {k} is not stored")
        return read_projections(self.study.path / f"{self._name(k)}.mha").data[0]

    def view(self, k: int) -> View:
        """Stored view ``k`` as recorded (its realised matrix)."""
        p = self.panel
        return View.from_matrix(self.records[k].matrix, p.pixel_pitch_mm, p.rows, p.cols)

    def put(self, record: ViewRecord, line_integrals: np.ndarray, counts: np.ndarray) -> None:
        """Store one view and return once it is stored (:meth:`start_put`, then its wait)."""
        self.start_put(record, line_integrals, counts).wait()

    def start_put(
        self, record: ViewRecord, line_integrals: np.ndarray, counts: np.ndarray
    ) -> PendingView:
        """Start storing one view (into the files :meth:`reserve` allocated, when it was
        called): both images, then its record, which carries their sha256, each fsynced under
        a temporary name, the record renamed into place last
        (:meth:`scanner.study_folder.Study.start_write_with_record`). The view is stored (in
        :attr:`records`, :attr:`stored`) once :meth:`PendingView.wait` has returned; the
        images must not change until then. The manifest is saved with the stage's status
        (done, or SAFE); a view stored after its last save is verified against its record on
        reopening (:meth:`_load`)."""
        k = record.view
        self._refuse_stored(k)
        pitch = self.panel.pixel_pitch_mm
        base = self._name(k)
        images = {
            base + ".mha": encode_projections(line_integrals[None], pitch),
            base + "_counts.mha": encode_projections(counts[None], pitch),
        }

        def content(digests: dict[str, str]) -> bytes:
            return json.dumps({**record.to_json(), "files": digests}, indent=2).encode("utf-8")

        writing = self.study.start_write_with_record(images, base + ".json", content)
        self._storing.add(k)
        return PendingView(self, record, writing)

    def mark_incomplete(self, reason: str, failed_in: str) -> None:
        self.study.mark(
            self.stage,
            "incomplete",
            reason=reason,
            failed_in=failed_in,
            views_stored=len(self.records),
            views=self.n_views,
            resume=f"cbct scan --resume --study {self.study.path}",
        )

    def finish(self) -> None:
        """Assemble stacks, geometry and logs once every view is in; mark the scan complete."""
        missing = sorted(set(range(self.n_views)) - self.stored)
        if missing:
            raise StudyError(f"cannot finish the scan: views {missing[:10]} are not stored")
        order = range(self.n_views)
        pitch = self.panel.pixel_pitch_mm
        stacks = {"projections": [], "counts": []}
        for k in order:
            base = self.study.path / self._name(k)
            stacks["projections"].append(read_projections(base.with_suffix(".mha")).data[0])
            stacks["counts"].append(read_projections(f"{base}_counts.mha").data[0])
        for name, images in stacks.items():
            stack = np.stack(images)
            self.study.write(
                f"{self.folder}/{name}.mha", lambda p, a=stack: write_projections(p, a, pitch)
            )
        recorded = Geometry([self.view(k) for k in order])
        self.study.write(f"{self.folder}/geometry.xml", lambda p: write_rtk_geometry(p, recorded))
        self.study.write(
            f"{self.folder}/planned_geometry.xml", lambda p: write_rtk_geometry(p, self.planned)
        )
        if all(self.records[k].true_matrix is not None for k in order):
            truth = Geometry(
                [
                    View.from_matrix(
                        self.records[k].true_matrix, pitch, self.panel.rows, self.panel.cols
                    )
                    for k in order
                ]
            )
            self.study.write(
                f"{self.folder}/true_geometry.xml", lambda p: write_rtk_geometry(p, truth)
            )
        if all(self.records[k].true_poses is not None for k in order):
            bodies = tuple(sorted(self.records[0].true_poses))
            motion = BodyMotion(
                bodies,
                np.array([[self.records[k].true_poses[b] for b in bodies] for k in order]),
            )
            self.study.write(
                f"{self.folder}/true_motion.csv", lambda p: write_motion_csv(p, motion)
            )
        header = "view,clock_s," + ",".join(self.joint_names)
        rows = [
            f"{k},{self.records[k].clock_s:.6f}," + ",".join(f"{v:.6f}" for v in self.records[k].q)
            for k in order
        ]
        self.study.write(
            f"{self.folder}/joint_states.csv",
            lambda p: p.write_text(header + "\n" + "\n".join(rows) + "\n", encoding="utf-8"),
        )
        log = ["view,clock_s,kv,ma,ms,sequence"] + [
            f"{k},{r.clock_s:.6f},{r.kv:g},{r.ma:g},{r.ms:g},{r.exposure_sequence}"
            for k, r in ((k, self.records[k]) for k in order)
        ]
        self.study.write(
            f"{self.folder}/exposure_log.csv",
            lambda p: p.write_text("\n".join(log) + "\n", encoding="utf-8"),
        )
        self.study.mark(
            self.stage, "complete", views=self.n_views, dose_mas=round(self.dose_mas, 4)
        )
