"""RTK ``ThreeDCircularProjectionGeometry`` XML: our interchange format for geometries.

RTK describes each view by nine parameters in a frame rotated by ``M_R = Rz(-in_plane)
Rx(-out_of_plane) Ry(-gantry)``: the source at ``(SourceOffsetX, SourceOffsetY,
SourceToIsocenterDistance)`` and the detector's projection coordinate ``(a, b)`` at
``(a + ProjectionOffsetX, b + ProjectionOffsetY, SID - SDD)``. Its matrices map world mm to
the projection image's physical mm; the projection image's header (origin, spacing and
direction: :class:`PanelHeader`) turns those into pixel indices. That image lives beside the
XML (an ``.mha`` stack), so reading and writing take its header explicitly; RTK's own
projectors honour all three fields, and so does :func:`read_rtk_geometry`, the one place a
header becomes a panel.

Signs. The rotated frame's z axis is the panel's normal ``row x column``. When it points back
at the source (our orbits, recon.geometry), SID and SDD are positive and RTK's matrices have
``w < 0`` in front of the source; when it points towards the panel (a panel turned or
mirrored in its plane, e.g. rows along the rotation axis, as RTK's
``AddProjection(source, detector, row, column)`` builds it), SID and SDD are negative and
``w > 0`` in front. The detector lies at ``w = -SDD``, so a matrix read from RTK is scaled by
``-sign(SDD)``: ``w > 0`` between source and panel, always (docs/conventions.md).

RTK can express every view with orthogonal pixel axes on a flat panel; skewed axes, parallel
beams (SDD 0) and cylindrical detectors are refused with the file, projection and field named.
"""

from __future__ import annotations

import math
import sys
import warnings
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from recon.geometry import Geometry, View

_ANGLES = ("GantryAngle", "OutOfPlaneAngle", "InPlaneAngle")
_DISTANCES = (
    "SourceToIsocenterDistance",
    "SourceOffsetX",
    "SourceOffsetY",
    "SourceToDetectorDistance",
    "ProjectionOffsetX",
    "ProjectionOffsetY",
)
_DEFAULTS = {name: 0.0 for name in (*_ANGLES, *_DISTANCES)} | {"RadiusCylindricalDetector": 0.0}
_IGNORED = {"CollimationUInf", "CollimationUSup", "CollimationVInf", "CollimationVSup"}
_MATRIX_RTOL = 1e-6
_ORTHONORMAL_ATOL = 1e-6


def centered_origin_uv_mm(
    rows: int, cols: int, pitch_u_mm: float, pitch_v_mm: float
) -> tuple[float, float]:
    """Projection-image origin (mm) that centres the panel on RTK's detector origin.

    Args:
        rows: panel rows, pixels.
        cols: panel columns, pixels.
        pitch_u_mm: pixel pitch along a row (u), mm.
        pitch_v_mm: pixel pitch along a column (v), mm.

    Returns:
        (u, v) of the centre of pixel (row 0, column 0), mm.
    """
    return (-0.5 * (cols - 1) * pitch_u_mm, -0.5 * (rows - 1) * pitch_v_mm)


