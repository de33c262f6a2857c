"""Digitally reconstructed radiographs of bones and of the whole knee scene.

A bone is its CBCT attenuation minus the soft tissue's, in a sub-volume cropped around it
(:class:`BoneModel`); the soft tissue is the CBCT volume with every bone voxel filled with the
soft tissue's attenuation (the bones displace it, no hole is left), in two parts that follow
the femur and the tibia (:func:`soft_tissue_parts`). A frame's scene is the soft
tissue plus every bone at its pose; moving a bone by ``T`` is rendering the unmoved bone
through the view moved by ``T^-1`` (recon.geometry.View.transformed), with the recon
projector (Joseph). Views are binned for the coarse levels of a resolution pyramid, and
volumes are averaged over 2 x 2 x 2 voxels for the views whose pixels (at the volume) are at
least twice the voxel size (:class:`RigidVolume`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import distance_transform_edt

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


def _pooled(
    data: np.ndarray, grid: VolumeGrid, axes_xyz: tuple[int, ...] = (0, 1, 2)
) -> tuple[np.ndarray, VolumeGrid]:
    """Mean over pairs of voxels along ``axes_xyz`` (0 = x); a trailing odd slice is dropped."""
    factor = np.ones(3, dtype=int)
    factor[list(axes_xyz)] = 2
    fz, fy, fx = factor[::-1]
    nz, ny, nx = (n // f for n, f in zip(data.shape, (fz, fy, fx), strict=True))
    blocks = data[: fz * nz, : fy * ny, : fx * nx].reshape(nz, fz, ny, fy, nx, fx)
    spacing = np.asarray(grid.spacing_mm)
    origin = np.asarray(grid.origin_mm) + 0.5 * (factor - 1) * spacing
    pooled = VolumeGrid((nz, ny, nx), tuple(factor * spacing), tuple(origin))
    return blocks.mean(axis=(1, 3, 5), dtype=np.float32), pooled


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
    def of(cls, data: np.ndarray, grid: VolumeGrid, fine: bool = True) -> RigidVolume:
        """Prepare ``data`` on ``grid``; ``fine=False`` keeps only the pooled copy (smooth
        volumes such as soft tissue, whose detail the high-pass similarity does not see)."""
        data = np.asarray(data, dtype=np.float32)
        coarse = JosephProjector(*_pooled(data, grid))
        if not fine:
            return cls((coarse, coarse, coarse), coarse)
        along = tuple(JosephProjector(*_pooled(data, grid, (k,))) for k in range(3))
        return cls(along, coarse)

    def voxel_mm(self) -> float:
        """The fine level's voxel size across the rays, mm."""
        return float(sorted(self.along[0].grid.spacing_mm)[0])

    def render(self, view: View, T_world: np.ndarray, coarse: bool = False) -> np.ndarray:
        """Line integrals of the volume moved by ``T_world``, float32 (rows, cols)."""
        moved = view.transformed(np.linalg.inv(T_world))
        if coarse:
            projector = self.coarse
        else:
            axis = int(np.argmax(np.abs(moved.detector_center_mm - moved.source_mm)))
            projector = self.along[axis]
        return projector.project(Geometry([moved]))[0]


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

    def render(self, view: View, T_world_bone: np.ndarray, coarse: bool = False) -> np.ndarray:
        """Line integrals of the bone moved by ``T_world_bone``, float32 (rows, cols)."""
        return self.volume.render(view, T_world_bone, coarse)


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
    if edge_mm <= 0:
        return units
    outside = units == 0
    distance, nearest = distance_transform_edt(
        outside, sampling=labels.grid.spacing_mm[::-1], return_indices=True
    )
    rim = outside & (distance <= edge_mm) & (labels.data == SOFT_TISSUE_LABEL)
    units[rim] = units[tuple(index[rim] for index in nearest)]
    return units


def bone_models(
    volume: Volume,
    labels: Volume,
    margin_mm: float = CROP_MARGIN_MM,
    edge_mm: float = BONE_EDGE_MM,
) -> dict[str, BoneModel]:
    """The tracked bones of a segmented CBCT volume (attenuation 1/mm, labels on its grid):
    each the attenuation above the soft tissue's over its labels, plus the part above it in
    its :func:`bone_regions` rim (the blurred edge; a darker rim, e.g. fat, stays behind with
    the soft tissue); its points and centroid from its labels alone."""
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


def soft_tissue_parts(
    volume: Volume,
    labels: Volume,
    blend_mm: float = SOFT_TISSUE_BLEND_MM,
    edge_mm: float = BONE_EDGE_MM,
) -> dict[str, RigidVolume]:
    """The soft tissue (every bone voxel filled with the soft tissue's attenuation, every rim
    voxel of :func:`bone_regions` capped at it: the complement of :func:`bone_models`) in two
    parts that sum to it: one moves with the femur, one with the tibia and fibula. The share
    of the femur's part rises smoothly (a smoothstep over ``blend_mm``) across the joint line,
    midway between the femur's lowest and the tibia's highest voxel, so that bending the knee
    leaves no cut edge in the images. Kept at half resolution only."""
    soft = soft_tissue_level(volume, labels)
    bone = labels.data > SOFT_TISSUE_LABEL
    rim = ~bone & (bone_regions(labels, edge_mm) > 0)
    filled = np.where(bone, soft, np.where(rim, np.minimum(volume.data, soft), volume.data))
    filled = filled.astype(np.float32)
    z = volume.grid.axes_mm()[2]
    femur_z = z[np.flatnonzero(np.isin(labels.data, BONE_UNITS["femur"]).any(axis=(1, 2)))]
    tibia_z = z[np.flatnonzero(np.isin(labels.data, BONE_UNITS["tibia_fibula"]).any(axis=(1, 2)))]
    if not femur_z.size or not tibia_z.size:
        raise ValueError("the soft tissue is split at the knee: femur and tibia must be labelled")
    joint = 0.5 * (femur_z.min() + tibia_z.max())
    t = np.clip((z - joint) / blend_mm + 0.5, 0.0, 1.0)
    share = (t * t * (3.0 - 2.0 * t)).astype(np.float32)[:, None, None]
    return {
        "femur": RigidVolume.of(filled * share, volume.grid, fine=False),
        "tibia_fibula": RigidVolume.of(filled * (1.0 - share), volume.grid, fine=False),
    }


def scene(
    view: View,
    bones: dict[str, BoneModel],
    poses: dict[str, np.ndarray],
    soft_tissue: dict[str, RigidVolume] | None = None,
    coarse: bool = False,
) -> np.ndarray:
    """Line integrals of every bone at its pose plus the soft tissue parts moved with theirs
    (``coarse``: the bones' pooled volumes)."""
    image = np.zeros((view.rows, view.cols), dtype=np.float32)
    for name, part in (soft_tissue or {}).items():
        image += part.render(view, poses[name], coarse=True)
    for name, model in bones.items():
        image += model.render(view, poses[name], coarse)
    return image
