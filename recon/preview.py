"""Orthogonal-slice previews of volumes as PNG (matplotlib, Agg, no screen).

Panels follow the radiological convention in the LPS world frame:

- axial (constant z): patient's left (+x) on the viewer's right, anterior (-y) at the top;
- coronal (constant y): superior (+z) at the top, patient's left (+x) on the right;
- sagittal (constant x): superior (+z) at the top, anterior (-y) on the left.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from recon.volume import Volume

FIGSIZE_IN = (13.0, 4.6)
DPI = 100
"""The PNG is FIGSIZE_IN * DPI pixels: 1300 x 460."""

_UNIT_LABELS = {"1/mm": "linear attenuation (1/mm)", "HU": "HU", "label": "label"}
_WINDOW_PERCENTILES = (0.5, 99.5)


@dataclass(frozen=True)
class SlicePanel:
    """One 2-D slice ready for ``imshow(image, extent=extent_mm, origin="upper")``.

    Attributes:
        name: "axial", "coronal" or "sagittal".
        image: values, row 0 at the top of the display, column 0 at the left.
        extent_mm: (left, right, bottom, top) world mm of the outer voxel edges along the
            horizontal and vertical display axes.
        xlabel, ylabel: axis labels naming world axis, unit and anatomical direction.
        title: panel title with the slice position.
    """

    name: str
    image: np.ndarray
    extent_mm: tuple[float, float, float, float]
    xlabel: str
    ylabel: str
    title: str


def orthogonal_slices(volume: Volume, point_mm: Sequence[float] | None = None) -> list[SlicePanel]:
    """Axial, coronal and sagittal slices through ``point_mm`` (default: the grid centre).

    Args:
        volume: values indexed [z, y, x] on an LPS grid.
        point_mm: world point (x, y, z) mm inside the grid; the nearest voxel's planes are used.

    Returns:
        The three panels in display orientation (see the module docstring).
    """
    grid = volume.grid
    point = grid.center_mm if point_mm is None else np.asarray(point_mm, dtype=np.float64)
    ix, iy, iz = _nearest_voxel(volume, point)
    (x_lo, x_hi), (y_lo, y_hi), (z_lo, z_hi) = _edges(volume)
    x, y, z = grid.index_to_world((ix, iy, iz))
    data = volume.data
    x_label = "x (mm), patient left →"
    z_label = "z (mm), superior ↑"
    return [
        SlicePanel(
            "axial",
            data[iz],
            (x_lo, x_hi, y_hi, y_lo),
            x_label,
            "y (mm), anterior ↑",
            f"axial, z = {z:.1f} mm",
        ),
        SlicePanel(
            "coronal",
            data[::-1, iy, :],
            (x_lo, x_hi, z_lo, z_hi),
            x_label,
            z_label,
            f"coronal, y = {y:.1f} mm",
        ),
        SlicePanel(
            "sagittal",
            data[::-1, :, ix],
            (y_lo, y_hi, z_lo, z_hi),
            "y (mm), ← anterior",
            z_label,
            f"sagittal, x = {x:.1f} mm",
        ),
    ]


def render_orthogonal_slices(
    volume: Volume,
    title: str | None = None,
    window: tuple[float, float] | None = None,
    point_mm: Sequence[float] | None = None,
) -> Figure:
    """A figure of the three slices with mm axes and a colorbar in the volume's unit.

    Args:
        volume: the volume to show.
        title: figure title.
        window: display range (low, high) in the volume's unit; default the 0.5 and 99.5
            percentiles (0 to the largest label for label volumes).
        point_mm: world point (x, y, z) mm the slices pass through; default the grid centre.
    """
    low, high = _window(volume) if window is None else (float(window[0]), float(window[1]))
    if not low < high:
        raise ValueError(f"window must be (low, high) with low < high, got {window!r}")
    cmap = "nipy_spectral" if volume.unit == "label" else "gray"
    fig = Figure(figsize=FIGSIZE_IN, dpi=DPI, layout="constrained")
    axes = fig.subplots(1, 3)
    for ax, panel in zip(axes, orthogonal_slices(volume, point_mm), strict=True):
        shown = ax.imshow(
            panel.image,
            extent=panel.extent_mm,
            origin="upper",
            cmap=cmap,
            vmin=low,
            vmax=high,
            interpolation="nearest",
            aspect="equal",
        )
        ax.set(xlabel=panel.xlabel, ylabel=panel.ylabel, title=panel.title)
    fig.colorbar(shown, ax=list(axes), label=_UNIT_LABELS[volume.unit], shrink=0.8)
    if title:
        fig.suptitle(title)
    return fig


def save_orthogonal_slices(
    volume: Volume,
    path_png: str | Path,
    title: str | None = None,
    window: tuple[float, float] | None = None,
    point_mm: Sequence[float] | None = None,
) -> Path:
    """Write :func:`render_orthogonal_slices` to a PNG of 1300 x 460 pixels.

    Args:
        volume: the volume (its unit labels the colour bar).
        path_png: the PNG to write.
        title: the figure's title (default: none).
        window: display range (low, high) in the volume's unit (default: as
            :func:`render_orthogonal_slices` chooses it).
        point_mm: world point (x, y, z) mm the three slices pass through (default: the grid
            centre).

    Raises:
        FileNotFoundError: the output folder does not exist.
        ValueError: a bad window or a point outside the grid.
    """
    path = Path(path_png)
    if not path.parent.is_dir():
        raise FileNotFoundError(f"{path}: output folder {path.parent} does not exist")
    render_orthogonal_slices(volume, title, window, point_mm).savefig(path, format="png", dpi=DPI)
    return path


def _nearest_voxel(volume: Volume, point: np.ndarray) -> tuple[int, int, int]:
    if point.shape != (3,) or not np.all(np.isfinite(point)):
        raise ValueError(f"point_mm must be 3 finite numbers (x, y, z), got {point.tolist()}")
    index = np.rint(volume.grid.world_to_index(point)).astype(int)
    if np.any(index < 0) or np.any(index >= np.array(volume.grid.size_xyz)):
        raise ValueError(f"point_mm {point.tolist()} lies outside the volume's grid")
    return int(index[0]), int(index[1]), int(index[2])


def _edges(volume: Volume) -> list[tuple[float, float]]:
    """(low, high) world mm of the outer voxel edges along x, y and z."""
    corners = volume.grid.corners_mm()
    return [(float(corners[:, a].min()), float(corners[:, a].max())) for a in range(3)]


def _window(volume: Volume) -> tuple[float, float]:
    data = np.asarray(volume.data, dtype=np.float64)
    if volume.unit == "label":
        low, high = 0.0, float(data.max())
    else:
        low, high = (float(v) for v in np.nanpercentile(data, _WINDOW_PERCENTILES))
    return (low, high) if low < high else (low, low + 1.0)
