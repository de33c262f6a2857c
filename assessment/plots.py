"""The knee-assessment plots (matplotlib Agg, no pyplot global state).

Each function of ``PLOTS`` draws one figure of docs/system.md's "Clinical assessment (knee)" at
``DPI`` and returns a :class:`Plot`: the encoded PNG and where each frame's point falls on it
(the report marks the current frame there); ``save_all`` writes them all to a folder.
"""

from __future__ import annotations

import io
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import matplotlib.colors
import matplotlib.image
import numpy as np
import trimesh
from matplotlib import colormaps
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection
from matplotlib.colors import Colormap, LinearSegmentedColormap, Normalize
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from mpl_toolkits.mplot3d.art3d import Poly3DCollection

from assessment.results import KneeKinematics
from assessment.viewer import COLORS as BODY_COLORS
from assessment.viewer import MotionScene, view_direction
from registration.meshes import decimated
from registration.roles import KNOWN_ROLES

DPI = 100
"""Resolution of every PNG, dots per inch."""

FIGSIZE_IN = (7.0, 5.0)
"""Size of a single-panel figure, inches (700 x 500 px at DPI)."""

MEDIAL_COLOR = "tab:blue"
LATERAL_COLOR = "tab:orange"
FLAG_COLOR = "tab:red"
EXCLUDED_COLOR = "0.45"
"""Titles of frames not measured: grey, never the flags' red."""


@dataclass(frozen=True)
class Plot:
    """A drawn plot: its PNG, and where each frame's point falls on it.

    Attributes:
        png: The encoded PNG.
        markers: Per marked series and frame, the point's place on the image: (x from the
            left, y from the top) as fractions of its width and height (series, frames, 2).
    """

    png: bytes
    markers: np.ndarray


def _drawn(fig: Figure, series: Sequence[tuple[Axes, np.ndarray, np.ndarray]]) -> Plot:
    """``fig`` as a :class:`Plot` whose markers are each series' points (axes, x, y)."""
    fig.canvas.draw()  # the layout is fixed here, as savefig lays it out again
    width, height = fig.canvas.get_width_height()
    markers = []
    for ax, x, y in series:
        px = ax.transData.transform(np.column_stack((x, y)).astype(np.float64))
        markers.append(np.column_stack((px[:, 0] / width, 1.0 - px[:, 1] / height)))
    return Plot(_png(fig), np.array(markers))


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


def _shade_excluded(ax: Axes, kin: KneeKinematics) -> None:
    """Shade the frames not measured on a per-frame axis (one legend entry)."""
    label = "not measured"
    for frame in kin.frames[~kin.measured]:
        ax.axvspan(frame - 0.5, frame + 0.5, color="0.88", zorder=0, label=label)
        label = None


def _span(*values: np.ndarray) -> tuple[float, float]:
    """The least and greatest finite value of ``values`` ((0, 1) when there is none)."""
    finite = np.concatenate([np.ravel(v) for v in values])
    finite = finite[np.isfinite(finite)]
    return (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)


def distance_scatter(kin: KneeKinematics) -> Plot:
    """Medial vs lateral TP–condyle distance per frame, coloured by frame.

    Draws the y = x diagonal (equal gaps) and the ±``kin.flag_mm`` band around it; points
    outside the band are the flagged frames.

    Args:
        kin: per-frame knee metrics.

    Returns:
        The PNG, and each frame's point on it.
    """
    fig = _figure()
    ax = fig.add_subplot()
    cmap = _time_cmap()
    med, lat = kin.medial_distance_mm, kin.lateral_distance_mm
    lo, hi = _span(med, lat)
    lo, hi = lo - kin.flag_mm - 0.5, hi + kin.flag_mm + 0.5
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
    return _drawn(fig, [(ax, med, lat)])


def mld(kin: KneeKinematics) -> Plot:
    """Medial–lateral difference (MLD) per frame with the ±``kin.flag_mm`` band shaded, the
    frames not measured shaded grey (a gap in the line).

    Args:
        kin: per-frame knee metrics.

    Returns:
        The PNG, and each frame's point on it.
    """
    fig = _figure()
    ax = fig.add_subplot()
    mld, flagged = kin.mld_mm, kin.flagged
    _shade_excluded(ax, kin)
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
    span = max(_span(np.abs(mld))[1], kin.flag_mm) * 1.3
    ax.set_ylim(-span, span)
    ax.text(0.99, 0.97, "medial gap larger", transform=ax.transAxes, ha="right", va="top")
    ax.text(0.99, 0.03, "lateral gap larger", transform=ax.transAxes, ha="right", va="bottom")
    ax.set_xlabel("Frame")
    ax.set_ylabel("MLD = medial − lateral distance (mm)")
    ax.set_title("Medial–lateral difference per frame")
    ax.legend(loc="upper left")
    ax.grid(alpha=0.3)
    return _drawn(fig, [(ax, kin.frames, mld)])


