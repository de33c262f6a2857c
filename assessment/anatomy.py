"""Anatomical frames of the femur and tibia found automatically in a label volume.

The volume is the static, standing CBCT scan (bones roughly vertical, the patient facing -y).
Left knees are mirrored into right knees first (x -> -x), so everything here reads a right
knee: medial is +x, lateral -x, anterior -y, proximal +z.

- Long axes: a line fitted through the centroids of axial slices of the shaft (the third of
  the bone farthest from the joint that the volume holds).
- Femoral transepicondylar axis (TEA): the medial and lateral epicondyles are the centroids of
  the surface caps farthest medial and lateral across the long axis (within 3 mm of the
  extreme); the knee centre is their midpoint.
- Condyles: the femur's surface points within reach of the TEA, split by the sagittal plane
  through the knee centre into medial and lateral compartments.
- Tibial plateau (TP) plane: least squares through the tibia's surface points that face up
  (normal within 45 degrees of the long axis) within 12 mm of its top, shifted along its
  normal by the configured offset.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from skimage.measure import marching_cubes

from recon.volume import Volume

PLATEAU_DEPTH_MM = 12.0
CONDYLE_REACH_MM = 45.0
EPICONDYLE_CAP_MM = 3.0


@dataclass(frozen=True)
class BoneSurface:
    """Surface of one bone: vertices (N, 3) and outward unit normals (N, 3), world mm."""

    points_mm: np.ndarray
    normals: np.ndarray


@dataclass(frozen=True)
class FemurAnatomy:
    """Femur landmarks in its reference pose (world mm, right-knee convention).

    Attributes:
        center_mm: knee centre, midpoint of the epicondyles.
        medial_epicondyle_mm, lateral_epicondyle_mm: TEA end points.
        lateral_axis: unit vector medial -> lateral along the TEA (X of the femur frame).
        proximal_axis: unit long axis, distal -> proximal (Z), orthogonal to X.
        medial_condyle_mm, lateral_condyle_mm: articular surface points per compartment.
    """

    center_mm: np.ndarray
    medial_epicondyle_mm: np.ndarray
    lateral_epicondyle_mm: np.ndarray
    lateral_axis: np.ndarray
    proximal_axis: np.ndarray
    medial_condyle_mm: np.ndarray
    lateral_condyle_mm: np.ndarray

    @property
    def frame(self) -> np.ndarray:
        """4x4 femur frame: X lateral, Y anterior, Z proximal, origin the knee centre."""
        return _frame(self.center_mm, self.lateral_axis, self.proximal_axis)


@dataclass(frozen=True)
class TibiaAnatomy:
    """Tibia landmarks in its reference pose (world mm, right-knee convention).

    Attributes:
        plateau_center_mm: centroid of the plateau points (TP plane point, after the offset).
        plateau_normal: unit TP plane normal, pointing proximally.
        proximal_axis: unit long axis, distal -> proximal.
        lateral_axis: unit medial -> lateral direction, orthogonal to the long axis.
        surface_mm: the plateau's upward-facing surface points (N, 3), where the condyles
            rest (assessment.contact); None when unknown.
    """

    plateau_center_mm: np.ndarray
    plateau_normal: np.ndarray
    proximal_axis: np.ndarray
    lateral_axis: np.ndarray
    surface_mm: np.ndarray | None = None

    @property
    def frame(self) -> np.ndarray:
        """4x4 tibia frame: X lateral, Y anterior, Z proximal, origin the plateau centre."""
        return _frame(self.plateau_center_mm, self.lateral_axis, self.proximal_axis)

    @property
    def plane_axes(self) -> tuple[np.ndarray, np.ndarray]:
        """Unit axes of the TP plane's 2-D frame: toward medial, toward anterior."""
        medial = -self.lateral_axis + np.dot(self.lateral_axis, self.plateau_normal) * (
            self.plateau_normal
        )
        medial /= np.linalg.norm(medial)
        anterior = np.cross(self.plateau_normal, -medial)
        return medial, anterior / np.linalg.norm(anterior)


def _frame(origin: np.ndarray, x_axis: np.ndarray, z_axis: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, 0] = x_axis
    T[:3, 1] = np.cross(z_axis, x_axis)
    T[:3, 2] = z_axis
    T[:3, 3] = origin
    return T


def mirror_x(volume: Volume) -> Volume:
    """The volume reflected through the plane x = 0 (a left knee seen as a right one)."""
    grid = volume.grid
    x_last = grid.origin_mm[0] + (grid.shape[2] - 1) * grid.spacing_mm[0]
    mirrored = type(grid)(grid.shape, grid.spacing_mm, (-x_last, *grid.origin_mm[1:]))
    return Volume(np.ascontiguousarray(volume.data[:, :, ::-1]), mirrored, volume.unit)


