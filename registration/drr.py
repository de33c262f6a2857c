"""Digitally reconstructed radiographs of bones and of the whole knee scene.

A bone is its CBCT attenuation minus the soft tissue's, in a sub-volume cropped around it
(:class:`BoneModel`); the soft tissue is the CBCT volume with every bone voxel filled with the
soft tissue's attenuation (the bones displace it, no hole is left), bent at the knee by the
femur's and the tibia's poses (:class:`SoftTissue`). A frame's scene is the soft
tissue plus every bone at its pose; moving a bone by ``T`` is rendering the unmoved bone
through the view moved by ``T^-1`` (recon.geometry.View.transformed), with the recon
projector (Joseph). Views are binned for the coarse levels of a resolution pyramid, and
volumes are averaged over 2 x 2 x 2 voxels for the views whose pixels (at the volume) are at
least twice the voxel size (:class:`RigidVolume`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numba
import numpy as np
from scipy.ndimage import binary_erosion, distance_transform_edt

from recon.geometry import Geometry, View
from recon.project import JosephProjector
from recon.volume import Volume, VolumeGrid
from registration.labels import BONE_UNITS, LABELS

SOFT_TISSUE_LABEL = LABELS["soft_tissue"]
CROP_MARGIN_MM = 3.0
BONE_EDGE_MM = 1.5
"""Soft-tissue rim moved with each bone (the blurred outside of its edge), mm."""
SOFT_TISSUE_BLEND_MM = 40.0
"""Width of the smooth hand-over of the soft tissue from the tibia to the femur, mm."""
SOFT_TISSUE_VOXEL_MM = 2.0
"""The soft tissue's lattice: the scan's voxels pooled to about this size, mm (its detail is
the skin and fat outline, which the high-pass similarity sees at a few mm)."""
CUT_LEVELS = (0.5, 1.5)
"""Where the scan's box cuts the leg: on each face of the box, the outlines of what exceeds
these fractions of the soft tissue's attenuation (the skin; the bones' cortex)."""


def _pooled(
    data: np.ndarray, grid: VolumeGrid, factor_xyz: tuple[int, int, int] = (2, 2, 2)
) -> tuple[np.ndarray, VolumeGrid]:
    """Mean over blocks of ``factor_xyz`` voxels (x, y, z); trailing partial blocks are dropped.
    Float32; summed axis by axis over strided slices (a reshape's strided mean over x took
    ten times longer)."""
    factor = np.asarray(factor_xyz, dtype=int)
    out = np.asarray(data, dtype=np.float32)
    for axis, f in enumerate(factor[::-1]):  # array axes z, y, x
        if f > 1:
            n = out.shape[axis] // f
            parts = [out[(slice(None),) * axis + (slice(k, n * f, f),)] for k in range(f)]
            out = sum(parts[1:], parts[0]) / np.float32(f)
    return out, _pooled_grid(grid, factor_xyz)


def _pooled_grid(grid: VolumeGrid, factor_xyz: tuple[int, int, int]) -> VolumeGrid:
    """The lattice of :func:`_pooled`'s blocks of ``factor_xyz`` voxels (x, y, z) of ``grid``."""
    factor = np.asarray(factor_xyz, dtype=int)
    shape = tuple(int(n) for n in np.asarray(grid.shape) // factor[::-1])
    spacing = np.asarray(grid.spacing_mm)
    origin = np.asarray(grid.origin_mm) + 0.5 * (factor - 1) * spacing
    return VolumeGrid(shape, tuple(factor * spacing), tuple(origin))


def along_axis(data: np.ndarray, grid: VolumeGrid, axis: int) -> JosephProjector:
    """A projector of ``data`` averaged over pairs of slices along ``axis`` (0, 1, 2: x, y,
    z): half the cost for rays near that axis, at full resolution across them."""
    return JosephProjector(*_pooled(data, grid, tuple(np.eye(3, dtype=int)[axis] + 1)))


@dataclass(frozen=True)
class RigidVolume:
    """Attenuation (1/mm) that moves rigidly, ready to render at two resolutions.

    The fine level samples the volume every other slice along the ray's main axis, each
    sample the mean of two slices (``along``): Joseph's integral keeps its full resolution
    across the ray at half the cost (for rays within ~10 degrees of that axis the samples
    move by under 0.1 voxel). The coarse level averages 2 x 2 x 2 voxels.
    """

    along: tuple[JosephProjector, JosephProjector, JosephProjector]
    coarse: JosephProjector

    @classmethod
    def of(cls, data: np.ndarray, grid: VolumeGrid) -> RigidVolume:
        """Prepare ``data`` on ``grid``."""
        data = np.asarray(data, dtype=np.float32)
        coarse = JosephProjector(*_pooled(data, grid))
        return cls(tuple(along_axis(data, grid, k) for k in range(3)), coarse)

    def voxel_mm(self) -> float:
        """The fine level's voxel size across the rays, mm."""
        return float(sorted(self.along[0].grid.spacing_mm)[0])

    def render(
        self,
        view: View,
        T_world: np.ndarray,
        coarse: bool = False,
        spans: np.ndarray | None = None,
    ) -> np.ndarray:
        """Line integrals of the volume moved by ``T_world``, float32 (rows, cols); only over
        each row's column span (recon.project.JosephProjector.project_moved) if given."""
        return self.render_many(view, T_world[None], coarse, spans)[0]

    def render_many(
        self,
        view: View,
        Ts_world: np.ndarray,
        coarse: bool = False,
        spans: np.ndarray | None = None,
    ) -> np.ndarray:
        """:meth:`render` at each of the poses ``Ts_world`` (n, 4, 4), float32 (n, rows,
        cols): the poses whose rays run along the same axis of the volume in one call of the
        projector (recon.project.JosephProjector.project_moved_many)."""
        if coarse:
            return self.coarse.project_moved_many(view, Ts_world, spans)
        ray = (view.detector_center_mm - view.source_mm) @ Ts_world[:, :3, :3]  # in the volume
        axes = np.argmax(np.abs(ray), axis=1)
        out = np.empty((len(Ts_world), view.rows, view.cols), dtype=np.float32)
        for axis in np.unique(axes):
            along = axes == axis
            out[along] = self.along[axis].project_moved_many(view, Ts_world[along], spans)
        return out


@dataclass(frozen=True)
class BoneModel:
    """One rigid bone for rendering and error measurement.

    Attributes:
        name: "femur", "tibia_fibula" or "patella".
        volume: the bone's excess attenuation (1/mm over soft tissue) on its cropped grid.
        points_mm: centres of the bone's voxels at the reference pose (N, 3).
        centroid_mm: their mean (rotations of the 6-DoF parameterisation are about it).
    """

    name: str
    volume: RigidVolume
    points_mm: np.ndarray
    centroid_mm: np.ndarray

    def voxel_mm(self) -> float:
        """The model's voxel across the rays, mm (:meth:`RigidVolume.voxel_mm`)."""
        return self.volume.voxel_mm()

    def render(
        self,
        view: View,
        T_world_body: np.ndarray,
        coarse: bool = False,
        spans: np.ndarray | None = None,
    ) -> np.ndarray:
        """Line integrals of the bone moved by ``T_world_body`` (see :meth:`RigidVolume.render`).

        Args:
            view: The view rendered.
            T_world_body: Pose of the bone, 4x4, translation in mm.
            coarse: Render the pooled (coarser) volume, for the registration's first level.
            spans: Columns traced per row, int (rows, 2); ``None`` traces all.

        Returns:
            Line integrals (unitless: 1/mm times mm), float32 (rows, cols).
        """
        return self.volume.render(view, T_world_body, coarse, spans)

    def render_many(
        self,
        view: View,
        Ts_world_body: np.ndarray,
        coarse: bool = False,
        spans: np.ndarray | None = None,
    ) -> np.ndarray:
        """:meth:`render` at each of several poses, in as few calls of the projector as the
        rays' axes allow.

        Args:
            view: The view rendered.
            Ts_world_body: Poses of the bone, (n, 4, 4), translations in mm.
            coarse: Render the pooled (coarser) volume.
            spans: Columns traced per row, int (rows, 2); ``None`` traces all.

        Returns:
            Line integrals, float32 (n, rows, cols).
        """
        return self.volume.render_many(view, Ts_world_body, coarse, spans)


def _crop(
    mask: np.ndarray, grid: VolumeGrid, margin_mm: float
) -> tuple[tuple[slice, ...], VolumeGrid]:
    where = np.nonzero(mask)
    pad = [int(np.ceil(margin_mm / s)) for s in grid.spacing_mm[::-1]]
    lo = [max(0, int(w.min()) - p) for w, p in zip(where, pad, strict=True)]
    hi = [min(n, int(w.max()) + p + 1) for w, n, p in zip(where, grid.shape, pad, strict=True)]
    box = tuple(slice(a, b) for a, b in zip(lo, hi, strict=True))
    origin = grid.index_to_world(np.array(lo[::-1], dtype=np.float64))
    sub = VolumeGrid(
        tuple(b - a for a, b in zip(lo, hi, strict=True)), grid.spacing_mm, tuple(origin)
    )
    return box, sub


def cut_outlines(volume: Volume, soft_level: float) -> tuple[np.ndarray, np.ndarray]:
    """Where the box of ``volume`` cuts the leg: the voxels of each face layer on the outline
    of what exceeds :data:`CUT_LEVELS` times ``soft_level`` there (including where it meets
    the face's rim), world mm (N, 3), and their face's outward normal (N, 3). A DRR of the
    scan ends at the box while the leg goes on: seen edge-on, a face's cut section projects
    within its outline, a step in the line integrals; seen face-on, what lies beyond thins
    out to nothing at the outline (no step)."""
    data = volume.data
    shape = data.shape  # (z, y, x)
    points, normals = [], []
    for axis in range(3):
        for end, sign in ((0, -1.0), (shape[axis] - 1, 1.0)):
            face = np.take(data, end, axis=axis)
            for level in CUT_LEVELS:
                inside = face > level * soft_level
                outline = inside & ~binary_erosion(inside, border_value=0)
                index = list(np.nonzero(outline))
                index.insert(axis, np.full(len(index[0]), end))
                points.append(np.column_stack(index[::-1]).astype(np.float64))  # x, y, z
                normal = np.zeros(3)
                normal[2 - axis] = sign
                normals.append(np.tile(normal, (len(points[-1]), 1)))
    return volume.grid.index_to_world(np.vstack(points)), np.vstack(normals)


def soft_tissue_level(volume: Volume, labels: Volume) -> float:
    """Median attenuation of the soft tissue (1/mm)."""
    soft = volume.data[labels.data == SOFT_TISSUE_LABEL]
    if soft.size == 0:
        raise ValueError("the label volume has no soft tissue (label 1)")
    return float(np.median(soft))


def bone_regions(labels: Volume, edge_mm: float = BONE_EDGE_MM) -> np.ndarray:
    """Which tracked unit (1-based, in :data:`BONE_UNITS` order; 0 none) each voxel moves
    with: the unit's labels plus the soft-tissue voxels within ``edge_mm`` of it (to the
    nearest unit). The rim carries the blurred outer half of the bone's edge, which a mask at
    the segmentation's threshold would leave behind in the soft tissue as a ghost and cut off
    the moving bone: a bone model too small by a tenth of a millimetre already reads as a
    millimetre of depth in a lateral view (1 mm along the ray scales the image by ~0.1 %)."""
    units = np.zeros(labels.data.shape, dtype=np.int8)
    for k, values in enumerate(BONE_UNITS.values(), start=1):
        units[np.isin(labels.data, values)] = k
    if edge_mm <= 0 or not units.any():
        return units
    # the rim lies within edge_mm of a bone: the distances over the bones' box widened by it
    box, _ = _crop(units > 0, labels.grid, edge_mm)
    inside = units[box]  # a view: the rim is written into units
    outside = inside == 0
    distance, nearest = distance_transform_edt(
        outside, sampling=labels.grid.spacing_mm[::-1], return_indices=True
    )
    rim = outside & (distance <= edge_mm) & (labels.data[box] == SOFT_TISSUE_LABEL)
    inside[rim] = inside[tuple(index[rim] for index in nearest)]
    return units


def bone_models(
    volume: Volume,
    labels: Volume,
    margin_mm: float = CROP_MARGIN_MM,
    edge_mm: float = BONE_EDGE_MM,
) -> dict[str, BoneModel]:
    """The tracked bones of a segmented CBCT volume, ready to render.

    Each bone is the attenuation above the soft tissue's over its labels, plus the part above
    it in its :func:`bone_regions` rim (the blurred edge; a darker rim, e.g. fat, stays behind
    with the soft tissue); its points and centroid come from its labels alone.

    Args:
        volume: the static scan, attenuation in 1/mm.
        labels: its bone labels on the same grid (registration.labels.LABELS).
        margin_mm: margin kept around each bone's labels when its volume is cropped, mm.
        edge_mm: width of the rim beyond the labels that keeps the bone's blurred edge, mm.

    Returns:
        The models by tracked name (femur, tibia_fibula, patella), those the labels hold.
    """
    if volume.grid != labels.grid:
        raise ValueError(
            f"the label volume's grid {labels.grid} does not match the volume's {volume.grid}"
        )
    soft = soft_tissue_level(volume, labels)
    regions = bone_regions(labels, edge_mm)
    models = {}
    axes = volume.grid.axes_mm()
    for k, (name, values) in enumerate(BONE_UNITS.items(), start=1):
        mask = np.isin(labels.data, values)
        if mask.sum() < 27:
            raise ValueError(f"bone {name} (labels {list(values)}) is missing from the labels")
        region = regions == k
        box, sub = _crop(mask, volume.grid, max(margin_mm, edge_mm))
        above = volume.data[box] - soft
        rim = region[box] & ~mask[box]
        excess = np.where(rim, np.maximum(above, 0.0), np.where(region[box], above, 0.0))
        excess = excess.astype(np.float32)
        kz, ky, kx = np.nonzero(mask)
        points = np.column_stack((axes[0][kx], axes[1][ky], axes[2][kz]))
        models[name] = BoneModel(name, RigidVolume.of(excess, sub), points, points.mean(axis=0))
    return models


@numba.njit(fastmath=True, cache=True, inline="always")
def _blend(tibia_row, femur_row, p, share):  # pragma: no cover
    """One index coordinate of the blended pull-back of point ``p``."""
    qt = tibia_row[0] * p[0] + tibia_row[1] * p[1] + tibia_row[2] * p[2] + tibia_row[3]
    qf = femur_row[0] * p[0] + femur_row[1] * p[1] + femur_row[2] * p[2] + femur_row[3]
    return qt + share * (qf - qt)


@numba.njit(parallel=True, fastmath=True, cache=True, error_model="numpy")
def _pull_back(data, x, y, z, center, slope, tibia, femur, values, w):  # pragma: no cover
    """:meth:`SoftTissue.deformed`'s inner loop: at each voxel (x[i], y[j], z[k]) of the
    output, the femur's share ``w`` (smoothstep of ``(p - center) . slope + 1/2``) and ``data``
    trilinearly interpolated (zero outside) at the blended pull-back ``(1 - w) q_tibia + w
    q_femur``, each ``q = A p + b`` in ``data``'s voxel indices (x, y, z) from the 3 x 4
    ``tibia``, ``femur``."""
    nz, ny, nx = values.shape
    dz, dy, dx = data.shape
    for k in numba.prange(nz):
        for j in range(ny):
            for i in range(nx):
                p = (x[i], y[j], z[k])
                t = 0.5
                for a in range(3):
                    t += (p[a] - center[a]) * slope[a]
                t = min(max(t, 0.0), 1.0)
                share = t * t * (3.0 - 2.0 * t)
                w[k, j, i] = share
                qx = _blend(tibia[0], femur[0], p, share)
                qy = _blend(tibia[1], femur[1], p, share)
                qz = _blend(tibia[2], femur[2], p, share)
                ix, iy, iz = math.floor(qx), math.floor(qy), math.floor(qz)
                fx, fy, fz = qx - ix, qy - iy, qz - iz
                total = 0.0
                for cz in range(2):
                    zz = iz + cz
                    if zz < 0 or zz >= dz:
                        continue
                    wz = fz if cz else 1.0 - fz
                    for cy in range(2):
                        yy = iy + cy
                        if yy < 0 or yy >= dy:
                            continue
                        wy = fy if cy else 1.0 - fy
                        for cx in range(2):
                            xx = ix + cx
                            if xx < 0 or xx >= dx:
                                continue
                            total += wz * wy * (fx if cx else 1.0 - fx) * data[zz, yy, xx]
                values[k, j, i] = total


@numba.njit(cache=True, inline="always")
def _bone_share(w, femur):  # pragma: no cover
    """A voxel's share of the bone's motion, float32: the femur's ``w`` or the tibia's
    ``1 - w``."""
    return w if femur else np.float32(1.0) - w


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _split_kernel(data, w, femur, axis, pad, stays, carried):  # pragma: no cover
    """:meth:`SoftTissue.split`'s loops: ``data * (1 - s)`` into ``stays`` and the mean of
    each pair of ``data * s`` along array ``axis`` (0, 1, 2: z, y, x; an odd last slice
    dropped) into ``carried``, both ``pad`` voxels in from every side; ``s`` is the bone's
    share (:func:`_bone_share`). Float32 throughout, in numpy's order of operations (no
    fastmath): the values numpy's expressions give."""
    one, two = np.float32(1.0), np.float32(2.0)
    nz, ny, nx = data.shape
    for k in numba.prange(nz):
        for j in range(ny):
            for i in range(nx):
                s = _bone_share(w[k, j, i], femur)
                stays[k + pad, j + pad, i + pad] = data[k, j, i] * (one - s)
    dz, dy, dx = int(axis == 0), int(axis == 1), int(axis == 2)
    cz, cy, cx = carried.shape[0] - 2 * pad, carried.shape[1] - 2 * pad, carried.shape[2] - 2 * pad
    for k in numba.prange(cz):
        for j in range(cy):
            for i in range(cx):
                k0, j0, i0 = k * (1 + dz), j * (1 + dy), i * (1 + dx)
                k1, j1, i1 = k0 + dz, j0 + dy, i0 + dx
                first = data[k0, j0, i0] * _bone_share(w[k0, j0, i0], femur)
                second = data[k1, j1, i1] * _bone_share(w[k1, j1, i1], femur)
                carried[k + pad, j + pad, i + pad] = (first + second) / two


@dataclass(frozen=True, eq=False)
class SoftTissue:
    """The soft tissue (every bone voxel filled with the soft tissue's attenuation, every rim
    voxel of :func:`bone_regions` capped at it: the complement of :func:`bone_models`), on a
    lattice of about :data:`SOFT_TISSUE_VOXEL_MM`, deformed with the knee: a point ``x``
    shows the static scan at the blended pull-back ``(1 - w) T_tibia^-1 x + w T_femur^-1 x``,
    with ``w`` a smoothstep over ``blend_mm`` across the joint plane (through the moved joint
    centre, normal to the mean of the moved femoral and tibial long axes). The flesh bends
    at the knee instead of two rigid halves crossing each other; what the scan's box leaves
    out stays out, and where the box cuts the leg is known (``cuts``).

    Attributes:
        data: attenuation (1/mm) on ``grid``, the static scan's pose.
        grid: the lattice (the scan's box, pooled).
        joint_mm: the joint centre at the static scan (world mm).
        axes: the femur's and the tibia's long axes at the static scan, pointing up (2, 3).
        blend_mm: width of the hand-over from the tibia to the femur, mm.
        cuts: the scan's :func:`cut_outlines` (points, world mm, and their faces' normals, at
            the static scan) by the bone that carries them ("femur", "tibia_fibula": the
            larger share of the motion).
    """

    data: np.ndarray
    grid: VolumeGrid
    joint_mm: np.ndarray
    axes: np.ndarray
    blend_mm: float = SOFT_TISSUE_BLEND_MM
    cuts: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)

    @classmethod
    def of(
        cls,
        volume: Volume,
        labels: Volume,
        blend_mm: float = SOFT_TISSUE_BLEND_MM,
        edge_mm: float = BONE_EDGE_MM,
    ) -> SoftTissue:
        """The soft tissue of a segmented CBCT volume (attenuation 1/mm, labels on its grid)."""
        soft = soft_tissue_level(volume, labels)
        bone = labels.data > SOFT_TISSUE_LABEL
        rim = ~bone & (bone_regions(labels, edge_mm) > 0)
        filled = np.where(bone, soft, np.where(rim, np.minimum(volume.data, soft), volume.data))
        factor = tuple(max(1, round(SOFT_TISSUE_VOXEL_MM / s)) for s in volume.grid.spacing_mm)
        data, grid = _pooled(filled.astype(np.float32), volume.grid, factor)
        axes_mm = volume.grid.axes_mm()
        ends, axes, points = [], [], []
        for name in ("femur", "tibia"):
            kz, ky, kx = np.nonzero(labels.data == LABELS[name])
            if kz.size == 0:
                raise ValueError(f"the soft tissue bends at the knee: {name} must be labelled")
            xyz = np.column_stack((axes_mm[0][kx], axes_mm[1][ky], axes_mm[2][kz]))
            sample = xyz[:: max(1, len(xyz) // 20000)] - xyz.mean(axis=0)
            _, _, vt = np.linalg.svd(sample, full_matrices=False)
            # the principal axis nearest the standing leg's (world z): a bone the scan's box
            # cuts short can be wider than the part of it that is left is tall
            axis = vt[int(np.argmax(np.abs(vt[:, 2])))]
            axes.append(axis if axis[2] > 0 else -axis)
            ends.append(xyz[:, 2].min() if name == "femur" else xyz[:, 2].max())
            points.append(xyz)
        joint_z = 0.5 * sum(ends)
        near = np.vstack(points)
        near = near[np.abs(near[:, 2] - joint_z) < 0.5 * blend_mm]
        joint = np.array([*near[:, :2].mean(axis=0), joint_z])
        normal = axes[0] + axes[1]
        cuts, faces = cut_outlines(volume, soft)
        femoral = (cuts - joint) @ normal >= 0.0  # the femur's share >= 1/2
        carried = {
            b: (cuts[k], faces[k]) for b, k in (("femur", femoral), ("tibia_fibula", ~femoral))
        }
        return cls(data, grid, joint, np.array(axes), blend_mm, carried)

    def deformed(
        self, T_femur: np.ndarray, T_tibia: np.ndarray, view: View | None = None
    ) -> tuple[np.ndarray, np.ndarray, VolumeGrid]:
        """The soft tissue with the femur at ``T_femur`` and the tibia at ``T_tibia`` (zero
        where the pull-back leaves the scan's box), the femur's share ``w`` of each voxel's
        motion (the tibia's is ``1 - w``), and their grid: the lattice of ``grid`` over the
        box moved by either bone, within what ``view`` (if given) sees."""
        ends = [a[[0, -1]] for a in self.grid.axes_mm()]  # the outermost voxel centres
        corners = np.array([[x, y, z] for x in ends[0] for y in ends[1] for z in ends[2]])
        moved = np.vstack([corners @ T[:3, :3].T + T[:3, 3] for T in (T_femur, T_tibia)])
        lo, hi = moved.min(axis=0), moved.max(axis=0)
        if view is not None:
            lo, hi = _within_field(view, lo, hi)
        first = np.floor(self.grid.world_to_index(lo) + 1e-9)
        last = np.ceil(self.grid.world_to_index(hi) - 1e-9)
        spacing = np.asarray(self.grid.spacing_mm)
        origin = np.asarray(self.grid.origin_mm) + first * spacing
        shape = tuple(int(n) for n in np.maximum(last - first + 1, 1)[::-1])
        grid = VolumeGrid(shape, tuple(spacing), tuple(origin))
        normal = T_femur[:3, :3] @ self.axes[0] + T_tibia[:3, :3] @ self.axes[1]
        normal /= np.linalg.norm(normal)
        center = 0.5 * (T_femur[:3, :3] @ self.joint_mm + T_femur[:3, 3])
        center += 0.5 * (T_tibia[:3, :3] @ self.joint_mm + T_tibia[:3, 3])
        # each bone's pull-back straight to the scan's voxel indices: (x - origin) / spacing
        pull = []
        for T in (T_tibia, T_femur):
            inv = np.linalg.inv(T)
            pull.append(
                np.column_stack(
                    (inv[:3, :3] / spacing[:, None], (inv[:3, 3] - self.grid.origin_mm) / spacing)
                )
            )
        values = np.empty(shape, dtype=np.float32)
        w = np.empty(shape, dtype=np.float32)
        _pull_back(self.data, *grid.axes_mm(), center, normal / self.blend_mm, *pull, values, w)
        return values, w, grid

    def split(
        self, deformed: tuple[np.ndarray, np.ndarray, VolumeGrid], name: str, along: int
    ) -> tuple[JosephProjector, JosephProjector | None]:
        """The :meth:`deformed` soft tissue split into what stays when bone ``name`` moves a
        little and what it carries along (its share of each voxel's motion: the deformation
        to first order), ready to render: what stays on the deformation's lattice, what is
        carried averaged over pairs of slices along axis ``along`` (0, 1, 2: x, y, z; see
        :func:`along_axis`). All stays (and None is carried) for a bone other than the femur
        and the tibia. Each is written once, straight into its projector's padded array."""
        data, w, grid = deformed
        if name not in ("femur", "tibia_fibula"):
            return JosephProjector(data, grid), None
        pooled = _pooled_grid(grid, tuple(np.eye(3, dtype=int)[along] + 1))
        pad = JosephProjector.PAD
        stays = np.zeros(tuple(n + 2 * pad for n in grid.shape), dtype=np.float32)
        carried = np.zeros(tuple(n + 2 * pad for n in pooled.shape), dtype=np.float32)
        _split_kernel(data, w, name == "femur", 2 - along, pad, stays, carried)
        return JosephProjector.of_padded(stays, grid), JosephProjector.of_padded(carried, pooled)

    def render(self, view: View, poses: dict[str, np.ndarray]) -> np.ndarray:
        """Line integrals of the soft tissue deformed by ``poses`` (femur, tibia_fibula)."""
        data, _, grid = self.deformed(poses["femur"], poses["tibia_fibula"], view)
        return JosephProjector(data, grid).project(Geometry([view]))[0]


def _within_field(view: View, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The box ``lo``-``hi`` (world mm) cut to the bounding box of the part of ``view``'s
    field that crosses it: the panel's corner rays where they enter and leave the box's slab
    along the axis nearest the rays."""
    axis = int(np.argmax(np.abs(view.normal)))
    u = np.array([-0.5, view.cols - 0.5, -0.5, view.cols - 0.5])
    v = np.array([-0.5, -0.5, view.rows - 0.5, view.rows - 0.5])
    rays = view.pixel_to_world(u, v) - view.source_mm
    ends = [
        view.source_mm + ((plane - view.source_mm[axis]) / rays[:, axis])[:, None] * rays
        for plane in (lo[axis], hi[axis])
    ]
    seen = np.vstack(ends)
    cut_lo, cut_hi = np.maximum(lo, seen.min(axis=0)), np.minimum(hi, seen.max(axis=0))
    cut_lo[axis], cut_hi[axis] = lo[axis], hi[axis]
    return cut_lo, np.maximum(cut_hi, cut_lo)


def scene(
    view: View,
    bones: dict[str, BoneModel],
    poses: dict[str, np.ndarray],
    soft_tissue: SoftTissue | None = None,
    coarse: bool = False,
) -> np.ndarray:
    """Line integrals of every bone at its pose plus the soft tissue deformed by them
    (``coarse``: the bones' pooled volumes)."""
    image = np.zeros((view.rows, view.cols), dtype=np.float32)
    if soft_tissue is not None:
        image += soft_tissue.render(view, poses)
    for name, model in bones.items():
        image += model.render(view, poses[name], coarse)
    return image
