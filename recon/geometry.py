"""Projection geometry: immutable per-view cone-beam views and ordered geometries.

A :class:`View` is one flat-panel exposure: the focal spot ``source_mm``, the centre of
detector pixel (0, 0) ``detector_origin_mm``, unit vectors ``e_u`` (increasing column) and
``e_v`` (increasing row), the pixel pitches and the panel size. Its 3x4 projection matrix
``P`` maps world millimetres to pixel indices, ``(u*w, v*w, w) = P @ (x, y, z, 1)``, scaled so
that ``w`` is the fraction of the way from the source to the detector plane along the ray
(``w = 0`` at the source, ``w = 1`` on the detector, ``w > 0`` in front of the source).

A :class:`Geometry` is an ordered sequence of views sharing one panel size (a projection
stack). Both compare with ``==`` within :data:`ATOL_MM` and print a ``repr`` that rebuilds them.

Orbits built here rotate about world +z (up) through ``isocenter_mm``. At angle 0 the source
is anterior (-y) and the detector posterior (+y); angles increase counter-clockwise seen from
above. Detector rows increase upward (``e_v = +z``) and ``e_u x e_v`` points back at the
source, so images are seen from the source with row 0 at the bottom (display with
``origin="lower"``), and every view is expressible in RTK's parameters with positive distances.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Literal, overload

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

ATOL_MM = 1e-6
"""Tolerance for ``==`` on positions (mm) and unit vectors (dimensionless)."""


class DetectorSpec(BaseModel):
    """A flat-panel detector: ``rows x cols`` square pixels of ``pixel_pitch_mm``."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    rows: int = Field(gt=0, le=16384, description="pixels along e_v")
    cols: int = Field(gt=0, le=16384, description="pixels along e_u")
    pixel_pitch_mm: float = Field(gt=0.0, le=10.0, description="pixel pitch, mm")

    @property
    def width_mm(self) -> float:
        """Panel extent along e_u, mm (outer pixel edges)."""
        return self.cols * self.pixel_pitch_mm

    @property
    def height_mm(self) -> float:
        """Panel extent along e_v, mm (outer pixel edges)."""
        return self.rows * self.pixel_pitch_mm


def _vector3(name: str, value) -> np.ndarray:
    arr = np.array(value, dtype=np.float64).reshape(-1)
    if arr.shape != (3,):
        raise ValueError(f"{name} must have 3 components, got shape {np.shape(value)}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got {arr.tolist()}")
    arr.setflags(write=False)
    return arr


def _floats(arr: np.ndarray) -> list[float]:
    return [float(x) for x in arr]


