"""The quality-assurance figure of a motion-compensated scan (PNG, matplotlib Agg).

Top row: each body's motion over the scan at the knee, mm: the displacement of its bone
surface from the average pose (the largest over its points) and the x, y, z shift of its
centre, against time (s) or, without per-view times, the view index. Bottom row: the same
coronal and sagittal slices through the knee before and after compensation.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from recon.preview import orthogonal_slices
from recon.volume import Volume
from registration.scan_motion import MAX_COMPENSABLE_MM, MotionEstimate

_DPI = 100


def save_motion_figure(
    estimate: MotionEstimate, before: Volume, after: Volume, path: Path | str
) -> Path:
    """Write the figure (module docstring) to ``path``; the slices pass through the bodies'
    mean centre."""
    motion = estimate.motion
    times = estimate.times_s
    x = np.arange(len(motion)) if times is None else times
    xlabel = "view" if times is None else "time (s)"
    fig = Figure(figsize=(13.0, 8.0), dpi=_DPI)
    grid = fig.add_gridspec(2, 4, height_ratios=(1.0, 1.25))
    ax = fig.add_subplot(grid[0, :2])
    for k, body in enumerate(motion.bodies):
        ax.plot(x, estimate.displacement_mm[:, k], label=f"{body}: surface, largest")
    ax.axhline(MAX_COMPENSABLE_MM, color="0.5", ls=":", lw=1, label="limit of compensation")
    ax.set(xlabel=xlabel, ylabel="displacement from the average pose (mm)")
    ax.set_title(estimate.verdict(), fontsize=9)
    ax.legend(fontsize=8, loc="upper left")
    ax = fig.add_subplot(grid[0, 2:])
    centers = {b: pts.mean(axis=0) for b, pts in estimate.surface_points.items()}
    for k, body in enumerate(motion.bodies):
        c = np.append(centers[body], 1.0)
        shift = motion.poses[:, k, :3] @ c - c[:3]
        for axis, style in zip("xyz", ("-", "--", ":"), strict=True):
            ax.plot(x, shift[:, "xyz".index(axis)], style, lw=1, label=f"{body} {axis}")
    ax.set(xlabel=xlabel, ylabel="centre shift, world axes (mm)")
    ax.legend(fontsize=7, ncol=2, loc="upper left")
    point = np.mean(list(centers.values()), axis=0)
    panels = [(name, v) for name, v in (("before", before), ("after", after))]
    low, high = (
        np.percentile(after.data[after.data > 0], (1.0, 99.8)) if (after.data > 0).any() else (0, 1)
    )
    column = 0
    for name, volume in panels:
        for panel in orthogonal_slices(volume, point)[1:]:
            ax = fig.add_subplot(grid[1, column])
            ax.imshow(panel.image, extent=panel.extent_mm, cmap="gray", vmin=low, vmax=high)
            ax.set_title(f"{panel.name}, {name} compensation", fontsize=9)
            ax.set_xlabel(panel.xlabel, fontsize=7)
            ax.set_ylabel(panel.ylabel, fontsize=7)
            ax.tick_params(labelsize=7)
            column += 1
    fig.tight_layout()
    fig.savefig(path, dpi=_DPI)
    return Path(path)
