"""Measures the benchmarks share: the machine's CPU, a process's peak memory, SSIM over a
region, the central cylinder of a volume and the bone Dice of a reconstruction's
segmentation."""

from __future__ import annotations

import platform
from pathlib import Path

import numpy as np


def cpu_model() -> str:
    """The CPU's model name with its family, model and the code numba compiles for, e.g.
    "AMD EPYC (family 25 model 1, znver3)": a virtual machine often hides the model number,
    and two "AMD EPYC" hosts of different generations run the same kernels 3x apart."""
    fields: dict[str, str] = {}
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                key, _, value = line.partition(":")
                if not key.strip():
                    break  # the first processor's block is enough
                fields.setdefault(key.strip(), value.strip())
    except OSError:
        pass
    import llvmlite.binding

    name = fields.get("model name") or platform.processor() or platform.machine()
    facts = [f"family {fields['cpu family']} model {fields['model']}"] if "model" in fields else []
    facts.append(llvmlite.binding.get_host_cpu_name())
    return f"{name} ({', '.join(facts)})"


def peak_resident_mb() -> float:
    """This process's peak resident set, MB (VmHWM; ru_maxrss would carry the parent's over
    exec)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024.0
    raise RuntimeError("no VmHWM in /proc/self/status")


def central_region(shape: tuple[int, int, int], fraction: float = 0.75) -> np.ndarray:
    """Cylinder of ``fraction`` of the half-width, over ``fraction`` of the height."""
    nz, ny, nx = shape
    z, y, x = np.ogrid[:nz, :ny, :nx]
    r2 = ((x - (nx - 1) / 2) / (nx / 2)) ** 2 + ((y - (ny - 1) / 2) / (ny / 2)) ** 2
    return (r2 <= fraction**2) & (np.abs(z - (nz - 1) / 2) <= fraction * nz / 2)


def ssim(volume: np.ndarray, truth: np.ndarray, region: np.ndarray) -> float:
    """SSIM of ``volume`` against ``truth`` over the bounding box of ``region``, the data range
    the truth's there."""
    from skimage.metrics import structural_similarity

    zs, ys, xs = (np.flatnonzero(region.any(axis=axes)) for axes in ((1, 2), (0, 2), (0, 1)))
    box = np.s_[zs[0] : zs[-1] + 1, ys[0] : ys[-1] + 1, xs[0] : xs[-1] + 1]
    span = float(truth[box].max() - truth[box].min())
    return float(structural_similarity(volume[box], truth[box], data_range=span))


def bone_dice(volume, truth_labels: np.ndarray, segment=None, scored=None) -> float | None:
    """Mean Dice of femur, tibia, fibula and patella between the bones segmented in
    ``volume`` (a recon.volume.Volume) and the phantom's labels, over the voxels ``scored``
    (bool [z, y, x]; default all); None where segmentation finds no bone. ``segment``: a
    volume's labels (a Volume), default registration.segment.segment_bones."""
    from registration.labels import LABELS
    from registration.segment import segment_bones

    try:
        labels = (segment or segment_bones)(volume).data
    except ValueError:
        return None
    scores = []
    for bone in ("femur", "tibia", "fibula", "patella"):
        a, b = labels == LABELS[bone], truth_labels == LABELS[bone]
        if scored is not None:
            a, b = a & scored, b & scored
        scores.append(2 * float((a & b).sum()) / max(float(a.sum() + b.sum()), 1.0))
    return float(np.mean(scores))