@dataclass(frozen=True, eq=False)
class View:
    """One cone-beam view of a flat panel.

    Attributes:
        source_mm: focal spot, world mm, shape (3,).
        detector_origin_mm: centre of pixel (row 0, col 0), world mm, shape (3,).
        e_u: unit vector of increasing column index, shape (3,).
        e_v: unit vector of increasing row index, shape (3,).
        pitch_u_mm, pitch_v_mm: pixel pitch along e_u and e_v, mm.
        rows, cols: panel size in pixels; images are indexed [row, col] = [v, u].
    """

    source_mm: np.ndarray
    detector_origin_mm: np.ndarray
    e_u: np.ndarray
    e_v: np.ndarray
    pitch_u_mm: float
    pitch_v_mm: float
    rows: int
    cols: int

    def __post_init__(self) -> None:
        for name in ("source_mm", "detector_origin_mm", "e_u", "e_v"):
            object.__setattr__(self, name, _vector3(name, getattr(self, name)))
        for name in ("e_u", "e_v"):
            norm = float(np.linalg.norm(getattr(self, name)))
            if abs(norm - 1.0) > 1e-6:
                raise ValueError(f"{name} must be a unit vector, got norm {norm:.9g}")
        for name in ("pitch_u_mm", "pitch_v_mm"):
            value = float(getattr(self, name))
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"{name} must be a finite pitch > 0 mm, got {value!r}")
            object.__setattr__(self, name, value)
        for name in ("rows", "cols"):
            value = getattr(self, name)
            if int(value) != value or int(value) <= 0:
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
            object.__setattr__(self, name, int(value))
        cross = np.cross(self.e_u, self.e_v)
        if np.linalg.norm(cross) < 1e-3:
            raise ValueError("e_u and e_v are (nearly) parallel: not a detector plane")
        distance = float(np.dot(self.detector_origin_mm - self.source_mm, cross))
        if abs(distance) < 1e-3 * float(np.linalg.norm(cross)):
            raise ValueError("the source lies in the detector plane")

    # -- constructors -------------------------------------------------------------------

    @classmethod
    def from_poses(
        cls, source_mm: Sequence[float], T_world_detector: np.ndarray, detector: DetectorSpec
    ) -> View:
        """View from a focal spot and a detector pose.

        ``T_world_detector`` (4x4) follows docs/conventions.md: its origin is the centre of pixel
        (0, 0), its x axis is e_u and its y axis is e_v.
        """
        T = np.asarray(T_world_detector, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError(f"T_world_detector must be a finite 4x4 matrix, got {T.shape}")
        R = T[:3, :3]
        if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise ValueError("T_world_detector rotation is not a proper orthonormal matrix")
        return cls(
            source_mm=source_mm,
            detector_origin_mm=T[:3, 3],
            e_u=R[:, 0],
            e_v=R[:, 1],
            pitch_u_mm=detector.pixel_pitch_mm,
            pitch_v_mm=detector.pixel_pitch_mm,
            rows=detector.rows,
            cols=detector.cols,
        )

    @classmethod
    def from_center(
        cls,
        source_mm: Sequence[float],
        detector_center_mm: Sequence[float],
        e_u: Sequence[float],
        e_v: Sequence[float],
        detector: DetectorSpec,
    ) -> View:
        """View from the panel's centre point (between the middle pixels) and its axes."""
        center = _vector3("detector_center_mm", detector_center_mm)
        eu = _vector3("e_u", e_u)
        ev = _vector3("e_v", e_v)
        p = detector.pixel_pitch_mm
        origin = center - 0.5 * (detector.cols - 1) * p * eu - 0.5 * (detector.rows - 1) * p * ev
        return cls(source_mm, origin, eu, ev, p, p, detector.rows, detector.cols)

    @classmethod
    def from_matrix(cls, matrix: np.ndarray, pitch_u_mm: float, rows: int, cols: int) -> View:
        """Decompose a 3x4 projection matrix (world mm -> pixel indices).

        ``matrix`` may carry any positive scale; it must give ``w > 0`` for points between the
        source and the detector (negate matrices of toolkits with the opposite sign, e.g. RTK).
        The pitch along e_u fixes the detector distance; the pitch along e_v, the source
        position and the detector axes are recovered. Skewed pixel axes are kept as they are.
        """
        P = np.asarray(matrix, dtype=np.float64)
        if P.shape != (3, 4) or not np.all(np.isfinite(P)):
            raise ValueError(f"projection matrix must be a finite 3x4 array, got {P.shape}")
        M = P[:, :3]
        if abs(np.linalg.det(M)) < 1e-12 * np.linalg.norm(M) ** 3:
            raise ValueError("projection matrix is singular: no unique source position")
        A = np.linalg.inv(M)  # columns: scaled a = pitch_u*e_u, b = pitch_v*e_v, d0 - s
        source = -A @ P[:, 3]
        scale = float(pitch_u_mm) / np.linalg.norm(A[:, 0])
        a, b, c = (A[:, k] * scale for k in range(3))
        return cls(
            source_mm=source,
            detector_origin_mm=source + c,
            e_u=a / np.linalg.norm(a),
            e_v=b / np.linalg.norm(b),
            pitch_u_mm=float(pitch_u_mm),
            pitch_v_mm=float(np.linalg.norm(b)),
            rows=rows,
            cols=cols,
        )

    # -- derived quantities -------------------------------------------------------------

    @cached_property
    def matrix(self) -> np.ndarray:
        """3x4 projection matrix, world mm -> pixel indices, ``w`` = fraction of SDD."""
        A = np.column_stack(
            (
                self.pitch_u_mm * self.e_u,
                self.pitch_v_mm * self.e_v,
                self.detector_origin_mm - self.source_mm,
            )
        )
        Ainv = np.linalg.inv(A)
        P = np.hstack((Ainv, (-Ainv @ self.source_mm)[:, None]))
        P.setflags(write=False)
        return P

    @cached_property
    def normal(self) -> np.ndarray:
        """Unit normal of the detector plane pointing from the source towards the panel."""
        n = np.cross(self.e_u, self.e_v)
        n /= np.linalg.norm(n)
        if np.dot(self.detector_origin_mm - self.source_mm, n) < 0:
            n = -n
        n.setflags(write=False)
        return n

    @property
    def sdd_mm(self) -> float:
        """Perpendicular source-to-detector-plane distance, mm."""
        return float(np.dot(self.detector_origin_mm - self.source_mm, self.normal))

    @property
    def principal_point_px(self) -> tuple[float, float]:
        """(u, v) pixel coordinates of the foot of the perpendicular from the source."""
        u, v = self.project(self.source_mm + self.sdd_mm * self.normal)[0]
        return float(u), float(v)

    @property
    def detector_center_mm(self) -> np.ndarray:
        """World position of the panel centre (between the middle pixels), mm."""
        return (
            self.detector_origin_mm
            + 0.5 * (self.cols - 1) * self.pitch_u_mm * self.e_u
            + 0.5 * (self.rows - 1) * self.pitch_v_mm * self.e_v
        )

    @property
    def T_world_detector(self) -> np.ndarray:
        """4x4 pose of the detector frame (origin pixel (0, 0), x = e_u, y = e_v)."""
        if abs(float(np.dot(self.e_u, self.e_v))) > 1e-6:
            raise ValueError("detector axes are skewed: no rigid detector frame exists")
        T = np.eye(4)
        T[:3, 0], T[:3, 1] = self.e_u, self.e_v
        T[:3, 2] = np.cross(self.e_u, self.e_v)
        T[:3, 3] = self.detector_origin_mm
        return T

    def project(self, points_mm: np.ndarray) -> np.ndarray:
        """Pixel coordinates (u, v) of world points.

        Args:
            points_mm: World points (mm), shape (N, 3) or (3,).

        Returns:
            Detector coordinates (u, v) in pixels, shape (N, 2).

        Examples:
            The isocentre of a centred 96 x 96 panel falls between its two middle pixels:

            >>> panel = DetectorSpec(rows=96, cols=96, pixel_pitch_mm=2.0)
            >>> view = circular_orbit(4, 600.0, 1000.0, panel)[0]
            >>> view.project([0.0, 0.0, 0.0]).round(6).tolist()
            [[47.5, 47.5]]
        """
        pts = np.atleast_2d(np.asarray(points_mm, dtype=np.float64))
        h = pts @ self.matrix[:, :3].T + self.matrix[:, 3]
        return h[:, :2] / h[:, 2:3]

    def depth(self, points_mm: np.ndarray) -> np.ndarray:
        """``w`` of world points: 0 at the source, 1 on the detector plane.

        Args:
            points_mm: World points (mm), shape (N, 3) or (3,).

        Returns:
            The homogeneous depth ``w`` (unitless), shape (N,).
        """
        pts = np.atleast_2d(np.asarray(points_mm, dtype=np.float64))
        return pts @ self.matrix[2, :3] + self.matrix[2, 3]

    def pixel_to_world(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """World position of detector coordinates (u, v).

        Args:
            u: Column coordinate (pixels), any shape.
            v: Row coordinate (pixels), broadcastable with ``u``.

        Returns:
            World points (mm), shape broadcast(u, v) + (3,).
        """
        u = np.asarray(u, dtype=np.float64)[..., None]
        v = np.asarray(v, dtype=np.float64)[..., None]
        return (
            self.detector_origin_mm
            + u * self.pitch_u_mm * self.e_u
            + v * self.pitch_v_mm * self.e_v
        )

    def transformed(self, T: np.ndarray) -> View:
        """The view carried by the rigid motion ``T`` (4x4, mm): source, panel and axes move.

        Projecting a volume moved by ``T`` through this view equals projecting the unmoved
        volume through ``view.transformed(inv(T))``.

        Args:
            T: Rigid transform, 4x4, translation in mm.
        """
        T = np.asarray(T, dtype=np.float64)
        R, t = T[:3, :3], T[:3, 3]
        return View(
            R @ self.source_mm + t,
            R @ self.detector_origin_mm + t,
            R @ self.e_u,
            R @ self.e_v,
            self.pitch_u_mm,
            self.pitch_v_mm,
            self.rows,
            self.cols,
        )

    def binned(self, factor: int) -> View:
        """The view read out with ``factor x factor`` pixels binned (pitch x factor).

        Args:
            factor: Binning factor, a positive integer; the panel keeps ``rows // factor``
                rows and ``cols // factor`` columns.
        """
        if int(factor) != factor or factor < 1:
            raise ValueError(f"binning factor must be a positive integer, got {factor!r}")
        if factor == 1:
            return self
        shift = 0.5 * (factor - 1)
        origin = self.pixel_to_world(shift, shift)
        return View(
            self.source_mm,
            origin,
            self.e_u,
            self.e_v,
            self.pitch_u_mm * factor,
            self.pitch_v_mm * factor,
            self.rows // factor,
            self.cols // factor,
        )

    def cropped(self, row0: int, col0: int, rows: int, cols: int) -> View:
        """The sub-panel of ``rows x cols`` pixels starting at pixel (row0, col0).

        Args:
            row0: First row kept (pixels).
            col0: First column kept (pixels).
            rows: Number of rows kept.
            cols: Number of columns kept.
        """
        if not (
            0 <= row0
            and 0 <= col0
            and rows > 0
            and cols > 0
            and row0 + rows <= self.rows
            and col0 + cols <= self.cols
        ):
            raise ValueError(
                f"crop ({row0}, {col0}) + ({rows}, {cols}) leaves the "
                f"{self.rows} x {self.cols} panel"
            )
        origin = self.pixel_to_world(col0, row0)
        return View(
            self.source_mm, origin, self.e_u, self.e_v, self.pitch_u_mm, self.pitch_v_mm, rows, cols
        )

    # -- value semantics ----------------------------------------------------------------

    def isclose(self, other: View, atol_mm: float = ATOL_MM) -> bool:
        """Same panel size and every vector and pitch within ``atol_mm``.

        Args:
            other: The view compared with this one.
            atol_mm: Absolute tolerance (mm) on positions and pitches; unit vectors use the
                same number.
        """
        return (
            self.rows == other.rows
            and self.cols == other.cols
            and abs(self.pitch_u_mm - other.pitch_u_mm) <= atol_mm
            and abs(self.pitch_v_mm - other.pitch_v_mm) <= atol_mm
            and all(
                np.allclose(getattr(self, k), getattr(other, k), rtol=0.0, atol=atol_mm)
                for k in ("source_mm", "detector_origin_mm", "e_u", "e_v")
            )
        )

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, View):
            return NotImplemented
        return self.isclose(other)

    __hash__ = None  # type: ignore[assignment]  # equality is approximate

    def __repr__(self) -> str:
        return (
            f"View(source_mm={_floats(self.source_mm)}, "
            f"detector_origin_mm={_floats(self.detector_origin_mm)}, "
            f"e_u={_floats(self.e_u)}, e_v={_floats(self.e_v)}, "
            f"pitch_u_mm={self.pitch_u_mm!r}, pitch_v_mm={self.pitch_v_mm!r}, "
            f"rows={self.rows}, cols={self.cols})"
        )


class Geometry(Sequence[View]):
    """An ordered, immutable sequence of views with one panel size (one projection stack).

    Index with an int for a :class:`View`, with a slice or an index array for a
    sub-``Geometry``. Stacked arrays (``matrices``, ``sources_mm``) serve the kernels.
    """

    __slots__ = ("__dict__", "_views")

    def __init__(self, views: Sequence[View]) -> None:
        views = tuple(views)
        if not views:
            raise ValueError("a Geometry needs at least one view")
        for i, view in enumerate(views):
            if not isinstance(view, View):
                raise TypeError(f"view {i} is a {type(view).__name__}, not a View")
            if (view.rows, view.cols) != (views[0].rows, views[0].cols):
                raise ValueError(
                    f"view {i} has a {view.rows}x{view.cols} panel, view 0 has "
                    f"{views[0].rows}x{views[0].cols}: one geometry is one projection stack"
                )
        self._views = views

    @classmethod
    def from_matrices(cls, matrices: np.ndarray, detector: DetectorSpec) -> Geometry:
        """Geometry from stacked 3x4 matrices (N, 3, 4), see :meth:`View.from_matrix`."""
        mats = np.asarray(matrices, dtype=np.float64)
        if mats.ndim != 3 or mats.shape[1:] != (3, 4):
            raise ValueError(f"matrices must have shape (N, 3, 4), got {mats.shape}")
        views = []
        for i, P in enumerate(mats):
            try:
                views.append(
                    View.from_matrix(P, detector.pixel_pitch_mm, detector.rows, detector.cols)
                )
            except ValueError as err:
                raise ValueError(f"projection matrix {i}: {err}") from None
        return cls(views)

    @property
    def rows(self) -> int:
        return self._views[0].rows

    @property
    def cols(self) -> int:
        return self._views[0].cols

    @cached_property
    def matrices(self) -> np.ndarray:
        """Projection matrices stacked, float64 (N, 3, 4)."""
        out = np.stack([v.matrix for v in self._views])
        out.setflags(write=False)
        return out

    @cached_property
    def sources_mm(self) -> np.ndarray:
        """Focal spots stacked, world mm (N, 3)."""
        out = np.stack([v.source_mm for v in self._views])
        out.setflags(write=False)
        return out

    def transformed(self, T: np.ndarray) -> Geometry:
        """Every view carried by the rigid motion ``T`` (see :meth:`View.transformed`).

        Args:
            T: Rigid transform, 4x4, translation in mm.
        """
        return Geometry([v.transformed(T) for v in self._views])

    def __len__(self) -> int:
        return len(self._views)

    @overload
    def __getitem__(self, index: int) -> View: ...

    @overload
    def __getitem__(self, index: slice | Sequence[int] | np.ndarray) -> Geometry: ...

    def __getitem__(self, index):
        if isinstance(index, slice):
            return Geometry(self._views[index])
        if isinstance(index, (int, np.integer)):
            return self._views[index]
        return Geometry([self._views[int(i)] for i in np.asarray(index).reshape(-1)])

    def __iter__(self) -> Iterator[View]:
        return iter(self._views)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Geometry):
            return NotImplemented
        return len(self) == len(other) and all(a == b for a, b in zip(self, other, strict=True))

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        inner = ",\n    ".join(repr(v) for v in self._views)
        return f"Geometry([\n    {inner},\n])"