@dataclass(frozen=True)
class PanelHeader:
    """Where a projection stack's pixels lie in RTK's projection plane: its image header.

    Pixel (col i, row j) sits at ``origin_mm + direction @ (i * spacing_u, j * spacing_v)``
    in RTK's projection coordinates (mm), as ITK places image indices.

    Attributes:
        rows, cols: panel size in pixels.
        spacing_mm: pixel pitch (u, v) = (along the image's i axis, along its j axis), mm.
        origin_mm: physical position of pixel (0, 0), mm; ``None`` centres the panel.
        direction: 2x2, columns the image's i and j axes in projection coordinates
            (orthonormal: a rotation or a reflection of the plane).
        source: what the header was read from, for error messages.
    """

    rows: int
    cols: int
    spacing_mm: tuple[float, float]
    origin_mm: tuple[float, float] | None = None
    direction: tuple[tuple[float, float], tuple[float, float]] = ((1.0, 0.0), (0.0, 1.0))
    source: str = field(default="the projection stack", compare=False)

    def __post_init__(self) -> None:
        for name in ("rows", "cols"):
            value = getattr(self, name)
            if int(value) != value or value <= 0:
                raise ValueError(f"{self.source}: {name} must be a positive integer, got {value!r}")
        spacing = tuple(float(x) for x in self.spacing_mm)
        if len(spacing) != 2 or not all(math.isfinite(x) and x > 0 for x in spacing):
            raise ValueError(
                f"{self.source}: Spacing must be 2 finite pitches > 0 mm, got {self.spacing_mm!r}"
            )
        object.__setattr__(self, "spacing_mm", spacing)
        origin = self.origin_mm
        if origin is None:
            origin = centered_origin_uv_mm(self.rows, self.cols, *spacing)
        origin = tuple(float(x) for x in origin)
        if len(origin) != 2 or not all(math.isfinite(x) for x in origin):
            raise ValueError(f"{self.source}: Origin must be 2 finite numbers, got {origin!r}")
        object.__setattr__(self, "origin_mm", origin)
        d = np.asarray(self.direction, dtype=np.float64)
        if d.shape != (2, 2) or not np.allclose(d.T @ d, np.eye(2), atol=_ORTHONORMAL_ATOL):
            raise ValueError(
                f"{self.source}: Direction {np.round(d, 6).tolist()} of the panel's axes is not "
                "orthonormal: RTK's detector has orthogonal pixel axes of the given spacing"
            )
        object.__setattr__(self, "direction", tuple(tuple(float(x) for x in row) for row in d))

    @classmethod
    def centered(
        cls,
        rows: int,
        cols: int,
        pitch_u_mm: float,
        pitch_v_mm: float | None = None,
        source: str = "the projection stack",
    ) -> PanelHeader:
        """A panel centred on RTK's detector origin with identity direction."""
        pitch_v = pitch_u_mm if pitch_v_mm is None else pitch_v_mm
        return cls(rows, cols, (pitch_u_mm, pitch_v), source=source)

    @property
    def to_index(self) -> np.ndarray:
        """3x3 homogeneous map: projection coordinates (mm) -> pixel indices (u, v)."""
        d = np.asarray(self.direction)
        inv = np.diag(1.0 / np.asarray(self.spacing_mm)) @ d.T
        out = np.eye(3)
        out[:2, :2] = inv
        out[:2, 2] = -inv @ np.asarray(self.origin_mm)
        return out

    def check_views(self, geometry: Geometry, where: str) -> None:
        """ValueError unless ``geometry`` is a stack of this panel (size and pitch).

        Args:
            geometry: The views checked.
            where: Name of the file or field the message starts with.
        """
        if (geometry.rows, geometry.cols) != (self.rows, self.cols):
            raise ValueError(
                f"{where}: the geometry's panel has {geometry.rows} x {geometry.cols} pixels, "
                f"{self.source}'s header {self.rows} x {self.cols}"
            )
        for i, view in enumerate(geometry):
            pitch = (view.pitch_u_mm, view.pitch_v_mm)
            if not np.allclose(pitch, self.spacing_mm, rtol=1e-9, atol=0.0):
                raise ValueError(
                    f"{where}: view {i} has pitch {pitch} mm, {self.source}'s header Spacing "
                    f"{self.spacing_mm} mm: an RTK projection stack has one pixel spacing"
                )


def rtk_parameters(view: View, header: PanelHeader) -> dict[str, float]:
    """RTK's nine parameters (mm, degrees in [0, 360)) of one view of a stack with ``header``.

    SID and SDD come out negative when the panel's ``row x column`` normal points away from
    the source (module docstring). Raises ValueError for skewed pixel axes.
    """
    if abs(float(np.dot(view.e_u, view.e_v))) > 1e-9:
        raise ValueError(
            "RTK geometry needs orthogonal detector axes; this view's e_u . e_v = "
            f"{float(np.dot(view.e_u, view.e_v)):.3g}"
        )
    d = np.asarray(header.direction)
    axes = np.column_stack((view.e_u, view.e_v)) @ d.T  # RTK's row and column axes, world
    row, col = axes[:, 0], axes[:, 1]
    origin = view.detector_origin_mm - axes @ np.asarray(header.origin_mm)  # (0, 0) mm
    R = np.vstack((row, col, np.cross(row, col)))  # world -> rotated
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # gimbal lock at 90 deg out of plane
        gantry, out_of_plane, in_plane = Rotation.from_matrix(R.T).as_euler("YXZ", degrees=True)
    sx, sy, sid = R @ view.source_mm
    dx, dy, dz = R @ origin
    return {
        "GantryAngle": float(gantry % 360.0),
        "OutOfPlaneAngle": float(out_of_plane % 360.0),
        "InPlaneAngle": float(in_plane % 360.0),
        "SourceToIsocenterDistance": float(sid),
        "SourceOffsetX": float(sx),
        "SourceOffsetY": float(sy),
        "SourceToDetectorDistance": float(sid - dz),
        "ProjectionOffsetX": float(dx),
        "ProjectionOffsetY": float(dy),
    }


