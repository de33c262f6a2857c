"""Digitally reconstructed radiographs of bones and of the whole knee scene.

A bone is its CBCT attenuation minus the soft tissue's, in a sub-volume cropped around it
(:class:`BoneModel`); the soft tissue is the CBCT volume with every bone voxel filled with the
soft tissue's attenuation (the bones displace it, no hole is left). A frame's scene is the soft
tissue plus every bone at its pose; moving a bone by ``T`` is rendering the unmoved bone
through the view moved by ``T^-1`` (recon.geometry.View.transformed), with the recon
projector (Joseph). Views are binned for the coarse levels of a resolution pyramid.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from recon.geometry import Geometry, View
from recon.project import JosephProjector
from recon.volume import Volume, VolumeGrid
from registration.segment import BONE_UNITS, LABELS

SOFT_TISSUE_LABEL = LABELS["soft_tissue"]
CROP_MARGIN_MM = 3.0


@dataclass(frozen=True)
class BoneModel:
    """One rigid bone for rendering and error measurement.

    Attributes:
        name: "femur", "tibia_fibula" or "patella".
        projector: the bone's excess attenuation (1/mm over soft tissue) on its cropped grid.
        points_mm: centres of the bone's voxels at the reference pose (N, 3).
        centroid_mm: their mean (rotations of the 6-DoF parameterisation are about it).
    """

    name: str
    projector: JosephProjector
    points_mm: np.ndarray
    centroid_mm: np.ndarray

    def render(self, view: View, T_world_bone: np.ndarray) -> np.ndarray:
        """Line integrals of the bone moved by ``T_world_bone``, float32 (rows, cols)."""
        moved = view.transformed(np.linalg.inv(T_world_bone))
        return self.projector.project(Geometry([moved]))[0]


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


def bone_models(
    volume: Volume, labels: Volume, margin_mm: float = CROP_MARGIN_MM
) -> dict[str, BoneModel]:
    """The tracked bones of a segmented CBCT volume (attenuation 1/mm, labels on its grid)."""
    if volume.grid != labels.grid:
        raise ValueError(
            f"the label volume's grid {labels.grid} does not match the volume's {volume.grid}"
        )
    soft = soft_tissue_level(volume, labels)
    models = {}
    axes = volume.grid.axes_mm()
    for name, values in BONE_UNITS.items():
        mask = np.isin(labels.data, values)
        if mask.sum() < 27:
            raise ValueError(f"bone {name} (labels {list(values)}) is missing from the labels")
        box, sub = _crop(mask, volume.grid, margin_mm)
        excess = np.where(mask[box], volume.data[box] - soft, 0.0).astype(np.float32)
        kz, ky, kx = np.nonzero(mask)
        points = np.column_stack((axes[0][kx], axes[1][ky], axes[2][kz]))
        models[name] = BoneModel(name, JosephProjector(excess, sub), points, points.mean(axis=0))
    return models


def soft_tissue_projector(volume: Volume, labels: Volume) -> JosephProjector:
    """The CBCT volume with every bone voxel filled with soft tissue, ready to project."""
    soft = soft_tissue_level(volume, labels)
    bone = labels.data > SOFT_TISSUE_LABEL
    filled = np.where(bone, soft, volume.data).astype(np.float32)
    return JosephProjector(filled, volume.grid)


def scene(
    view: View,
    bones: dict[str, BoneModel],
    poses: dict[str, np.ndarray],
    soft_tissue: JosephProjector | None = None,
    soft_pose: np.ndarray | None = None,
) -> np.ndarray:
    """Line integrals of the soft tissue (moved by ``soft_pose``) plus every bone at its pose."""
    image = np.zeros((view.rows, view.cols), dtype=np.float32)
    if soft_tissue is not None:
        T = np.eye(4) if soft_pose is None else soft_pose
        image += soft_tissue.project(Geometry([view.transformed(np.linalg.inv(T))]))[0]
    for name, model in bones.items():
        image += model.render(view, poses[name])
    return image