# -- orbits ------------------------------------------------------------------------------


def _orbit_view(
    angle_rad: float,
    z_mm: float,
    sid_mm: float,
    sdd_mm: float,
    detector: DetectorSpec,
    isocenter_mm: np.ndarray,
) -> View:
    toward_source = np.array([math.sin(angle_rad), -math.cos(angle_rad), 0.0])
    e_u = np.array([math.cos(angle_rad), math.sin(angle_rad), 0.0])
    center = isocenter_mm + np.array([0.0, 0.0, z_mm])
    return View.from_center(
        source_mm=center + sid_mm * toward_source,
        detector_center_mm=center - (sdd_mm - sid_mm) * toward_source,
        e_u=e_u,
        e_v=(0.0, 0.0, 1.0),
        detector=detector,
    )


def _check_distances(sid_mm: float, sdd_mm: float) -> None:
    if not (math.isfinite(sid_mm) and sid_mm > 0):
        raise ValueError(f"sid_mm must be > 0, got {sid_mm!r}")
    if not (math.isfinite(sdd_mm) and sdd_mm > sid_mm):
        raise ValueError(f"sdd_mm must exceed sid_mm = {sid_mm!r}, got {sdd_mm!r}")


def short_scan_arc_deg(sdd_mm: float, detector: DetectorSpec) -> float:
    """Minimal short-scan arc of a centred panel: 180 degrees plus the full fan angle.

    Args:
        sdd_mm: Source-to-detector distance (mm).
        detector: The panel; its width sets the fan angle.

    Returns:
        The arc (degrees).

    Examples:
        A 307.2 mm wide panel 1000 mm from the source:

        >>> panel = DetectorSpec(rows=64, cols=512, pixel_pitch_mm=0.6)
        >>> round(short_scan_arc_deg(1000.0, panel), 2)
        197.46
    """
    return 180.0 + 2.0 * math.degrees(math.atan(0.5 * detector.width_mm / sdd_mm))


