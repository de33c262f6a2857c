"""The volumes the motion estimate (registration.scan_motion) fits to and checks with: FDK
through a motion, sharpened by one iterative correction, what its reprojection misses, the box
of tissue it is made on and the pixels whose rays it explains."""

from __future__ import annotations

import numpy as np

from recon.fdk import estimate_orbit, fdk_reconstruct, plane_basis
from recon.geometry import Geometry
from recon.motion import BodyMotion
from recon.project import JosephProjector
from recon.volume import Volume, VolumeGrid
from registration.motion_fit import cropped
from registration.segment import _soft_tissue_level


def tissue_box(volume: Volume, margin_mm: float = 10.0) -> VolumeGrid:
    """The part of ``volume``'s grid holding tissue (above half the soft-tissue level) plus
    ``margin_mm``, on the same voxels: the estimate leaves the field's air out."""
    tissue = volume.data > 0.5 * _soft_tissue_level(volume.data)
    grid = volume.grid
    pad = np.ceil(margin_mm / np.asarray(grid.spacing_mm[::-1])).astype(int)
    index = np.argwhere(tissue)
    low = np.maximum(index.min(axis=0) - pad, 0)
    high = np.minimum(index.max(axis=0) + pad + 1, grid.shape)
    origin = np.asarray(grid.origin_mm) + low[::-1] * np.asarray(grid.spacing_mm)
    return VolumeGrid(tuple(int(n) for n in high - low), grid.spacing_mm, tuple(origin))


def trusted_pixels(
    geometry: Geometry, volume: Volume, mask: np.ndarray, margin_mm: float
) -> np.ndarray:
    """Per view, the pixels (bool (N, rows, cols)) whose rays the volume explains.

    Where a long leg leaves the reconstructed field (FDK's ``mask``) along the orbit's axis,
    the rays go on through tissue the volume does not hold, and FDK's data are incomplete
    near the field's ends. At each end whose last ``margin_mm`` hold tissue, the tissue is
    taken to go on beyond as the cylinder about the orbit's axis that holds that end's tissue;
    a ray is left out if its chord through that cylinder reaches past the end less
    ``margin_mm``.
    """
    axis = estimate_orbit(geometry).axis
    frame = np.stack((*plane_basis(axis), axis))
    x, y, z = np.meshgrid(*volume.grid.axes_mm(), indexing="ij")
    local = (np.stack((x, y, z), axis=-1) @ frame.T).transpose(2, 1, 0, 3)
    tissue = (volume.data > 0.5 * _soft_tissue_level(volume.data)) & mask
    heights = local[..., 2][mask]
    ends = []  # (height of the end, +1 above / -1 below, cylinder centre, radius)
    for end, beyond in ((heights.min() + margin_mm, -1.0), (heights.max() - margin_mm, 1.0)):
        slab = tissue & (beyond * (local[..., 2] - end) > 0)
        if not slab.any():
            continue  # the object ends inside the field here
        footprint = local[slab][:, :2]
        center = 0.5 * (footprint.min(axis=0) + footprint.max(axis=0))
        radius = float(np.linalg.norm(footprint - center, axis=1).max())
        ends.append((end, beyond, center, radius + max(volume.grid.spacing_mm)))
    out = np.ones((len(geometry), geometry.rows, geometry.cols), dtype=bool)
    if not ends:
        return out
    rows, cols = np.mgrid[0 : geometry.rows, 0 : geometry.cols]
    for i, view in enumerate(geometry):
        s = frame @ view.source_mm
        d = view.pixel_to_world(cols.ravel(), rows.ravel()) @ frame.T - s
        a = d[:, 0] ** 2 + d[:, 1] ** 2
        for end, beyond, center, radius in ends:
            sx, sy = s[0] - center[0], s[1] - center[1]
            b = 2 * (sx * d[:, 0] + sy * d[:, 1])
            disc = b**2 - 4 * a * (sx**2 + sy**2 - radius**2)
            root = np.sqrt(np.maximum(disc, 0.0))
            z1 = s[2] + (-b - root) / (2 * a) * d[:, 2]
            z2 = s[2] + (-b + root) / (2 * a) * d[:, 2]
            reach = np.maximum(z1, z2) if beyond > 0 else np.minimum(z1, z2)
            past = (disc > 0) & (beyond * (reach - end) > 0)
            out[i] &= ~past.reshape(geometry.rows, geometry.cols)
    return out


def missed_by(
    projections: np.ndarray,
    geometry: Geometry,
    grid: VolumeGrid,
    motion: BodyMotion | None,
    orbit_geometry: Geometry | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """FDK through ``motion`` (float32 on ``grid``, voxels FDK masks 0), FDK's mask, and what
    the volume's reprojection through the motion misses of the projections."""
    first = fdk_reconstruct(
        projections, geometry, grid, orbit_geometry=orbit_geometry, motion=motion
    )
    volume = first.volume.data * first.mask
    weights = np.ones((1, *grid.shape), np.float32) if motion is None else motion.on(grid)
    poses = np.tile(np.eye(4), (len(geometry), 1, 1, 1)) if motion is None else motion.poses
    parts = [JosephProjector(*cropped(volume * w, grid)) for w in weights]
    missed = np.array(projections, dtype=np.float32, copy=True)
    for i, view in enumerate(geometry):
        for part, T in zip(parts, poses[i], strict=True):
            missed[i] -= part.project_moved(view, T)
    return volume, first.mask, missed


def sharpened(
    projections: np.ndarray,
    geometry: Geometry,
    grid: VolumeGrid,
    motion: BodyMotion | None,
    orbit_geometry: Geometry | None,
) -> tuple[np.ndarray, np.ndarray]:
    """FDK through ``motion`` plus the FDK of what its reprojection misses (one iterative
    correction), float32 on ``grid`` (voxels FDK masks are 0), and FDK's mask."""
    volume, mask, missed = missed_by(projections, geometry, grid, motion, orbit_geometry)
    correction = fdk_reconstruct(
        missed, geometry, grid, orbit_geometry=orbit_geometry, motion=motion
    )
    return (volume + correction.volume.data * mask).astype(np.float32), mask
