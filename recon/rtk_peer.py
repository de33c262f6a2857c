"""Run the peer toolkit RTK (itk-rtk, the ``dev`` extra) on our volumes and geometries.

Interoperability tests and benchmarks call RTK through these functions so that both toolkits
see identical inputs: our geometry becomes RTK's nine parameters per view (recon.rtk_xml),
volumes and projection stacks keep their world placement. RTK's outputs hold weak references
to their inputs, so every ITK object stays referenced until the result is copied out.

RTK's FDK and Parker weighting read view angles as gantry angles about RTK's y axis, while our
orbits turn about world z, and its FDK weighting treats source offsets from the isocentre as
detector offsets. :func:`rtk_fdk` therefore hands RTK the scan in a frame centred on the
isocentre and rotated so that the orbit axis is RTK's y (a signed permutation of the world axes,
so volumes map exactly by transposing and flipping arrays) and maps the result back.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from recon.geometry import Geometry
from recon.rtk_xml import PanelHeader, rtk_parameters
from recon.volume import Volume, VolumeGrid

_PARAMETER_ORDER = (
    "SourceToIsocenterDistance",
    "SourceToDetectorDistance",
    "GantryAngle",
    "ProjectionOffsetX",
    "ProjectionOffsetY",
    "OutOfPlaneAngle",
    "InPlaneAngle",
    "SourceOffsetX",
    "SourceOffsetY",
)


def _itk() -> tuple[Any, Any]:
    try:
        import itk
        from itk import RTK
    except ImportError as err:  # pragma: no cover - the dev extra installs it
        raise ImportError("the RTK peer needs itk-rtk: pip install 'dualarm-cbct[dev]'") from err
    return itk, RTK


def _header(geometry: Geometry) -> PanelHeader:
    """The centred panel every stack handed to RTK here is written on."""
    view0 = geometry[0]
    return PanelHeader.centered(geometry.rows, geometry.cols, view0.pitch_u_mm, view0.pitch_v_mm)


def rtk_geometry(geometry: Geometry) -> Any:
    """An ``rtk.ThreeDCircularProjectionGeometry`` with our views (centred stack origin)."""
    _, rtk = _itk()
    header = _header(geometry)
    out = rtk.ThreeDCircularProjectionGeometry.New()
    for view in geometry:
        params = rtk_parameters(view, header)
        out.AddProjection(*[float(params[name]) for name in _PARAMETER_ORDER])
    return out


def _axis_to_y(axis: np.ndarray) -> np.ndarray:
    """Signed permutation matrix taking a world-axis-aligned orbit ``axis`` to +y."""
    k = int(np.argmax(np.abs(axis)))
    if abs(abs(axis[k]) - 1.0) > 1e-3:
        raise ValueError(f"RTK's FDK needs an orbit about a world axis, got axis {axis.tolist()}")
    s = float(np.sign(axis[k]))
    if k == 1:
        return np.diag([1.0, s, s])
    if k == 2:  # x' = x, y' = s z, z' = -s y
        return np.array([[1.0, 0, 0], [0, 0, s], [0, -s, 0]])
    return np.array([[0, 0, -s], [s, 0, 0], [0, -1.0, 0]])  # x' = -s z, y' = s x, z' = -y


def _move_geometry(geometry: Geometry, T: np.ndarray, center: np.ndarray) -> Geometry:
    """The views seen in the frame ``x' = T (x - center)``."""
    motion = np.eye(4)
    motion[:3, :3] = T
    motion[:3, 3] = -T @ center
    return geometry.transformed(motion)


def _move_volume(array: np.ndarray, grid: VolumeGrid, T: np.ndarray, center: np.ndarray):
    """Array and grid of a volume seen in the frame ``x' = T (x - center)``, T a signed
    permutation, so voxels map one to one."""
    order, flips, spacing, origin = [], [], [], []
    n_xyz = grid.size_xyz
    for i in range(3):  # new world axis i
        j = int(np.argmax(np.abs(T[i])))
        sign = T[i, j]
        order.append(j)
        spacing.append(grid.spacing_mm[j])
        first = grid.origin_mm[j] - center[j]
        last = first + (n_xyz[j] - 1) * grid.spacing_mm[j]
        origin.append(first if sign > 0 else -last)
        flips.append(sign < 0)
    # array axes are world axes reversed: new array axis a <-> new world axis 2 - a
    moved = np.transpose(array, [2 - order[2 - a] for a in range(3)])
    for a in range(3):
        if flips[2 - a]:
            moved = np.flip(moved, axis=a)
    new_grid = VolumeGrid(shape=moved.shape, spacing_mm=tuple(spacing), origin_mm=tuple(origin))
    return np.ascontiguousarray(moved), new_grid