def circular_orbit(
    n_views: int,
    sid_mm: float,
    sdd_mm: float,
    detector: DetectorSpec,
    arc_deg: float = 360.0,
    start_deg: float = 0.0,
    isocenter_mm: Sequence[float] = (0.0, 0.0, 0.0),
) -> Geometry:
    """Circular orbit about world z through ``isocenter_mm``.

    A 360-degree arc spaces views by 360/n (no repeated end view); shorter arcs (short scans,
    see :func:`short_scan_arc_deg`) include both end angles.

    Args:
        n_views: Number of views.
        sid_mm: Source-to-isocentre distance (mm).
        sdd_mm: Source-to-detector distance (mm), larger than ``sid_mm``.
        detector: Panel size and pixel pitch.
        arc_deg: Angle swept (degrees), in (0, 3600].
        start_deg: Angle of the first view (degrees); 0 puts the source on -y (anterior).
        isocenter_mm: Centre of rotation in the world (mm).

    Examples:
        >>> panel = DetectorSpec(rows=96, cols=96, pixel_pitch_mm=2.0)
        >>> views = circular_orbit(180, 600.0, 1000.0, panel)
        >>> len(views), views.rows, views.cols
        (180, 96, 96)
        >>> [round(float(x), 6) + 0.0 for x in views[0].source_mm]  # angle 0: the source anterior
        [0.0, -600.0, 0.0]
    """
    return helical_orbit(
        n_views,
        sid_mm,
        sdd_mm,
        detector,
        arc_deg=arc_deg,
        z_start_mm=0.0,
        z_end_mm=0.0,
        start_deg=start_deg,
        isocenter_mm=isocenter_mm,
    )