def bone_surface(labels: Volume, label: int, name: str) -> BoneSurface:
    """Marching-cubes surface of ``labels == label`` in world mm; vertices whose gradient
    vanishes (voxels touching by an edge in a symmetric pattern) have no normal and are
    left out."""
    mask = labels.data == label
    if mask.sum() < 27:
        raise ValueError(f"bone {name} (label {label}) is missing from the label volume")
    padded = np.pad(mask, 1).astype(np.float32)
    spacing_zyx = labels.grid.spacing_mm[::-1]
    verts, faces, normals, _ = marching_cubes(padded, 0.5, spacing=spacing_zyx)
    del faces
    origin_zyx = np.array(labels.grid.origin_mm[::-1]) - np.array(spacing_zyx)
    points = (verts + origin_zyx)[:, ::-1]
    # marching_cubes normals point toward lower values: outward of the mask
    normals = normals[:, ::-1]
    length = np.linalg.norm(normals, axis=1)
    facing = length > 0.0
    return BoneSurface(points[facing], normals[facing] / length[facing, None])


def _long_axis(labels: Volume, label: int, away_from_joint: str) -> np.ndarray:
    """Unit proximal axis through slice centroids of the third of the bone farthest from the
    joint ("top" for the femur, "bottom" for the tibia)."""
    mask = labels.data == label
    zs = np.flatnonzero(mask.any(axis=(1, 2)))
    third = max(3, len(zs) // 3)
    use = zs[-third:] if away_from_joint == "top" else zs[:third]
    x, y, z = labels.grid.axes_mm()
    centroids = []
    for k in use:
        rows, cols = np.nonzero(mask[k])
        centroids.append([x[cols].mean(), y[rows].mean(), z[k]])
    centroids = np.array(centroids)
    _, _, vt = np.linalg.svd(centroids - centroids.mean(axis=0))
    axis = vt[0]
    return axis if axis[2] > 0 else -axis


def femur_anatomy(labels: Volume, femur_label: int) -> FemurAnatomy:
    """Femur landmarks of a right knee (mirror left knees first, :func:`mirror_x`)."""
    surface = bone_surface(labels, femur_label, "femur")
    up = _long_axis(labels, femur_label, "top")
    lateral0 = np.array([-1.0, 0.0, 0.0]) - up * (-up[0])
    lateral0 /= np.linalg.norm(lateral0)
    # the distal part: below the middle of the femur's extent along the long axis
    height = surface.points_mm @ up
    distal = surface.points_mm[height < np.median(height)]
    across = distal @ lateral0
    # each epicondyle: the centroid of the surface cap within EPICONDYLE_CAP_MM of the extreme,
    # so a rounded tip does not tilt the axis
    lateral_epi = distal[across >= across.max() - EPICONDYLE_CAP_MM].mean(axis=0)
    medial_epi = distal[across <= across.min() + EPICONDYLE_CAP_MM].mean(axis=0)
    lateral = lateral_epi - medial_epi
    lateral -= np.dot(lateral, up) * up
    lateral /= np.linalg.norm(lateral)
    proximal = up - np.dot(up, lateral) * lateral
    proximal /= np.linalg.norm(proximal)
    center = 0.5 * (lateral_epi + medial_epi)
    rel = surface.points_mm - center
    along_tea = rel @ lateral
    off_axis = rel - np.outer(along_tea, lateral)
    near = np.linalg.norm(off_axis, axis=1) <= CONDYLE_REACH_MM
    below_center_top = (rel @ proximal) <= 10.0
    articular = near & below_center_top
    return FemurAnatomy(
        center_mm=center,
        medial_epicondyle_mm=medial_epi,
        lateral_epicondyle_mm=lateral_epi,
        lateral_axis=lateral,
        proximal_axis=proximal,
        medial_condyle_mm=surface.points_mm[articular & (along_tea < 0)],
        lateral_condyle_mm=surface.points_mm[articular & (along_tea > 0)],
    )


def tibia_anatomy(labels: Volume, tibia_label: int, plateau_offset_mm: float = 0.0) -> TibiaAnatomy:
    """Tibia landmarks and the TP plane of a right knee (mirror left knees first)."""
    surface = bone_surface(labels, tibia_label, "tibia")
    up = _long_axis(labels, tibia_label, "bottom")
    height = surface.points_mm @ up
    top = height.max()
    facing_up = surface.normals @ up > np.cos(np.radians(45.0))
    plateau = surface.points_mm[facing_up & (height > top - PLATEAU_DEPTH_MM)]
    if len(plateau) < 30:
        raise ValueError("the tibial plateau was not found: too few upward-facing surface points")
    centroid = plateau.mean(axis=0)
    _, _, vt = np.linalg.svd(plateau - centroid)
    normal = vt[2] if np.dot(vt[2], up) > 0 else -vt[2]
    lateral = np.array([-1.0, 0.0, 0.0]) - up * (-up[0])
    lateral /= np.linalg.norm(lateral)
    return TibiaAnatomy(
        plateau_center_mm=centroid + plateau_offset_mm * normal,
        plateau_normal=normal,
        proximal_axis=up,
        lateral_axis=lateral,
        surface_mm=plateau,
    )