def _volume_image(array: np.ndarray, grid: VolumeGrid) -> Any:
    itk, _ = _itk()
    image = itk.image_from_array(np.ascontiguousarray(array, dtype=np.float32))
    image.SetSpacing(grid.spacing_mm)
    image.SetOrigin(grid.origin_mm)
    return image


def _stack_image(array: np.ndarray, geometry: Geometry) -> Any:
    itk, _ = _itk()
    header = _header(geometry)
    image = itk.image_from_array(np.ascontiguousarray(array, dtype=np.float32))
    image.SetSpacing((*header.spacing_mm, 1.0))
    image.SetOrigin((*header.origin_mm, 0.0))
    return image


def rtk_forward_project(volume: np.ndarray, grid: VolumeGrid, geometry: Geometry) -> np.ndarray:
    """RTK's Joseph forward projection, float32 (views, rows, cols)."""
    itk, rtk = _itk()
    image_type = itk.Image[itk.F, 3]
    vol = _volume_image(volume, grid)
    empty = _stack_image(np.zeros((len(geometry), geometry.rows, geometry.cols)), geometry)
    geo = rtk_geometry(geometry)
    projector = rtk.JosephForwardProjectionImageFilter[image_type, image_type].New()
    projector.SetInput(0, empty)
    projector.SetInput(1, vol)
    projector.SetGeometry(geo)
    projector.Update()
    return itk.array_from_image(projector.GetOutput()).copy()


def rtk_fdk(
    projections: np.ndarray,
    geometry: Geometry,
    grid: VolumeGrid,
    hann_cut: float = 0.0,
    parker: bool = False,
) -> np.ndarray:
    """RTK's CPU FDK (optionally after its Parker short-scan weighting), float32 [z, y, x].

    ``hann_cut`` is RTK's Hann window cut frequency (0 = plain ramp); RTK's ramp has no
    truncation correction here, like ours. The scan is handed to RTK about its y axis through its
    origin (see the module docstring).
    """
    from recon.fdk import estimate_orbit

    itk, rtk = _itk()
    image_type = itk.Image[itk.F, 3]
    orbit = estimate_orbit(geometry)
    T, center = _axis_to_y(orbit.axis), orbit.isocenter_mm
    turned = _move_geometry(geometry, T, center)
    stack = _stack_image(projections, turned)
    geo = rtk_geometry(turned)
    source = stack
    parker_filter = None
    if parker:
        parker_filter = rtk.ParkerShortScanImageFilter[image_type].New()
        parker_filter.SetInput(stack)
        parker_filter.SetGeometry(geo)
        parker_filter.Update()
        source = parker_filter.GetOutput()
    _, turned_grid = _move_volume(np.zeros(grid.shape, dtype=np.float32), grid, T, center)
    empty = _volume_image(np.zeros(turned_grid.shape, dtype=np.float32), turned_grid)
    fdk = rtk.FDKConeBeamReconstructionFilter[image_type].New()
    fdk.SetInput(0, empty)
    fdk.SetInput(1, source)
    fdk.SetGeometry(geo)
    fdk.GetRampFilter().SetTruncationCorrection(0.0)
    fdk.GetRampFilter().SetHannCutFrequency(hann_cut)
    fdk.Update()
    result = itk.array_from_image(fdk.GetOutput())
    back, _ = _move_volume(result, turned_grid, T.T, -T @ center)
    return back.copy()