def rtk_matrix(params: dict[str, float]) -> np.ndarray:
    """RTK's 3x4 matrix of one view: world mm -> projection physical mm (RTK's sign)."""
    rot = Rotation.from_euler(
        "YXZ",
        [params["GantryAngle"], params["OutOfPlaneAngle"], params["InPlaneAngle"]],
        degrees=True,
    )
    M_R = np.eye(4)
    M_R[:3, :3] = rot.as_matrix().T
    sx, sy = params["SourceOffsetX"], params["SourceOffsetY"]
    px, py = params["ProjectionOffsetX"], params["ProjectionOffsetY"]
    sid, sdd = params["SourceToIsocenterDistance"], params["SourceToDetectorDistance"]
    shift = np.array([[1.0, 0.0, sx - px], [0.0, 1.0, sy - py], [0.0, 0.0, 1.0]])
    magnify = np.array([[-sdd, 0.0, 0.0, 0.0], [0.0, -sdd, 0.0, 0.0], [0.0, 0.0, 1.0, -sid]])
    to_source = np.eye(4)
    to_source[:2, 3] = (-sx, -sy)
    return shift @ magnify @ to_source @ M_R


def pixel_matrix(rtk: np.ndarray, sdd_mm: float, header: PanelHeader) -> np.ndarray:
    """Our 3x4 matrix (world mm -> pixel indices, ``w > 0`` in front of the source) of RTK's
    matrix ``rtk`` of a view with SourceToDetectorDistance ``sdd_mm`` on ``header``'s panel."""
    return -math.copysign(1.0, sdd_mm) * (header.to_index @ rtk)


def _format(x: float) -> str:
    """Shortest round-trip text; subnormal numbers (below 2.2e-308, which RTK's reader
    cannot parse) as 0."""
    x = float(x)
    return repr(x if abs(x) >= sys.float_info.min else 0.0)


def write_rtk_geometry(
    path: str | Path, geometry: Geometry, header: PanelHeader | None = None
) -> Path:
    """Write ``geometry`` as RTK XML (version 3), every parameter per projection.

    ``header`` is the projection stack's header that the geometry belongs to (its origin,
    spacing and direction); ``None`` means a centred panel with the views' pitch. Raises
    ValueError for views RTK cannot express (skewed axes) and for a header that contradicts
    the views (panel size, pitch).

    Args:
        path: XML file written.
        geometry: The views.
        header: The projection stack's header, or ``None`` for a centred panel.

    Returns:
        ``path``.
    """
    path = Path(path)
    pu, pv = geometry[0].pitch_u_mm, geometry[0].pitch_v_mm
    if header is None:
        header = PanelHeader.centered(geometry.rows, geometry.cols, pu, pv)
    header.check_views(geometry, str(path))
    root = ET.Element("RTKThreeDCircularGeometry", version="3")
    for i, view in enumerate(geometry):
        try:
            params = rtk_parameters(view, header)
        except ValueError as err:
            raise ValueError(f"{path}: view {i}: {err}") from None
        mat = rtk_matrix(params)
        ours = pixel_matrix(mat, params["SourceToDetectorDistance"], header)
        ours *= np.linalg.norm(view.matrix) / np.linalg.norm(ours)
        if not np.allclose(ours, view.matrix, rtol=0, atol=1e-9 * np.abs(view.matrix).max()):
            raise AssertionError(f"view {i}: RTK parameters do not reproduce the view")
        proj = ET.SubElement(root, "Projection")
        for name, value in params.items():
            ET.SubElement(proj, name).text = _format(value)
        rows = "\n".join("  ".join(_format(x) for x in row) for row in mat)
        ET.SubElement(proj, "Matrix").text = f"\n{rows}\n"
    ET.indent(root)
    body = ET.tostring(root, encoding="unicode")
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(f'<?xml version="1.0"?>\n<!DOCTYPE RTKGEOMETRY>\n{body}\n', encoding="utf-8")
    tmp.replace(path)
    return path