def helical_orbit(
    n_views: int,
    sid_mm: float,
    sdd_mm: float,
    detector: DetectorSpec,
    arc_deg: float,
    z_start_mm: float,
    z_end_mm: float | None = None,
    z_step_mm: float | None = None,
    passes: int = 1,
    alternate: bool = True,
    start_deg: float = 0.0,
    isocenter_mm: Sequence[float] = (0.0, 0.0, 0.0),
) -> Geometry:
    """Helix or reverse spiral about world z: the orbit turns while z moves linearly.

    ``n_views`` are split evenly over ``passes``; each pass sweeps ``arc_deg`` from
    ``start_deg``, and with ``alternate`` every second pass sweeps back (reverse spiral).
    z advances by ``z_step_mm`` per view, or evenly from ``z_start_mm`` to ``z_end_mm``
    (give exactly one of the two). A single pass of a whole number of turns spaces views
    without repeating the start angle; other arcs include both end angles.

    Args:
        n_views: Number of views, a multiple of ``passes``.
        sid_mm: Source-to-isocentre distance (mm).
        sdd_mm: Source-to-detector distance (mm), larger than ``sid_mm``.
        detector: Panel size and pixel pitch.
        arc_deg: Angle swept by each pass (degrees), in (0, 3600].
        z_start_mm: Height of the first view's isocentre above ``isocenter_mm`` (mm).
        z_end_mm: Height of the last view (mm); or give ``z_step_mm``.
        z_step_mm: Height change per view (mm); or give ``z_end_mm``.
        passes: Number of passes.
        alternate: Sweep every second pass backwards (a reverse spiral).
        start_deg: Angle of the first view (degrees); 0 puts the source on -y (anterior).
        isocenter_mm: Centre of rotation at z = 0 (mm).
    """
    _check_distances(sid_mm, sdd_mm)
    if int(n_views) != n_views or n_views < 1:
        raise ValueError(f"n_views must be a positive integer, got {n_views!r}")
    if int(passes) != passes or passes < 1 or n_views % passes:
        raise ValueError(f"passes must divide n_views = {n_views}, got {passes!r}")
    if not (math.isfinite(arc_deg) and 0.0 < arc_deg <= 3600.0):
        raise ValueError(f"arc_deg must be in (0, 3600], got {arc_deg!r}")
    if (z_end_mm is None) == (z_step_mm is None):
        raise ValueError("give exactly one of z_end_mm and z_step_mm")
    if z_step_mm is None:
        z = np.linspace(z_start_mm, z_end_mm, n_views)
    else:
        z = z_start_mm + z_step_mm * np.arange(n_views)
    if not np.all(np.isfinite(z)):
        raise ValueError("z positions must be finite")
    iso = _vector3("isocenter_mm", isocenter_mm)
    per_pass = n_views // passes
    whole_turns = passes == 1 and math.isclose(arc_deg % 360.0, 0.0, abs_tol=1e-9)
    fractions = (
        np.arange(per_pass) / per_pass
        if whole_turns
        else np.linspace(0.0, 1.0, per_pass)
        if per_pass > 1
        else np.zeros(1)
    )
    angles = []
    for k in range(passes):
        sweep = fractions[::-1] if (alternate and k % 2) else fractions
        angles.append(start_deg + arc_deg * sweep)
    angles_rad = np.radians(np.concatenate(angles))
    return Geometry(
        [
            _orbit_view(float(a), float(zz), sid_mm, sdd_mm, detector, iso)
            for a, zz in zip(angles_rad, z, strict=True)
        ]
    )