def rtk_shepp_logan(
    geometry: Geometry, grid: VolumeGrid, scale_mm: float, center_mm=(0.0, 0.0, 0.0)
) -> tuple[np.ndarray, np.ndarray]:
    """RTK's 3-D Shepp-Logan phantom: analytic ray-ellipsoid projections through
    ``geometry`` (float32 (views, rows, cols)) and the phantom drawn on ``grid`` ([z, y, x]).

    ``scale_mm`` scales RTK's unit phantom; ``center_mm`` moves it.
    """
    itk, rtk = _itk()
    image_type = itk.Image[itk.F, 3]
    geo = rtk_geometry(geometry)
    empty = _stack_image(np.zeros((len(geometry), geometry.rows, geometry.cols)), geometry)
    projector = rtk.SheppLoganPhantomFilter[image_type, image_type].New()
    projector.SetInput(empty)
    projector.SetGeometry(geo)
    projector.SetPhantomScale(float(scale_mm))
    projector.SetOriginOffset([float(c) for c in center_mm])
    projector.Update()
    projections = itk.array_from_image(projector.GetOutput()).copy()
    blank = _volume_image(np.zeros(grid.shape, dtype=np.float32), grid)
    draw = rtk.DrawSheppLoganFilter[image_type, image_type].New()
    draw.SetInput(blank)
    draw.SetPhantomScale(float(scale_mm))
    draw.SetOriginOffset([float(c) for c in center_mm])
    draw.Update()
    return projections, itk.array_from_image(draw.GetOutput()).copy()


def _run(filter_: Any, projections: np.ndarray, geometry: Geometry, start: Volume) -> np.ndarray:
    """Run an RTK iterative filter on its two inputs (the start volume, the projections)."""
    itk, _ = _itk()
    volume, stack = _volume_image(start.data, start.grid), _stack_image(projections, geometry)
    filter_.SetInput(0, volume)
    filter_.SetInput(1, stack)
    filter_.SetGeometry(rtk_geometry(geometry))
    filter_.Update()
    return itk.array_from_image(filter_.GetOutput()).copy()


def rtk_sart(
    projections: np.ndarray,
    geometry: Geometry,
    start: Volume,
    iterations: int,
    views_per_subset: int = 1,
    relaxation: float = 0.8,
) -> np.ndarray:
    """RTK's OS-SART (Joseph forward, voxel-based back projection, positivity enforced) from
    ``start`` with ``views_per_subset`` projections per subset, float32 [z, y, x] on its grid."""
    itk, rtk = _itk()
    image_type = itk.Image[itk.F, 3]
    sart = rtk.SARTConeBeamReconstructionFilter[image_type, image_type].New()
    sart.SetNumberOfIterations(int(iterations))
    sart.SetNumberOfProjectionsPerSubset(int(views_per_subset))
    sart.SetLambda(float(relaxation))
    sart.SetEnforcePositivity(True)
    return _run(sart, projections, geometry, start)


def rtk_cg(
    projections: np.ndarray, geometry: Geometry, start: Volume, iterations: int
) -> np.ndarray:
    """RTK's conjugate gradient on the least-squares problem (unit weights) from ``start``."""
    itk, rtk = _itk()
    image_type = itk.Image[itk.F, 3]
    cg = rtk.ConjugateGradientConeBeamReconstructionFilter[image_type].New()
    weights = _stack_image(np.ones_like(projections), geometry)
    cg.SetInput(2, weights)
    cg.SetNumberOfIterations(int(iterations))
    return _run(cg, projections, geometry, start)


def rtk_admm_tv(
    projections: np.ndarray,
    geometry: Geometry,
    start: Volume,
    iterations: int,
    alpha: float,
    beta: float,
    cg_iterations: int,
) -> np.ndarray:
    """RTK's ADMM with total variation: ``iterations`` augmented-Lagrangian steps of
    ``cg_iterations`` conjugate-gradient steps each, TV weight ``alpha``, penalty ``beta``."""
    itk, rtk = _itk()
    image_type = itk.Image[itk.F, 3]
    admm = rtk.ADMMTotalVariationConeBeamReconstructionFilter[image_type].New()
    admm.SetAlpha(float(alpha))
    admm.SetBeta(float(beta))
    admm.SetAL_iterations(int(iterations))
    admm.SetCG_iterations(int(cg_iterations))
    return _run(admm, projections, geometry, start)
