"""The study's one rerun recording: every stage's recording merged, plus the volume's slices.

Each stage writes its own ``.rrd`` as it runs (plan, calibration scan, scan, the 4D series of
the assessment); :func:`merge_recordings` copies their chunks into ``recording.rrd`` under one
recording id, each stage keeping its own timeline (``plan_time``, ``scan_time`` and ``view``,
``frame``), so a single ``rerun recording.rrd`` shows them all. :func:`record_volume` logs a
reconstruction's axial, coronal and sagittal slices on the ``slice`` timeline.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import rerun as rr

from recon.volume import Volume

APPLICATION_ID = "dualarm-cbct"


def record_volume(volume: Volume, path: Path, entity: str = "recon", every: int = 4) -> Path:
    """Slices of ``volume`` (every ``every``-th along each axis) as images on the ``slice``
    timeline, index = slice number; written to ``path`` (must not exist)."""
    if path.exists():
        raise FileExistsError(f"{path} exists: recordings are never written over")
    rec = rr.RecordingStream(APPLICATION_ID)
    rec.save(path)
    data = volume.data.astype(np.float32)
    lo, hi = np.percentile(data, [1, 99.5])
    scaled = np.clip((data - lo) / max(hi - lo, 1e-12), 0, 1)
    for axis, name in ((0, "axial"), (1, "coronal"), (2, "sagittal")):
        for k in range(0, data.shape[axis], every):
            rec.set_time("slice", sequence=k)
            image = np.take(scaled, k, axis=axis)
            if axis != 0:
                image = image[::-1]  # z up
            rec.log(f"{entity}/{name}", rr.Image((image * 255).astype(np.uint8)))
    rec.flush()
    rec.disconnect()
    return path


def merge_recordings(paths: list[Path], out: Path) -> Path:
    """One recording holding every chunk of ``paths`` (in order); ``out`` must not exist."""
    if out.exists():
        raise FileExistsError(f"{out} exists: recordings are never written over")
    partial = out.with_name(out.name + ".partial")
    partial.unlink(missing_ok=True)
    rec = rr.RecordingStream(APPLICATION_ID)
    rec.save(partial)
    for path in paths:
        rec.send_chunks(list(rr.chunk.RrdReader(path).stream()))
    rec.flush()
    rec.disconnect()
    partial.rename(out)
    return out
