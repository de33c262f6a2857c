"""Additive ellipsoid phantoms: exact rasterisation, exact line integrals, Shepp–Logan 3D.

An :class:`Ellipsoid` adds ``value`` (1/mm) to every point inside it; overlapping ellipsoids
sum, as in the Shepp–Logan phantom. Line integrals are closed-form chord lengths, so
projections of these phantoms are exact references for the projectors and for FDK.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from recon.geometry import Geometry
from recon.volume import VolumeGrid

_TARGET_POINTS_PER_SLAB = 1 << 20


@dataclass(frozen=True, eq=False)
class Ellipsoid:
    """A solid ellipsoid of constant additive attenuation.

    Attributes:
        center_mm: centre, world mm (3,).
        semi_axes_mm: semi-axis lengths along the ellipsoid's own axes, mm (3,), all > 0.
        rotation: orientation, a 3x3 matrix or a ``scipy.spatial.transform.Rotation``; its
            columns are the ellipsoid's axes in the world (stored as a read-only 3x3 matrix).
        value: attenuation added inside, 1/mm (may be negative).
    """

    center_mm: np.ndarray
    semi_axes_mm: np.ndarray
    rotation: np.ndarray | Rotation = field(default_factory=Rotation.identity)
    value: float = 1.0

    def __post_init__(self) -> None:
        center = np.array(self.center_mm, dtype=np.float64).reshape(-1)
        axes = np.array(self.semi_axes_mm, dtype=np.float64).reshape(-1)
        if center.shape != (3,) or not np.all(np.isfinite(center)):
            raise ValueError(f"center_mm must be 3 finite numbers, got {self.center_mm!r}")
        if axes.shape != (3,) or not np.all(np.isfinite(axes)) or np.any(axes <= 0):
            raise ValueError(f"semi_axes_mm must be 3 finite numbers > 0, got {self.semi_axes_mm}")
        rot = self.rotation
        if not isinstance(rot, Rotation):
            m = np.asarray(rot, dtype=np.float64)
            if m.shape != (3, 3) or not np.allclose(m.T @ m, np.eye(3), atol=1e-6):
                raise ValueError("rotation must be an orthonormal 3x3 matrix or a Rotation")
            if np.linalg.det(m) < 0:
                raise ValueError("rotation must be proper (determinant +1), not a reflection")
            rot = Rotation.from_matrix(m)
        matrix = rot.as_matrix()
        if not np.isfinite(float(self.value)):
            raise ValueError(f"value must be finite, got {self.value!r}")
        for name, arr in (("center_mm", center), ("semi_axes_mm", axes), ("rotation", matrix)):
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)
        object.__setattr__(self, "value", float(self.value))

    @property
    def volume_mm3(self) -> float:
        """4/3 pi a b c, mm^3."""
        return float(4.0 / 3.0 * np.pi * np.prod(self.semi_axes_mm))

    @property
    def half_extent_mm(self) -> np.ndarray:
        """Half sizes of the world axis-aligned bounding box, mm (3,)."""
        return np.sqrt(np.sum((self.rotation * self.semi_axes_mm) ** 2, axis=1))

    def normalized(self, points_mm: np.ndarray) -> np.ndarray:
        """Points in the frame where the ellipsoid is the unit ball.

        Args:
            points_mm: World points (mm), shape (N, 3).

        Returns:
            The points scaled to the unit ball's frame (unitless), shape (N, 3).
        """
        return ((np.asarray(points_mm, dtype=np.float64) - self.center_mm) @ self.rotation) / (
            self.semi_axes_mm
        )


def rasterize_ellipsoids(
    ellipsoids: Iterable[Ellipsoid], grid: VolumeGrid, supersample: int = 1
) -> np.ndarray:
    """Sum of the ellipsoids' values on a grid, with partial volume.

    Each voxel gets the mean over ``supersample**3`` sub-voxel samples (a regular sub-grid),
    so a voxel cut by a surface holds the sampled fraction of the value. Voxels that are
    provably entirely inside or outside an ellipsoid (the voxel's bounding ball, scaled by the
    smallest semi-axis, clears the unit sphere) are set without sub-sampling.

    Args:
        ellipsoids: the phantom.
        grid: voxel grid, world mm.
        supersample: sub-samples per voxel edge, >= 1.

    Returns:
        float32 array [z, y, x] of shape ``grid.shape``, 1/mm.
    """
    n = int(supersample)
    if n < 1 or n != supersample:
        raise ValueError(f"supersample must be a positive integer, got {supersample!r}")
    f = (np.arange(n) + 0.5) / n - 0.5
    sub = np.stack(np.meshgrid(f, f, f, indexing="ij"), axis=-1).reshape(-1, 3)
    offsets = sub * np.asarray(grid.spacing_mm)
    half_diag = 0.5 * float(np.linalg.norm(grid.spacing_mm))
    ax, ay, az = grid.axes_mm()
    out = np.zeros(grid.shape, dtype=np.float64)
    for e in ellipsoids:
        lo = grid.world_to_index(e.center_mm - e.half_extent_mm - half_diag)
        hi = grid.world_to_index(e.center_mm + e.half_extent_mm + half_diag)
        i0 = np.maximum(np.floor(lo).astype(int), 0)
        i1 = np.minimum(np.ceil(hi).astype(int) + 1, grid.size_xyz)
        if np.any(i1 <= i0):
            continue
        xs, ys, zs = ax[i0[0] : i1[0]], ay[i0[1] : i1[1]], az[i0[2] : i1[2]]
        margin = half_diag / float(e.semi_axes_mm.min())
        yy, xx = np.meshgrid(ys, xs, indexing="ij")
        plane = np.stack((xx.ravel(), yy.ravel()), axis=-1)
        slab = max(1, _TARGET_POINTS_PER_SLAB // plane.shape[0])
        for z0 in range(0, zs.size, slab):
            zc = zs[z0 : z0 + slab]
            pts = np.empty((zc.size * plane.shape[0], 3))
            pts[:, :2] = np.tile(plane, (zc.size, 1))
            pts[:, 2] = np.repeat(zc, plane.shape[0])
            r = np.linalg.norm(e.normalized(pts), axis=1)
            frac = (r <= 1.0).astype(np.float64)
            edge = np.abs(r - 1.0) < margin
            if n > 1 and np.any(edge):
                sp = (pts[edge][:, None, :] + offsets[None, :, :]).reshape(-1, 3)
                inside = np.sum(e.normalized(sp) ** 2, axis=1) <= 1.0
                frac[edge] = inside.reshape(-1, offsets.shape[0]).mean(axis=1)
            block = out[i0[2] + z0 : i0[2] + z0 + zc.size, i0[1] : i1[1], i0[0] : i1[0]]
            block += e.value * frac.reshape(block.shape)
    return out.astype(np.float32)


def ellipsoid_line_integrals(
    ellipsoids: Iterable[Ellipsoid], starts_mm: np.ndarray, ends_mm: np.ndarray
) -> np.ndarray:
    """Exact line integrals of the phantom along straight segments.

    For each segment start -> end the chord of every ellipsoid (the part of the line inside
    it, clipped to the segment) is found in closed form from the quadratic
    ``|q0 + t dq|^2 = 1`` in the ellipsoid's unit-ball frame, and its world length times the
    ellipsoid's value is summed.

    Args:
        ellipsoids: the phantom.
        starts_mm: segment starts (e.g. the source), world mm (N, 3) or (3,).
        ends_mm: segment ends (e.g. detector pixel centres), world mm (N, 3).

    Returns:
        float64 (N,): line integrals, value x mm (dimensionless for values in 1/mm).
    """
    ends = np.atleast_2d(np.asarray(ends_mm, dtype=np.float64))
    starts = np.broadcast_to(np.asarray(starts_mm, dtype=np.float64), ends.shape)
    if ends.shape[-1] != 3 or ends.ndim != 2:
        raise ValueError(f"ends_mm must have shape (N, 3), got {np.shape(ends_mm)}")
    seg = ends - starts
    seg_len = np.linalg.norm(seg, axis=1)
    total = np.zeros(ends.shape[0])
    for e in ellipsoids:
        q0 = e.normalized(starts)
        dq = (seg @ e.rotation) / e.semi_axes_mm
        a = np.einsum("ij,ij->i", dq, dq)
        b = np.einsum("ij,ij->i", q0, dq)
        c = np.einsum("ij,ij->i", q0, q0) - 1.0
        disc = b * b - a * c
        hit = (disc > 0.0) & (a > 0.0)
        # numerically stable roots of a t^2 + 2 b t + c = 0
        q = -(b + np.copysign(np.sqrt(np.where(hit, disc, 0.0)), b))
        with np.errstate(divide="ignore", invalid="ignore"):
            r1 = np.where(hit, q / np.where(hit, a, 1.0), 0.0)
            r2 = np.where(hit & (q != 0.0), c / np.where(q != 0.0, q, 1.0), r1)
        t_in = np.clip(np.minimum(r1, r2), 0.0, 1.0)
        t_out = np.clip(np.maximum(r1, r2), 0.0, 1.0)
        total += e.value * np.where(hit, t_out - t_in, 0.0) * seg_len
    return total


def project_ellipsoids(ellipsoids: Iterable[Ellipsoid], geometry: Geometry) -> np.ndarray:
    """Exact cone-beam projections: line integrals from the source to every pixel centre.

    Args:
        ellipsoids: the phantom.
        geometry: the views; pixel (row v, col u) is ``view.pixel_to_world(u, v)``.

    Returns:
        float32 (views, rows, cols): line integrals (-ln(I/I0) for values in 1/mm).
    """
    phantom = list(ellipsoids)
    out = np.empty((len(geometry), geometry.rows, geometry.cols), dtype=np.float32)
    vv, uu = np.meshgrid(np.arange(geometry.rows), np.arange(geometry.cols), indexing="ij")
    for k, view in enumerate(geometry):
        ends = view.pixel_to_world(uu, vv).reshape(-1, 3)
        out[k] = ellipsoid_line_integrals(phantom, view.source_mm, ends).reshape(vv.shape)
    return out


# Kak & Slaney, Principles of Computerized Tomographic Imaging (1988), p. 102 (3D head):
# semi-axes (a, b, c), centre (x0, y0, z0) in units of the phantom scale, rotation phi (deg)
# about the z (head-foot) axis, and the additive density of the original table.
_SHEPP_LOGAN_3D = np.array(
    [
        # a      b      c      x0      y0      z0     phi   density
        [0.6900, 0.920, 0.900, 0.000, 0.000, 0.000, 0.0, 2.00],
        [0.6624, 0.874, 0.880, 0.000, 0.000, 0.000, 0.0, -0.98],
        [0.4100, 0.160, 0.210, -0.220, 0.000, -0.250, 108.0, -0.02],
        [0.3100, 0.110, 0.220, 0.220, 0.000, -0.250, 72.0, -0.02],
        [0.2100, 0.250, 0.500, 0.000, 0.350, -0.250, 0.0, 0.02],
        [0.0460, 0.046, 0.046, 0.000, 0.100, -0.250, 0.0, 0.02],
        [0.0460, 0.023, 0.020, -0.080, -0.650, -0.250, 0.0, 0.01],
        [0.0460, 0.023, 0.020, 0.060, -0.650, -0.250, 90.0, 0.01],
        [0.0560, 0.040, 0.100, 0.060, -0.105, 0.625, 90.0, 0.02],
        [0.0560, 0.056, 0.100, 0.000, 0.100, 0.625, 0.0, -0.02],
    ]
)
# Yu, Ye & Wang, "Katsevich-type algorithms for variable radius spiral cone-beam CT",
# Proc. SPIE 5535 (2004): the same ellipsoids with higher-contrast densities.
_MODIFIED_DENSITIES = np.array([1.0, -0.8, -0.2, -0.2, 0.2, 0.2, 0.1, 0.1, 0.2, -0.2])


def shepp_logan_3d(
    scale_mm: float,
    center_mm: Sequence[float] = (0.0, 0.0, 0.0),
    modified: bool = True,
    value_per_unit: float = 1.0,
) -> list[Ellipsoid]:
    """The 10-ellipsoid 3D Shepp–Logan head phantom.

    Geometry from Kak & Slaney, *Principles of Computerized Tomographic Imaging* (1988),
    p. 102 (semi-axes and centres in units of ``scale_mm``; rotations about the head-foot
    axis). Densities: with ``modified`` the higher-contrast values of Yu, Ye & Wang (SPIE 5535,
    2004): 1.0, -0.8, -0.2, -0.2, 0.2, 0.2, 0.1, 0.1, 0.2, -0.2 (skull 1.0, brain
    1.0 - 0.8 = 0.2); otherwise the original 2.0, -0.98, -0.02, -0.02, 0.02, 0.02, 0.01, 0.01,
    0.02, -0.02 (brain 1.02), which is also the table of RTK's ``rtk::SheppLoganPhantom``
    (RTK lists the same ellipsoids with its y and z axes swapped, y being its head-foot axis).

    Axis mapping: the table's x, y and z are world x, y and z, so the head-foot axis is world
    z (up) and the table's phi is a counter-clockwise rotation about world z.

    Args:
        scale_mm: phantom half-size: the outer ellipsoid has semi-axes
            (0.69, 0.92, 0.90) * scale_mm.
        center_mm: world position of the phantom centre, mm.
        modified: Yu–Ye–Wang densities (True) or the original Kak–Slaney ones (False).
        value_per_unit: attenuation (1/mm) per unit of the table's density; 1.0 keeps the
            table's numbers as 1/mm.

    Returns:
        The 10 ellipsoids, additive.
    """
    if not (np.isfinite(scale_mm) and scale_mm > 0):
        raise ValueError(f"scale_mm must be > 0, got {scale_mm!r}")
    center = np.asarray(center_mm, dtype=np.float64).reshape(3)
    densities = _MODIFIED_DENSITIES if modified else _SHEPP_LOGAN_3D[:, 7]
    return [
        Ellipsoid(
            center_mm=center + scale_mm * row[3:6],
            semi_axes_mm=scale_mm * row[0:3],
            rotation=Rotation.from_euler("z", row[6], degrees=True),
            value=float(density) * value_per_unit,
        )
        for row, density in zip(_SHEPP_LOGAN_3D, densities, strict=True)
    ]