def _float(path: Path, element: ET.Element, where: str) -> float:
    try:
        value = float(element.text)
    except (TypeError, ValueError):
        raise ValueError(
            f"{path}: {where}: <{element.tag}> is not a number: {element.text!r}"
        ) from None
    if not math.isfinite(value):
        raise ValueError(f"{path}: {where}: <{element.tag}> is not finite: {value!r}")
    return value


def read_rtk_matrices(path: str | Path) -> tuple[list[dict[str, float]], np.ndarray]:
    """Parse RTK XML: per-projection parameters and RTK's matrices (N, 3, 4), checked.

    Raises ValueError naming the file and projection for malformed content, cylindrical
    detectors, and stored matrices that disagree with the parameters.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such geometry file")
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as err:
        raise ValueError(f"{path}: not valid XML ({err})") from None
    if root.tag != "RTKThreeDCircularGeometry":
        raise ValueError(f"{path}: root element is <{root.tag}>, not <RTKThreeDCircularGeometry>")
    if root.get("version") != "3":
        raise ValueError(f"{path}: RTK geometry version {root.get('version')!r}; only 3 is read")
    common = dict(_DEFAULTS)
    projections = []
    for child in root:
        if child.tag == "Projection":
            projections.append(child)
        elif child.tag in _DEFAULTS:
            common[child.tag] = _float(path, child, "global")
        elif child.tag not in _IGNORED:
            raise ValueError(f"{path}: unknown element <{child.tag}>")
    if not projections:
        raise ValueError(f"{path}: no <Projection> elements")
    all_params, matrices = [], []
    for i, proj in enumerate(projections):
        params = dict(common)
        stored = None
        for child in proj:
            if child.tag == "Matrix":
                try:
                    stored = np.array(child.text.split(), dtype=np.float64).reshape(3, 4)
                except (AttributeError, ValueError):
                    raise ValueError(
                        f"{path}: projection {i}: <Matrix> is not 12 numbers"
                    ) from None
            elif child.tag in _DEFAULTS:
                params[child.tag] = _float(path, child, f"projection {i}")
            elif child.tag not in _IGNORED:
                raise ValueError(f"{path}: projection {i}: unknown element <{child.tag}>")
        if params["RadiusCylindricalDetector"] != 0.0:
            raise ValueError(
                f"{path}: projection {i}: RadiusCylindricalDetector = "
                f"{params['RadiusCylindricalDetector']!r}: cylindrical detectors are not "
                "supported (flat panels only, radius 0)"
            )
        if params["SourceToDetectorDistance"] == 0.0:
            raise ValueError(
                f"{path}: projection {i}: SourceToDetectorDistance = 0 is RTK's parallel "
                "beam, which is not supported (cone beam only)"
            )
        mat = rtk_matrix(params)
        if stored is not None and not np.allclose(
            stored, mat, rtol=0, atol=_MATRIX_RTOL * np.abs(mat).max()
        ):
            raise ValueError(
                f"{path}: projection {i}: stored <Matrix> disagrees with the parameters"
            )
        all_params.append(params)
        matrices.append(mat)
    return all_params, np.stack(matrices)


def read_rtk_geometry(path: str | Path, header: PanelHeader) -> Geometry:
    """Read RTK XML as the :class:`Geometry` of the projection stack whose header is ``header``.

    RTK's matrices (projection mm) go through the header's origin, spacing and direction to
    pixel indices, each view's sign chosen so that ``w > 0`` in front of its source.
    ValueError names the file and projection of a view that has no source.

    Args:
        path: RTK geometry XML file.
        header: The stack's panel (:func:`recon.io.read_stack_header`, or
            ``PanelHeader.centered`` for images without one).
    """
    params, matrices = read_rtk_matrices(path)
    views = []
    for i, (p, m) in enumerate(zip(params, matrices, strict=True)):
        P = pixel_matrix(m, p["SourceToDetectorDistance"], header)
        try:
            views.append(View.from_matrix(P, header.spacing_mm[0], header.rows, header.cols))
        except ValueError as err:
            raise ValueError(f"{path}: projection {i}: {err}") from None
    return Geometry(views)