class OrbitSpec(BaseModel):
    """A scan orbit about world z, as written in protocol files (units in the names).

    ``kind``: ``circular`` (``arc_deg`` default 360), ``short_scan`` (``arc_deg`` default 180
    plus the fan plus ``overscan_deg``), ``helix`` (one pass of ``arc_deg``, which may exceed
    360), ``reverse_spiral`` (``passes`` sweeps of ``arc_deg``, alternating direction) or
    ``static`` (every view at ``start_deg``: a fluoroscopy pose).
    Helices and spirals move z through ``z_travel_mm`` in total, or ``z_step_mm`` per view,
    centred on ``isocenter_mm``'s z.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    kind: Literal["circular", "short_scan", "helix", "reverse_spiral", "static"]
    views: int = Field(ge=3, le=20000)
    sid_mm: float = Field(gt=0.0, le=3000.0, description="source to rotation axis, mm")
    sdd_mm: float = Field(gt=0.0, le=5000.0, description="source to detector, mm")
    arc_deg: float | None = Field(default=None, gt=0.0, le=3600.0)
    overscan_deg: float = Field(default=2.0, ge=0.0, le=180.0)
    passes: int = Field(default=1, ge=1, le=100)
    z_travel_mm: float | None = Field(default=None, ge=-2000.0, le=2000.0)
    z_step_mm: float | None = Field(default=None, ge=-50.0, le=50.0)
    start_deg: float = Field(default=0.0, ge=-360.0, le=360.0)
    isocenter_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @model_validator(mode="after")
    def _consistent(self) -> OrbitSpec:
        if self.sdd_mm <= self.sid_mm:
            raise ValueError(
                f"sdd_mm = {self.sdd_mm} must exceed sid_mm = {self.sid_mm} (detector beyond "
                "the rotation axis)"
            )
        moving = self.kind in ("helix", "reverse_spiral")
        if moving and (self.z_travel_mm is None) == (self.z_step_mm is None):
            raise ValueError(f"a {self.kind} needs exactly one of z_travel_mm and z_step_mm")
        if not moving and (self.z_travel_mm or self.z_step_mm):
            raise ValueError(f"a {self.kind} orbit does not move in z: drop z_travel_mm/z_step_mm")
        if self.kind == "reverse_spiral" and self.passes < 2:
            raise ValueError(f"a reverse_spiral needs passes >= 2, got {self.passes}")
        if self.kind != "reverse_spiral" and self.passes != 1:
            raise ValueError(f"passes = {self.passes} needs kind reverse_spiral")
        if self.views % self.passes:
            raise ValueError(f"views = {self.views} must divide evenly into passes = {self.passes}")
        return self

    def geometry(self, detector: DetectorSpec) -> Geometry:
        """The orbit's views for a panel of ``detector`` pixels."""
        iso = np.array(self.isocenter_mm, dtype=np.float64)
        if self.kind == "static":
            _check_distances(self.sid_mm, self.sdd_mm)
            view = _orbit_view(
                math.radians(self.start_deg), 0.0, self.sid_mm, self.sdd_mm, detector, iso
            )
            return Geometry([view] * self.views)
        if self.kind in ("circular", "short_scan"):
            arc = self.arc_deg
            if arc is None:
                arc = (
                    360.0
                    if self.kind == "circular"
                    else (short_scan_arc_deg(self.sdd_mm, detector) + self.overscan_deg)
                )
            return circular_orbit(
                self.views,
                self.sid_mm,
                self.sdd_mm,
                detector,
                arc_deg=arc,
                start_deg=self.start_deg,
                isocenter_mm=iso,
            )
        travel = (
            self.z_travel_mm if self.z_travel_mm is not None else self.z_step_mm * (self.views - 1)
        )
        return helical_orbit(
            self.views,
            self.sid_mm,
            self.sdd_mm,
            detector,
            arc_deg=360.0 if self.arc_deg is None else self.arc_deg,
            z_start_mm=-0.5 * travel,
            z_end_mm=0.5 * travel,
            passes=self.passes,
            start_deg=self.start_deg,
            isocenter_mm=iso,
        )
