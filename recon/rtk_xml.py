"""RTK ``ThreeDCircularProjectionGeometry`` XML: our interchange format for geometries.

RTK describes each view by nine parameters in a frame rotated by ``M_R = Rz(-in_plane)
Rx(-out_of_plane) Ry(-gantry)``: the source at ``(SourceOffsetX, SourceOffsetY,
SourceToIsocenterDistance)`` and the detector's projection coordinate ``(a, b)`` at
``(a + ProjectionOffsetX, b + ProjectionOffsetY, SID - SDD)``. Its matrices map world mm to
the projection image's physical mm (with ``w < 0`` in front of the source); the projection
image's origin and spacing turn those into pixel indices. That image lives beside the XML (an
``.mha`` stack), so reading and writing take the panel and its origin explicitly. By default
the origin is centred: ``(-(cols-1)/2 * pitch_u, -(rows-1)/2 * pitch_v)`` (see recon.io).

Any view with orthonormal detector axes is expressible; ``e_u x e_v`` pointing back at the
source keeps RTK's distances positive (our orbits do, see recon.geometry).
"""

from __future__ import annotations

import math
import warnings
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from recon.geometry import DetectorSpec, Geometry, View

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


def centered_origin_uv_mm(rows: int, cols: int, pitch_u_mm: float, pitch_v_mm: float):
    """Projection-image origin (mm) that centres the panel on RTK's detector origin."""
    return (-0.5 * (cols - 1) * pitch_u_mm, -0.5 * (rows - 1) * pitch_v_mm)


def rtk_parameters(view: View, origin_uv_mm: tuple[float, float]) -> dict[str, float]:
    """RTK's nine parameters (mm, degrees in [0, 360)) of one view."""
    if abs(float(np.dot(view.e_u, view.e_v))) > 1e-9:
        raise ValueError("RTK geometry needs orthogonal detector axes; this view is skewed")
    R = np.vstack((view.e_u, view.e_v, np.cross(view.e_u, view.e_v)))  # world -> rotated
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # gimbal lock at 90 deg out of plane
        gantry, out_of_plane, in_plane = Rotation.from_matrix(R.T).as_euler("YXZ", degrees=True)
    sx, sy, sid = R @ view.source_mm
    dx, dy, dz = R @ view.detector_origin_mm
    return {
        "GantryAngle": float(gantry % 360.0),
        "OutOfPlaneAngle": float(out_of_plane % 360.0),
        "InPlaneAngle": float(in_plane % 360.0),
        "SourceToIsocenterDistance": float(sid),
        "SourceOffsetX": float(sx),
        "SourceOffsetY": float(sy),
        "SourceToDetectorDistance": float(sid - dz),
        "ProjectionOffsetX": float(dx - origin_uv_mm[0]),
        "ProjectionOffsetY": float(dy - origin_uv_mm[1]),
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


def _mm_to_index(pitch_u_mm: float, pitch_v_mm: float, origin_uv_mm) -> np.ndarray:
    return np.array(
        [
            [1.0 / pitch_u_mm, 0.0, -origin_uv_mm[0] / pitch_u_mm],
            [0.0, 1.0 / pitch_v_mm, -origin_uv_mm[1] / pitch_v_mm],
            [0.0, 0.0, 1.0],
        ]
    )


def _format(x: float) -> str:
    return repr(float(x))


def write_rtk_geometry(
    path: str | Path, geometry: Geometry, origin_uv_mm: tuple[float, float] | None = None
) -> Path:
    """Write ``geometry`` as RTK XML (version 3), every parameter per projection.

    ``origin_uv_mm`` is the projection image's origin (mm) that the stack is written with;
    ``None`` means centred. All views must share the pixel pitch (one stack, one spacing).
    """
    path = Path(path)
    pu, pv = geometry[0].pitch_u_mm, geometry[0].pitch_v_mm
    for i, view in enumerate(geometry):
        if not (math.isclose(view.pitch_u_mm, pu) and math.isclose(view.pitch_v_mm, pv)):
            raise ValueError(
                f"view {i} has pitch ({view.pitch_u_mm}, {view.pitch_v_mm}) mm, view 0 has "
                f"({pu}, {pv}) mm: an RTK projection stack has one pixel spacing"
            )
    if origin_uv_mm is None:
        origin_uv_mm = centered_origin_uv_mm(geometry.rows, geometry.cols, pu, pv)
    to_index = _mm_to_index(pu, pv, origin_uv_mm)
    root = ET.Element("RTKThreeDCircularGeometry", version="3")
    for i, view in enumerate(geometry):
        try:
            params = rtk_parameters(view, origin_uv_mm)
        except ValueError as err:
            raise ValueError(f"view {i}: {err}") from None
        mat = rtk_matrix(params)
        ours = -to_index @ mat
        scale = np.linalg.norm(view.matrix) / np.linalg.norm(ours)
        if not np.allclose(
            ours * scale, view.matrix, rtol=0, atol=1e-9 * np.abs(view.matrix).max()
        ):
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
            raise ValueError(f"{path}: projection {i}: cylindrical detectors are not supported")
        if params["SourceToDetectorDistance"] == 0.0:
            raise ValueError(f"{path}: projection {i}: parallel-beam geometry is not supported")
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


def read_rtk_geometry(
    path: str | Path,
    detector: DetectorSpec,
    origin_uv_mm: tuple[float, float] | None = None,
) -> Geometry:
    """Read RTK XML as a :class:`Geometry` for a panel of ``detector`` pixels.

    ``origin_uv_mm`` is the origin of the projection stack the XML belongs to (read it from
    the stack's header, see recon.io.read_projections); ``None`` means centred.
    """
    _, matrices = read_rtk_matrices(path)
    p = detector.pixel_pitch_mm
    if origin_uv_mm is None:
        origin_uv_mm = centered_origin_uv_mm(detector.rows, detector.cols, p, p)
    to_index = _mm_to_index(p, p, origin_uv_mm)
    return Geometry.from_matrices(-(to_index @ matrices), detector)
