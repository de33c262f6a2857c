"""Reconstruction during acquisition: every view weighted, filtered and backprojected as soon as
it is stored, on a worker thread, so that the volume is ready when the scan ends.

A :class:`LiveRecon` is the scan's view sink (:class:`scanner.session.ViewSink`). The exposure
loop only queues each stored view (no copy, no wait); the worker, whose filter and
backprojector leave one core to the exposure loop and which runs at the lowest CPU priority
(:data:`WORKER_NICENESS`), gathers them into the batches
of the offline reconstruction (views ``16 j .. 16 j + 15``, :data:`BATCH_VIEWS`) and adds each
batch to an :class:`recon.fdk.FDKAccumulator` once all its views are in. The geometry is the
one the offline recon stage uses (:func:`study.stages.recon_geometry`): the calibrated views
when the study has a calibration, else each view as recorded with the plan's orbit for the
angular weights. Same views, same batches, same order: the volume equals the offline
``recon`` stage's to float rounding. A resumed scan first queues the views already stored,
read back from the study.

The worker writes the volume (``recon.live/volume.mha``) the moment its last batch is in,
while the arms retreat and the scan assembles its stacks; the recon stage then takes that file
as its own (:func:`study.stages.recon_stage`) and adds the rest.
"""

from __future__ import annotations

import os
import queue
import shutil
import sys
import threading
from pathlib import Path

import numba
import numpy as np

from recon.fdk import FDKAccumulator, FDKResult
from recon.geometry import Geometry
from recon.io import write_volume
from scanner.storage import ScanStore, ViewRecord
from study.stages import recon_geometry, recon_grid, scan_protocol

BATCH_VIEWS = 16
"""Views filtered and backprojected together, as the offline reconstruction batches them."""
WORKER_NICENESS = 19
"""The worker thread's nice value (Linux; 19, the lowest priority): the exposure loop, its
storage and the recording take a core whenever they need one, the reconstruction the rest (a
batch runs for about a quarter of a second; at the same priority it stretched the loop's work
after each pulse by up to 5 ms while it ran)."""
LIVE_FOLDER = "recon.live"
"""Where the worker writes the finished volume, in the study folder (derived data: a new
session's reconstruction clears it)."""


class LiveRecon:
    """Weighted FDK of a scan's views while they are acquired (a scan's view sink).

    Args:
        voxel_mm: the recon stage's voxel size, mm.
    """

    def __init__(self, voxel_mm: float = 1.0) -> None:
        if not voxel_mm > 0:
            raise ValueError(f"recon voxel_mm must be > 0, got {voxel_mm!r}")
        self.voxel_mm = voxel_mm
        self.accumulator: FDKAccumulator | None = None
        self.received = 0
        """Views handed to the worker (stored ones of a resumed scan included)."""
        self.done = 0
        """Views backprojected."""
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._pending: dict[int, np.ndarray] = {}
        self._error: BaseException | None = None
        self._thread: threading.Thread | None = None
        self._store: ScanStore | None = None
        self._recorded = True
        self._result: FDKResult | None = None
        self.volume_path: Path | None = None
        """The volume as written by the worker once every view is in."""

    @property
    def backlog(self) -> int:
        """Views stored but not yet backprojected (waiting for their batch, or queued)."""
        return self.received - self.done

    def start(self, store: ScanStore) -> None:
        """Set up the accumulator on the study's geometry and queue the views already stored."""
        protocol = scan_protocol(store.study)
        orbit, self._recorded = recon_geometry(store.study, protocol, store.planned)
        self.accumulator = FDKAccumulator(orbit, recon_grid(protocol, self.voxel_mm))
        self._store = store
        folder = store.study.path / LIVE_FOLDER
        if folder.exists():  # an earlier session's: this one rebuilds from every stored view
            shutil.rmtree(folder)
        self._thread = threading.Thread(target=self._work, name="live-recon", daemon=True)
        self._thread.start()
        for k in sorted(store.stored):
            self.received += 1
            self._queue.put((k, None))

    def view(self, record: ViewRecord, image: np.ndarray) -> None:
        """Queue one stored view; returns at once."""
        self.received += 1
        self._queue.put((record.view, image))

    def finish(self) -> FDKResult:
        """Wait for the last batch; the volume of every view of the scan."""
        self._stop()
        if self._error is not None:
            raise RuntimeError(f"reconstruction during the scan failed: {self._error}")
        missing = np.flatnonzero(~self.accumulator.added)
        if missing.size:
            raise RuntimeError(f"views {missing[:10].tolist()} were never reconstructed")
        return self._result

    def close(self) -> None:
        """Stop the worker without a result (the scan stopped before its last view)."""
        if self._thread is not None:
            self._stop()

    def _stop(self) -> None:
        self._queue.put(None)
        self._thread.join()

    def _work(self) -> None:
        # one core fewer for the filter and backprojector, at the lowest priority: the
        # exposure loop keeps a core to itself and gets the other one when it needs it
        numba.set_num_threads(max(1, numba.config.NUMBA_NUM_THREADS - 1))
        if sys.platform == "linux":  # a thread's own priority (elsewhere: the process's)
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), WORKER_NICENESS)
        while (item := self._queue.get()) is not None:
            if self._error is not None:
                continue  # keep draining: the scan must never wait on a failed worker
            try:
                k, image = item
                self._pending[k] = self._store.image(k) if image is None else image
                self._add_batch_of(k)
            except Exception as err:
                self._error = err

    def _add_batch_of(self, k: int) -> None:
        n = self.accumulator.n_views
        first = k - k % BATCH_VIEWS
        batch = range(first, min(first + BATCH_VIEWS, n))
        if not all(i in self._pending for i in batch):
            return
        images = np.stack([self._pending.pop(i) for i in batch])
        views = Geometry([self._store.view(i) for i in batch]) if self._recorded else None
        self.accumulator.add(first, images, views)
        self.done += len(batch)
        if self.accumulator.added.all():
            self._result = self.accumulator.result()
            folder = self._store.study.path / LIVE_FOLDER
            folder.mkdir()
            self.volume_path = write_volume(folder / "volume.mha", self._result.volume)
