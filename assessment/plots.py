"""The knee-assessment plots as PNG bytes (matplotlib Agg, no pyplot global state).

Each ``*_png(kin)`` function draws one figure of docs/system.md's "Clinical assessment (knee)" at
``DPI`` and returns the encoded PNG; ``PLOTS`` lists them by file stem and ``save_all`` writes
them all to a folder.
"""

from __future__ import annotations

import io
from collections.abc import Callable
from pathlib import Path

import matplotlib.image
import numpy as np
from matplotlib import colormaps
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection
from matplotlib.colors import Colormap, LinearSegmentedColormap, Normalize
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from assessment.results import KneeKinematics

DPI = 100
"""Resolution of every PNG, dots per inch."""

FIGSIZE_IN = (7.0, 5.0)
"""Size of a single-panel figure, inches (700 x 500 px at DPI)."""

MEDIAL_COLOR = "tab:blue"
LATERAL_COLOR = "tab:orange"
FLAG_COLOR = "tab:red"


def _time_cmap() -> Colormap:
    """Sequential light-to-dark colormap for time (frames); skips the near-white start of Blues."""
    blues = colormaps["Blues"]
    return LinearSegmentedColormap.from_list("frames", blues(np.linspace(0.25, 1.0, 256)))


def _figure(figsize: tuple[float, float] = FIGSIZE_IN) -> Figure:
    """A figure bound to an Agg canvas."""
    fig = Figure(figsize=figsize, dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _png(fig: Figure) -> bytes:
    """Encode a figure as PNG at DPI."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    return buf.getvalue()


def _frame_colorbar(fig: Figure, ax: Axes, kin: KneeKinematics, cmap: Colormap) -> Normalize:
    """Add a "Frame" colorbar to ``ax`` and return the frame-number normalisation."""
    norm = Normalize(float(np.min(kin.frames)), float(np.max(kin.frames)))
    mappable = ax.scatter([], [], c=[], cmap=cmap, norm=norm)
    fig.colorbar(mappable, ax=ax, label="Frame")
    return norm


def distance_scatter_png(kin: KneeKinematics) -> bytes:
    """Medial vs lateral TP–condyle distance per frame, coloured by frame.

    Draws the y = x diagonal (equal gaps) and the ±``kin.flag_mm`` band around it; points
    outside the band are the flagged frames.

    Args:
        kin: per-frame knee metrics.

    Returns:
        PNG bytes.
    """
    fig = _figure()
    ax = fig.add_subplot()
    cmap = _time_cmap()
    med, lat = kin.medial_distance_mm, kin.lateral_distance_mm
    lo = float(min(med.min(), lat.min())) - kin.flag_mm - 0.5
    hi = float(max(med.max(), lat.max())) + kin.flag_mm + 0.5
    line = np.array([lo, hi])
    ax.fill_between(
        line,
        line - kin.flag_mm,
        line + kin.flag_mm,
        color="0.88",
        label=f"|MLD| ≤ {kin.flag_mm:g} mm",
    )
    ax.plot(line, line, color="0.3", linestyle="--", linewidth=1, label="y = x (equal gaps)")
    norm = _frame_colorbar(fig, ax, kin, cmap)
    ax.scatter(med, lat, c=kin.frames, cmap=cmap, norm=norm, edgecolors="0.3", linewidths=0.5)
    ax.set_xlim(lo, hi)
    ax.set_ylim(lo, hi)
    ax.set_aspect("equal")
    ax.set_xlabel("Medial TP–condyle distance (mm)")
    ax.set_ylabel("Lateral TP–condyle distance (mm)")
    ax.set_title("Medial vs lateral distance")
    ax.legend(loc="upper left")
    ax.grid(alpha=0.3)
    return _png(fig)


def mld_png(kin: KneeKinematics) -> bytes:
    """Medial–lateral difference (MLD) per frame with the ±``kin.flag_mm`` band shaded.

    Args:
        kin: per-frame knee metrics.

    Returns:
        PNG bytes.
    """
    fig = _figure()
    ax = fig.add_subplot()
    mld, flagged = kin.mld_mm, kin.flagged
    ax.axhspan(-kin.flag_mm, kin.flag_mm, color="0.9", label=f"within ±{kin.flag_mm:g} mm")
    for level in (-kin.flag_mm, kin.flag_mm):
        ax.axhline(level, color=FLAG_COLOR, linestyle="--", linewidth=1)
    ax.axhline(0.0, color="0.5", linewidth=0.8)
    ax.plot(kin.frames, mld, color="0.2", marker="o", markersize=3, linewidth=1.2, label="MLD")
    ax.scatter(
        kin.frames[flagged],
        mld[flagged],
        color=FLAG_COLOR,
        s=40,
        zorder=3,
        label=f"flagged (|MLD| > {kin.flag_mm:g} mm)",
    )
    span = max(float(np.max(np.abs(mld))), kin.flag_mm) * 1.3
    ax.set_ylim(-span, span)
    ax.text(0.99, 0.97, "medial gap larger", transform=ax.transAxes, ha="right", va="top")
    ax.text(0.99, 0.03, "lateral gap larger", transform=ax.transAxes, ha="right", va="bottom")
    ax.set_xlabel("Frame")
    ax.set_ylabel("MLD = medial − lateral distance (mm)")
    ax.set_title("Medial–lateral difference per frame")
    ax.legend(loc="upper left")
    ax.grid(alpha=0.3)
    return _png(fig)


def extension_distance_png(kin: KneeKinematics) -> bytes:
    """Medial and lateral TP–condyle distances against the extension angle (= −flexion).

    Args:
        kin: per-frame knee metrics.

    Returns:
        PNG bytes.
    """
    fig = _figure()
    ax = fig.add_subplot()
    extension = -kin.flexion_deg
    for dist, color, name in (
        (kin.medial_distance_mm, MEDIAL_COLOR, "medial"),
        (kin.lateral_distance_mm, LATERAL_COLOR, "lateral"),
    ):
        ax.plot(extension, dist, color=color, marker="o", markersize=4, linewidth=1, label=name)
    ax.set_xlabel("Extension angle = −flexion (°)")
    ax.set_ylabel("TP–condyle distance (mm)")
    ax.set_title("Distance vs extension angle")
    ax.legend()
    ax.grid(alpha=0.3)
    return _png(fig)


def trajectories_png(kin: KneeKinematics) -> bytes:
    """Trajectories of the medial and lateral projection points on the TP plane (Feng's method).

    Each frame's medial (circle) and lateral (square) points are joined by a line; colours go
    light to dark over time.

    Args:
        kin: per-frame knee metrics.

    Returns:
        PNG bytes.
    """
    fig = _figure((7.0, 6.0))
    ax = fig.add_subplot()
    cmap = _time_cmap()
    norm = _frame_colorbar(fig, ax, kin, cmap)
    colors = cmap(norm(kin.frames))
    med, lat = kin.medial_point_mm, kin.lateral_point_mm
    ax.add_collection(LineCollection(np.stack([med, lat], axis=1), colors=colors, linewidths=1))
    ax.scatter(med[:, 0], med[:, 1], c=colors, marker="o", s=25, edgecolors="0.3", linewidths=0.5)
    ax.scatter(lat[:, 0], lat[:, 1], c=colors, marker="s", s=25, edgecolors="0.3", linewidths=0.5)
    ax.legend(
        handles=[
            Line2D([], [], color="0.4", marker="o", linestyle="", label="medial point"),
            Line2D([], [], color="0.4", marker="s", linestyle="", label="lateral point"),
            Line2D([], [], color="0.4", linewidth=1, label="same frame"),
        ],
        loc="best",
    )
    ax.autoscale_view()
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("Medial–lateral on TP plane (mm)")
    ax.set_ylabel("Anterior–posterior on TP plane (mm)")
    ax.set_title("Condyle trajectories on the tibial plateau")
    ax.grid(alpha=0.3)
    return _png(fig)


def angles_png(kin: KneeKinematics) -> bytes:
    """Joint angles per frame: flexion, varus and internal rotation, one panel each.

    Args:
        kin: per-frame knee metrics.

    Returns:
        PNG bytes.
    """
    fig = _figure((7.0, 6.5))
    axes = fig.subplots(3, 1, sharex=True)
    for ax, values, label in zip(
        axes,
        (kin.flexion_deg, kin.varus_deg, kin.internal_rotation_deg),
        ("Flexion (°)", "Varus (°)", "Internal rot. (°)"),
        strict=True,
    ):
        ax.plot(kin.frames, values, color="0.2", marker="o", markersize=3, linewidth=1.2)
        ax.axhline(0.0, color="0.6", linewidth=0.8)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("Frame")
    fig.suptitle(f"Joint angles ({kin.side} knee; + = flexion, varus, internal rotation)")
    return _png(fig)


MOTION_FRAMES = 6
"""Frames the motion-frames figure shows, evenly spaced over the sequence."""


def motion_frames_png(kin: KneeKinematics, images: dict[int, Path]) -> bytes:
    """The motion frames with their joint angles (the paper's figure): up to
    :data:`MOTION_FRAMES` frames evenly spaced over those with an image, each titled with
    its frame number and Grood–Suntay angles; flagged frames titled in red.

    Args:
        kin: per-frame knee metrics.
        images: the frames' images (PNG) by frame number; only those shown are read.
    """
    shown = [k for k, f in enumerate(int(f) for f in kin.frames) if f in images]
    if not shown:
        raise ValueError("no frame has an image for the motion-frames figure")
    picks = sorted({shown[round(i)] for i in np.linspace(0, len(shown) - 1, MOTION_FRAMES)})
    fig = _figure((2.3 * len(picks), 3.0))
    for ax, k in zip(fig.subplots(1, len(picks), squeeze=False)[0], picks, strict=True):
        ax.imshow(matplotlib.image.imread(images[int(kin.frames[k])]), cmap="gray")
        ax.set_axis_off()
        ax.set_title(
            f"frame {int(kin.frames[k])}: flexion {kin.flexion_deg[k]:.0f}°\n"
            f"varus {kin.varus_deg[k]:.1f}°, int. rot. {kin.internal_rotation_deg[k]:.1f}°",
            fontsize=9,
            color=FLAG_COLOR if kin.flagged[k] else "black",
        )
    return _png(fig)


PLOTS: dict[str, Callable[[KneeKinematics], bytes]] = {
    "distance_scatter": distance_scatter_png,
    "mld": mld_png,
    "extension_distance": extension_distance_png,
    "trajectories": trajectories_png,
    "angles": angles_png,
}
"""The plots by file stem, in report order."""


def save_all(kin: KneeKinematics, folder: Path | str) -> dict[str, Path]:
    """Write every plot in ``PLOTS`` to ``folder/<name>.png`` (creating the folder).

    Args:
        kin: per-frame knee metrics.
        folder: output folder.

    Returns:
        The written paths by plot name, in report order.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths: dict[str, Path] = {}
    for name, plot in PLOTS.items():
        path = folder / f"{name}.png"
        path.write_bytes(plot(kin))
        paths[name] = path
    return paths