def extension_distance(kin: KneeKinematics) -> Plot:
    """Medial and lateral TP–condyle distances against the extension angle (= −flexion).

    Args:
        kin: per-frame knee metrics.

    Returns:
        The PNG, and each frame's point on it.
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
    return _drawn(
        fig,
        [(ax, extension, kin.medial_distance_mm), (ax, extension, kin.lateral_distance_mm)],
    )


def trajectories(kin: KneeKinematics) -> Plot:
    """Trajectories of the medial and lateral projection points on the TP plane (Feng's method).

    Each frame's medial (circle) and lateral (square) points are joined by a line; colours go
    light to dark over time.

    Args:
        kin: per-frame knee metrics.

    Returns:
        The PNG, and each frame's point on it.
    """
    fig = _figure((7.0, 6.0))
    ax = fig.add_subplot()
    cmap = _time_cmap()
    norm = _frame_colorbar(fig, ax, kin, cmap)
    colors = cmap(norm(kin.frames))
    med, lat = kin.medial_point_mm, kin.lateral_point_mm
    shown = kin.measured
    ax.add_collection(
        LineCollection(np.stack([med, lat], axis=1)[shown], colors=colors[shown], linewidths=1)
    )
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
    return _drawn(fig, [(ax, med[:, 0], med[:, 1]), (ax, lat[:, 0], lat[:, 1])])


def angles(kin: KneeKinematics) -> Plot:
    """Joint angles per frame: flexion, varus and internal rotation, one panel each; the
    frames not measured shaded grey.

    Args:
        kin: per-frame knee metrics.

    Returns:
        The PNG, and each frame's point on it.
    """
    fig = _figure((7.0, 6.5))
    axes = fig.subplots(3, 1, sharex=True)
    series = (kin.flexion_deg, kin.varus_deg, kin.internal_rotation_deg)
    for ax, values, label in zip(
        axes,
        series,
        ("Flexion (°)", "Varus (°)", "Internal rot. (°)"),
        strict=True,
    ):
        _shade_excluded(ax, kin)
        ax.plot(kin.frames, values, color="0.2", marker="o", markersize=3, linewidth=1.2)
        ax.axhline(0.0, color="0.6", linewidth=0.8)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("Frame")
    fig.suptitle(f"Joint angles ({kin.side} knee; + = flexion, varus, internal rotation)")
    return _drawn(fig, [(ax, kin.frames, v) for ax, v in zip(axes, series, strict=True)])


MOTION_FRAMES = 6
"""Frames the motion-frames figure shows, evenly spaced over the sequence."""


def _picks(kin: KneeKinematics, images: dict[int, Path]) -> list[int]:
    """Up to :data:`MOTION_FRAMES` indices of ``kin``'s frames, evenly spaced over those with
    an image."""
    shown = [k for k, f in enumerate(int(f) for f in kin.frames) if f in images]
    if not shown:
        raise ValueError("no frame has an image for the motion-frames figure")
    return sorted({shown[round(i)] for i in np.linspace(0, len(shown) - 1, MOTION_FRAMES)})


def motion_frames_png(kin: KneeKinematics, images: dict[int, Path]) -> bytes:
    """The motion frames with their joint angles (the paper's figure): up to
    :data:`MOTION_FRAMES` frames evenly spaced over those with an image, each titled with
    its frame number and Grood–Suntay angles; flagged frames titled in red, frames not
    measured in grey.

    Args:
        kin: per-frame knee metrics.
        images: the frames' images (PNG) by frame number; only those shown are read.
    """
    picks = _picks(kin, images)
    fig = _figure((2.3 * len(picks), 3.0))
    for ax, k in zip(fig.subplots(1, len(picks), squeeze=False)[0], picks, strict=True):
        ax.imshow(matplotlib.image.imread(images[int(kin.frames[k])]), cmap="gray")
        ax.set_axis_off()
        if not kin.measured[k]:
            ax.set_title(
                f"frame {int(kin.frames[k])}:\nnot measured", fontsize=9, color=EXCLUDED_COLOR
            )
            continue
        ax.set_title(
            f"frame {int(kin.frames[k])}: flexion {kin.flexion_deg[k]:.0f}°\n"
            f"varus {kin.varus_deg[k]:.1f}°, int. rot. {kin.internal_rotation_deg[k]:.1f}°",
            fontsize=9,
            color=FLAG_COLOR if kin.flagged[k] else "black",
        )
    return _png(fig)


FIGURE_FACES = 2500
"""Faces per mesh in the 4D rendering of :func:`frames_beside_4d_png`."""


def frames_beside_4d_png(kin: KneeKinematics, images: dict[int, Path], scene: MotionScene) -> bytes:
    """The registered frames beside the 4D rendering at the same instants (the paper's
    "motion frames from 2D scanning / from 4D virtual imaging"): the frames of
    :func:`motion_frames_png` on top; below each, the bodies at their registered poses as
    the report's 3D view first shows them, with the TP plane and the lowest medial and
    lateral condyle points.

    Args:
        kin: per-frame knee metrics (the scene's frames).
        images: the frames' images (PNG) by frame number; only those shown are read.
        scene: the motion in 3D (:func:`assessment.viewer.motion_scene`).
    """
    picks = _picks(kin, images)
    meshes = {
        name: decimated(trimesh.Trimesh(v, f, process=False), FIGURE_FACES)
        for name, (v, f) in scene.meshes.items()
    }
    look = view_direction(scene.side)
    points = np.concatenate([m.vertices for m in meshes.values()])
    center = 0.5 * (points.min(axis=0) + points.max(axis=0))
    half = 0.5 * float(np.max(points.max(axis=0) - points.min(axis=0)))
    fig = _figure((2.3 * len(picks), 5.4))
    axes = fig.subplots(2, len(picks), squeeze=False)
    for i, k in enumerate(picks):
        top = axes[0][i]
        top.imshow(matplotlib.image.imread(images[int(kin.frames[k])]), cmap="gray")
        top.set_axis_off()
        top.set_title(f"frame {int(kin.frames[k])}", fontsize=9)
        axes[1][i].remove()
        ax = fig.add_subplot(2, len(picks), len(picks) + i + 1, projection="3d")
        for name, mesh in meshes.items():
            T = scene.poses[name][k]
            triangles = (mesh.vertices @ T[:3, :3].T + T[:3, 3])[mesh.faces]
            normals = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
            normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
            shade = 0.35 + 0.65 * np.abs(normals @ look)
            colour = BODY_COLORS.get(KNOWN_ROLES.get(name), "#b0b0b0")
            rgb = np.array(matplotlib.colors.to_rgb(colour))
            ax.add_collection3d(
                Poly3DCollection(triangles, facecolors=shade[:, None] * rgb, linewidths=0)
            )
        carrier = scene.poses[scene.tibia][k]
        plane = scene.plane @ carrier[:3, :3].T + carrier[:3, 3]
        ax.add_collection3d(Poly3DCollection([plane], facecolors=(0.24, 0.55, 0.25, 0.35)))
        for j, color in enumerate((MEDIAL_COLOR, LATERAL_COLOR)):
            if np.isfinite(scene.condyles[k, j]).all():  # none in a frame not measured
                ax.scatter(*scene.condyles[k, j], color=color, s=12, depthshade=False)
        for set_limits, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), center, strict=True):
            set_limits(c - half, c + half)
        ax.set_box_aspect((1, 1, 1), zoom=1.5)
        ax.view_init(
            elev=float(np.degrees(np.arcsin(look[2]))),
            azim=float(np.degrees(np.arctan2(look[1], look[0]))),
        )
        ax.set_axis_off()
    return _png(fig)


PLOTS: dict[str, Callable[[KneeKinematics], Plot]] = {
    "distance_scatter": distance_scatter,
    "mld": mld,
    "extension_distance": extension_distance,
    "trajectories": trajectories,
    "angles": angles,
}
"""The plots by file stem, in report order."""


def save_all(kin: KneeKinematics, folder: Path | str) -> dict[str, tuple[Path, Plot]]:
    """Write every plot in ``PLOTS`` to ``folder/<name>.png`` (creating the folder).

    Args:
        kin: per-frame knee metrics.
        folder: output folder.

    Returns:
        By plot name, in report order: the written path and the plot.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    written: dict[str, tuple[Path, Plot]] = {}
    for name, draw in PLOTS.items():
        plot = draw(kin)
        path = folder / f"{name}.png"
        path.write_bytes(plot.png)
        written[name] = (path, plot)
    return written
