"""A rerun recording of an acquisition, written while it runs (``scan/recording.rrd``).

Entities (world frame, mm; ``scan`` is the stage's name, ``calibration_scan`` for the
steel-ball phantom), on the ``scan_time`` timeline (the plan's seconds) and the ``view``
sequence:

- ``scan/joints/<name>``: measured joints at each exposure (deg; lift mm).
- ``world/scan/source``, ``world/scan/detector``: the recorded focal spot and panel centre;
  ``world/scan/frustum``: the rays to the panel corners of the recorded view.
- ``scan/projection``: each stored projection (line integrals).
- ``scan/events``: exposures (technique, generator sequence) and state changes.

The file streams to ``<name>.partial`` and is renamed when the acquisition ends (also after a
fault: what was recorded is kept). A resumed scan writes ``recording-2.rrd`` and so on (after a
killed session's ``.partial`` too).
rerun writes into a pipe that a thread here copies to the file: rerun's own file sink, on a
full disk, blocks its flush, its disconnect and the process's exit for ever, where a write here
raises (the copy then drains the pipe, the file stays ``.partial`` and the failure is raised).

The recording is not the scan's record (the stored views are): it is written on a worker
thread, off the exposure loop, which only queues each view and waits only when the recording
is :data:`QUEUE_VIEWS` views behind. A failure of the worker stops the scan at the next view,
as it did when the loop logged the views itself.
"""

from __future__ import annotations

import itertools
import os
import queue
import shutil
import tempfile
import threading
from collections.abc import Callable
from pathlib import Path

import numpy as np
import rerun as rr

from recon.geometry import View
from scanner.storage import SCAN_FOLDERS, ViewRecord
from scanner.study_folder import Study
from trajectories.plan_recording import frustum

TIMELINE = "scan_time"
VIEW_TIMELINE = "view"
QUEUE_VIEWS = 8
"""Views queued for the recording before the exposure loop waits for the worker."""


class ScanRecorder:
    """Streams an acquisition into the study's scan folder."""

    def __init__(
        self, study: Study, joint_names: tuple[str, ...], pitch_mm: float, stage: str = "scan"
    ) -> None:
        folder = study.path / SCAN_FOLDERS[stage]
        self.stage = stage
        folder.mkdir(parents=True, exist_ok=True)
        for k in itertools.count(1):  # a killed session's .partial is kept too
            self.path = folder / ("recording.rrd" if k == 1 else f"recording-{k}.rrd")
            self.partial = self.path.with_name(self.path.name + ".partial")
            if not self.path.exists() and not self.partial.exists():
                break
        self.study, self.joint_names, self.pitch_mm = study, joint_names, pitch_mm
        self._queue: queue.Queue[Callable[[], None] | None] = queue.Queue(QUEUE_VIEWS)
        self._failure: BaseException | None = None
        self._file_failure: OSError | None = None
        self._reported = False
        self._pipe_folder = Path(tempfile.mkdtemp(prefix="cbct-recording-"))
        pipe = self._pipe_folder / "recording.rrd"
        os.mkfifo(pipe)
        self._copier = threading.Thread(
            target=self._copy, args=(pipe,), name="scan-recording-file", daemon=True
        )
        self._copier.start()
        self.rec = rr.RecordingStream("dualarm-cbct")
        self.rec.save(pipe)
        self.rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self._worker = threading.Thread(target=self._work, name="scan-recording", daemon=True)
        self._worker.start()

    def view(self, record: ViewRecord, image: np.ndarray) -> None:
        """Queue a stored view (its joints, geometry and image, float32 (rows, cols), which
        must not change afterwards) for the recording; raises if the worker failed."""
        self._raise_failure()
        self._queue.put(lambda: self._log_view(record, image))

    def event(self, text: str, level: str = "INFO") -> None:
        """Queue a text event after the views queued so far."""
        self._raise_failure()
        self._queue.put(lambda: self.rec.log(f"{self.stage}/events", rr.TextLog(text, level=level)))

    def close(self) -> Path:
        """Record what is queued, finish the file and record its checksum in the study;
        raises if the worker failed and no :meth:`view` has said so yet."""
        self._queue.put(None)
        self._worker.join()
        self.rec.flush()  # never blocks on the disk: the copy drains the pipe
        self.rec.disconnect()
        self._copier.join()
        shutil.rmtree(self._pipe_folder, ignore_errors=True)
        if self._file_failure is not None:
            raise RuntimeError(
                f"the scan's rerun recording could not be written to {self.partial}: "
                f"{self._file_failure}"
            ) from self._file_failure
        self.partial.rename(self.path)
        self.study.adopt(self.path.relative_to(self.study.path).as_posix())
        self.study.save()
        self._raise_failure()
        return self.path

    def _raise_failure(self) -> None:
        failure = self._failure
        if failure is not None and not self._reported:
            self._reported = True
            raise RuntimeError(f"the scan's rerun recording failed: {failure}") from failure

    def _copy(self, pipe: Path) -> None:
        """Copy what rerun writes into ``pipe`` to the partial file, fsynced at the end; after
        a failed write keep draining the pipe (rerun must never wait on it)."""
        with open(pipe, "rb") as source, open(self.partial, "wb", buffering=0) as target:
            while block := source.read(1 << 16):
                view = memoryview(block)
                while view and self._file_failure is None:
                    try:
                        view = view[target.write(view) :]
                    except OSError as err:
                        self._file_failure = err
                        self._failure = self._failure or err
            if self._file_failure is None:
                try:
                    os.fsync(target.fileno())
                except OSError as err:
                    self._file_failure = err

    def _work(self) -> None:
        while (job := self._queue.get()) is not None:
            if self._failure is None:  # after a failure keep draining: the loop never blocks
                try:
                    job()
                except Exception as err:
                    self._failure = err

    def _log_view(self, record: ViewRecord, image: np.ndarray) -> None:
        rec = self.rec
        rec.set_time(TIMELINE, duration=record.planned_time_s)
        rec.set_time(VIEW_TIMELINE, sequence=record.view)
        for name, value in zip(self.joint_names, record.q, strict=True):
            rec.log(f"{self.stage}/joints/{name}", rr.Scalars(float(value)))
        rows, cols = image.shape
        view = View.from_matrix(record.matrix, self.pitch_mm, rows, cols)
        rec.log(
            f"world/{self.stage}/source", rr.Points3D([view.source_mm], colors=[(230, 120, 40)])
        )
        rec.log(
            f"world/{self.stage}/detector",
            rr.Points3D([view.detector_center_mm], colors=[(60, 130, 220)]),
        )
        rec.log(f"world/{self.stage}/frustum", rr.LineStrips3D(frustum(view)))
        rec.log(f"{self.stage}/projection", rr.Image(np.asarray(image, dtype=np.float32)))
        rec.log(
            f"{self.stage}/events",
            rr.TextLog(
                f"view {record.view}: {record.kv:g} kV {record.ma:g} mA {record.ms:g} ms "
                f"(pulse {record.exposure_sequence})"
            ),
        )
