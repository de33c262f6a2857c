"""Bone segmentation of a knee CBCT volume without model weights (docs/system.md, step 1).

Classical 3D segmentation of a reconstruction in linear attenuation (1/mm), in five steps:

1. **Intensity reference.** The soft-tissue level is the mode of the histogram of the voxels
   above the air/tissue Otsu threshold (muscle is the commonest tissue in a knee), unless
   given. Cone-beam reconstructions drift in level toward the ends of the scanned range, so
   each axial slice is rescaled by the median of its tissue (relative to the median slice)
   and every threshold below is a multiple of the soft-tissue level.
2. **Bone mask.** Cortical bone is 2-2.5 times as attenuating as soft tissue, cancellous bone
   only ~20 % more and marrow less, so bone is found through its cortical shell: the voxels
   above an edge threshold, closed by one voxel and filled (holes per axial slice, caps where
   a shaft leaves the field of view, then holes in 3D). The edge threshold is the isovalue
   among :data:`EDGE_CANDIDATES` (1.3-1.95 times soft tissue) with the largest mean gradient
   magnitude, among those that meet the bone broadly (:data:`MIN_EDGE_BAND_SHARE`): the bone
   surface is where the intensity changes fastest. For a 1.5 mm cortex seen at 1 mm this
   sits slightly outside the half-bone partial-volume surface (the phantom's labels), by a
   fraction of a voxel.
3. **Separation.** Each bone's cortex encloses its own interior, also where cortices fuse
   across a joint space thinner than the resolution: the tibiofibular joint (~1.5 mm), and
   the femorotibial (~4 mm) or patellofemoral ones in coarse volumes. The distance transform
   has no neck there (the fibular head rests broadly against the tibia), so the markers of
   the watershed are the interiors, and the cortex goes to the nearest interior within the
   bone (a watershed of the distance to the markers); bone without an interior at this
   resolution is one region per connected component.
4. **Naming** in the world frame (standing patient, LPS: +z up, -y anterior, +x toward the
   patient's left). Femur and tibia are the pair of regions with the largest total volume
   lying one above the other (each centroid beyond the other's extent in z); the joint line is
   the femur's lowest point. The patella is the largest region anterior to both, above the
   tibia's centroid; the fibula the largest region below the joint line, posterior and lateral
   to the tibia (lateral is -x for a right knee, +x for a left one, so its side tells which
   knee this is unless ``side`` is given). Watershed fragments of none of these join the named
   bone they share most boundary with; isolated fragments are dropped.
5. **Soft tissue** is the largest connected region above half the soft-tissue level, filled
   per axial slice; the rest is air.

Label values follow registration.labels (:data:`LABELS`, also the phantom's).
Registration tracks three units (:data:`BONE_UNITS`): femur, tibia with fibula, patella;
:func:`bone_surfaces` meshes them and :func:`bone_points` returns their voxel clouds.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import trimesh
from scipy import ndimage
from scipy.spatial import ConvexHull, Delaunay
from skimage.measure import marching_cubes
from skimage.segmentation import watershed

from recon.volume import Volume
from registration.labels import BONE_UNITS, LABELS

EDGE_CANDIDATES = np.arange(1.30, 1.96, 0.05)
"""Bone edge thresholds tried, in multiples of the soft-tissue level."""
MIN_EDGE_BAND_SHARE = 0.2
"""An edge candidate's band must hold at least this share of the fullest candidate's voxels:
an isovalue above most of the cortex meets the bone only in patches (the cortex's brightest
voxels, whose few steep gradients would otherwise win; a TV-regularised volume has them)."""

METAL_AS_CORTEX = 2.5
"""An implant's stand-in level for bone segmentation, in multiples of the soft tissue's (a
cortex's: bone is found through its cortex)."""
CAPPED_BONE = 1.1
"""Bone an implant caps: above this many times the soft tissue's level (measured on the
simulated knee replacement through NMAR: the bones' Dice within 20 mm of the metal 0.91-0.92
from 1.05 to 1.15, the femur's falling from 1.2)."""
MIN_MARKER_MM3 = 20.0
"""Smallest bone interior that seeds a region of its own, mm^3."""

MIN_BONE_MM3 = 500.0
"""Smallest region named as a bone, mm^3 (the patella is ~20 cm^3, the fibular head ~5)."""

_BODY_LEVEL = 0.5  # soft tissue: above this fraction of the soft-tissue level
_MIN_SLICE_TISSUE = 0.01  # share of a slice that must be tissue to estimate its level
_TISSUE_FRACTION = 0.25  # tissue: above this share of the 99th percentile (bone)
_LEVEL_SMOOTHING_SLICES = 5  # median filter of the per-slice levels along z
_HISTOGRAM_BINS = 256
_ANTERIOR_MARGIN_MM = 10.0  # patella centroid at least this far anterior of femur and tibia
_LATERAL_MARGIN_MM = 10.0  # fibula centroid at least this far lateral of the tibia's


@dataclass(frozen=True)
class _Region:
    """A candidate bone region: its watershed label, size (mm^3) and world extent (mm)."""

    label: int
    volume_mm3: float
    centroid: np.ndarray
    lo: np.ndarray
    hi: np.ndarray


def segment_bones(
    volume: Volume,
    *,
    soft_tissue_per_mm: float | None = None,
    side: Literal["right", "left"] | None = None,
    anchors: np.ndarray | None = None,
) -> Volume:
    """Label the femur, tibia, fibula and patella of a knee CBCT volume (module docstring).

    Args:
        volume: reconstruction in linear attenuation, unit "1/mm", world frame LPS with +z up
            (standing patient).
        soft_tissue_per_mm: soft-tissue (muscle) attenuation, 1/mm; default estimated from
            the histogram.
        side: "right" or "left" knee; default inferred from the fibula (lateral: -x for a
            right knee, +x for a left one).
        anchors: Bone without an interior of its own that marks a region of its own in the
            separation (bool [z, y, x]; an implant and the voxels touching it): the cortex
            next to it goes to it, not to the nearest other bone's interior.

    Returns:
        uint8 labels on the same grid, unit "label": :data:`LABELS` (air 0, soft tissue 1,
        femur 2, tibia 3, fibula 4, patella 5).

    Raises:
        ValueError: not attenuation, no tissue or no bone in the volume, or one of the four
            bones not found where anatomy puts it.
    """
    if volume.unit != "1/mm":
        raise ValueError(f"segment_bones needs linear attenuation (unit '1/mm'), got {volume.unit}")
    data = np.asarray(volume.data, dtype=np.float32)
    soft = _soft_tissue_level(data) if soft_tissue_per_mm is None else float(soft_tissue_per_mm)
    if not soft > 0.0:
        raise ValueError(f"soft_tissue_per_mm must be > 0 1/mm, got {soft_tissue_per_mm!r}")
    relative = data / (soft * _slice_levels(data, soft))[:, None, None]
    spacing_zyx = np.array(volume.grid.spacing_mm[::-1])
    voxel_mm3 = volume.grid.voxel_volume_mm3

    candidate = relative >= EDGE_CANDIDATES[0]
    sizes = np.bincount(ndimage.label(candidate)[0].ravel())[1:]
    if not np.any(sizes * voxel_mm3 >= MIN_BONE_MM3):
        raise ValueError(
            f"a volume without bone: no region of {MIN_BONE_MM3:g} mm^3 is brighter than "
            f"{EDGE_CANDIDATES[0]:g} x the soft-tissue level ({soft:.4g} 1/mm)"
        )
    box = _bounding_box(candidate, margin=3)
    edge = _edge_threshold(relative[box], spacing_zyx)
    bone = np.zeros(data.shape, dtype=bool)
    regions = np.zeros(data.shape, dtype=np.int32)
    bone[box], interior = _fill_bone(relative[box] >= edge)
    anchored = None if anchors is None else np.asarray(anchors, dtype=bool)[box] & bone[box]
    regions[box] = _separate(bone[box], interior, spacing_zyx, voxel_mm3, anchored)
    named = _name_bones(regions, volume, side)

    labels = np.zeros(data.shape, dtype=np.uint8)
    labels[_body_mask(relative) | bone] = LABELS["soft_tissue"]
    value_of_region = np.zeros(int(regions.max()) + 1, dtype=np.uint8)
    for region, name in named.items():
        value_of_region[region] = LABELS[name]
    bone_labels = value_of_region[regions]
    labels[bone_labels > 0] = bone_labels[bone_labels > 0]
    return Volume(labels, volume.grid, "label")


def segment_bones_with_metal(
    volume: Volume,
    metal: np.ndarray,
    metal_label: int,
    side: Literal["right", "left"] | None = None,
) -> Volume:
    """Label the bones of a knee with an implant (:func:`segment_bones`), ``metal`` (bool
    [z, y, x], recon.mar's) labelled ``metal_label`` with the voxels touching it.

    Bone is found through its cortex, and next to metal the cortex is what a reconstruction
    loses first (its rays all cross the metal). So before the bones are segmented:

    - the metal and the voxels touching it are set to :data:`METAL_AS_CORTEX` x the soft
      tissue's level: bone fixed to an implant is closed by it as by its own cortex;
    - so is the bone the implant caps: the voxels inside each metal region's convex hull (a
      femoral component's box, a tray's plate and stem) above :data:`CAPPED_BONE` x the soft
      tissue's level once smoothed (cancellous bone is ~1.4 x; the notch's soft tissue ~1);
    - each implant, with the voxels touching it, is a marker of its own in the separation
      (``anchors``): the cortex beside a tray that encloses no interior of its own goes to
      the tray, and with it to the tibia, not to the fibula's interior nearby. (The capped
      bone as well would take the femur's posterior condyles from it.)
    """
    near = ndimage.binary_dilation(np.asarray(metal, dtype=bool))
    data = np.asarray(volume.data, dtype=np.float32).copy()
    soft = _soft_tissue_level(np.where(near, 0.0, data))
    smooth = ndimage.gaussian_filter(np.where(near, soft, data), 1.0)
    capped = _convex_hulls(np.asarray(metal, dtype=bool)) & (smooth > CAPPED_BONE * soft)
    data[near | capped] = METAL_AS_CORTEX * soft
    labels = segment_bones(Volume(data, volume.grid, "1/mm"), side=side, anchors=near)
    labels.data[near] = metal_label
    return labels


def _convex_hulls(mask: np.ndarray) -> np.ndarray:
    """The voxels inside the convex hull of each connected region of ``mask`` (bool)."""
    regions, _ = ndimage.label(mask)
    out = np.zeros(mask.shape, dtype=bool)
    for k, box in enumerate(ndimage.find_objects(regions), start=1):
        points = np.argwhere(regions[box] == k)
        if len(points) < 4 or np.linalg.matrix_rank(points - points[0]) < 3:
            out[box] |= regions[box] == k  # flat: its own voxels
            continue
        hull = Delaunay(points[ConvexHull(points).vertices])
        voxels = np.indices(regions[box].shape).reshape(3, -1).T
        out[box] |= (hull.find_simplex(voxels) >= 0).reshape(regions[box].shape)
    return out


def bone_surfaces(labels: Volume) -> dict[str, trimesh.Trimesh]:
    """Surface meshes of the :data:`BONE_UNITS` ("femur", "tibia_fibula", "patella").

    Marching cubes at 0.5 of each unit's binary mask, padded by one voxel so that bones cut by
    the field of view are closed by a cap there (the meshes are watertight); vertices in world
    mm, faces oriented outward.

    Args:
        labels: :func:`segment_bones` output (or phantom labels), unit "label".

    Raises:
        ValueError: a unit has no voxel.
    """
    grid = labels.grid
    out = {}
    for name, mask in _unit_masks(labels).items():
        padded = np.pad(mask, 1).astype(np.float32)
        verts, faces, _, _ = marching_cubes(padded, 0.5, spacing=grid.spacing_mm[::-1])
        xyz = verts[:, ::-1] - np.asarray(grid.spacing_mm) + np.asarray(grid.origin_mm)
        mesh = trimesh.Trimesh(xyz, faces, process=True)
        if mesh.volume < 0.0:
            mesh.invert()
        out[name] = mesh
    return out


def bone_points(labels: Volume, volume: Volume) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Voxel clouds of the :data:`BONE_UNITS`: centres (N, 3) world mm and values (N,).

    Args:
        labels: :func:`segment_bones` output, unit "label".
        volume: the values to sample (e.g. the reconstruction, 1/mm) on the same grid.

    Raises:
        ValueError: the grids differ or a unit has no voxel.
    """
    if labels.grid != volume.grid:
        raise ValueError(f"labels grid {labels.grid} differs from volume grid {volume.grid}")
    x, y, z = labels.grid.axes_mm()
    out = {}
    for name, mask in _unit_masks(labels).items():
        kz, ky, kx = np.nonzero(mask)
        points = np.stack((x[kx], y[ky], z[kz]), axis=1)
        out[name] = (points, np.asarray(volume.data[kz, ky, kx], dtype=np.float64))
    return out


# -- steps ---------------------------------------------------------------------------------


def _soft_tissue_level(data: np.ndarray) -> float:
    """Mode of the histogram of the tissue voxels, 1/mm: those above a quarter of the 99th
    percentile (bone), which separates air from tissue whether or not the grid holds much
    air (an Otsu split of a grid inside the leg would fall between soft tissue and bone)."""
    sample = data[::2, ::2, ::2]
    if not np.ptp(sample) > 0.0:
        raise ValueError("a constant volume has no tissue to segment")
    tissue = sample[sample > _TISSUE_FRACTION * np.percentile(sample, 99)]
    counts, edges = np.histogram(
        tissue, bins=_HISTOGRAM_BINS, range=(float(tissue.min()), float(np.percentile(tissue, 99)))
    )
    peak = int(np.argmax(ndimage.gaussian_filter1d(counts.astype(np.float64), 2.0)))
    level = 0.5 * float(edges[peak] + edges[peak + 1])
    if not level > 0.0:
        raise ValueError("no tissue found: the volume's histogram has no positive peak")
    return level


def _slice_levels(data: np.ndarray, soft: float) -> np.ndarray:
    """Per axial slice, its tissue level relative to the volume's (1 where undetermined)."""
    medians = np.full(data.shape[0], np.nan)
    min_voxels = _MIN_SLICE_TISSUE * data.shape[1] * data.shape[2]
    for k, image in enumerate(data):
        level = soft
        for _ in range(2):  # re-threshold at half the slice's own level
            tissue = image[image > _BODY_LEVEL * level]
            if tissue.size < min_voxels:
                break
            level = float(np.median(tissue))
        else:
            medians[k] = level
    if np.all(np.isnan(medians)):
        return np.ones(data.shape[0])
    relative = medians / np.nanmedian(medians)
    relative = np.where(np.isnan(relative), 1.0, relative)
    return ndimage.median_filter(relative, _LEVEL_SMOOTHING_SLICES, mode="nearest")


def _bounding_box(mask: np.ndarray, margin: int) -> tuple[slice, ...]:
    """Slices of the bounding box of ``mask``, widened by ``margin`` voxels."""
    box = []
    for axis in range(3):
        hit = np.nonzero(np.any(mask, axis=tuple(a for a in range(3) if a != axis)))[0]
        box.append(slice(max(int(hit[0]) - margin, 0), int(hit[-1]) + margin + 1))
    return tuple(box)


def _edge_threshold(relative: np.ndarray, spacing_zyx: np.ndarray) -> float:
    """Isovalue of :data:`EDGE_CANDIDATES` where the mean gradient magnitude is largest, of
    those whose band near the bone holds :data:`MIN_EDGE_BAND_SHARE` of the fullest band."""
    gradient = np.linalg.norm(np.stack(np.gradient(relative, *spacing_zyx)), axis=0)
    near_bone = ndimage.binary_dilation(relative >= EDGE_CANDIDATES[0])
    values, gradient = relative[near_bone], gradient[near_bone]
    half = 0.5 * (EDGE_CANDIDATES[1] - EDGE_CANDIDATES[0])
    bands = [np.abs(values - t) < half for t in EDGE_CANDIDATES]
    counts = np.array([band.sum() for band in bands])
    means = [
        float(gradient[band].mean()) if count >= max(MIN_EDGE_BAND_SHARE * counts.max(), 1) else 0.0
        for band, count in zip(bands, counts, strict=True)
    ]
    return float(EDGE_CANDIDATES[int(np.argmax(means))])


def _fill_bone(shell: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cortical shell -> solid bone and its interior (cancellous bone and marrow).

    The shell is closed by one voxel and filled: holes per slice along each axis (shafts
    leaving through the top or bottom; a gap in one slice's shell is usually closed in the
    slices across it), caps on the faces of the array (filled cross-sections where a bone
    leaves the field of view), then holes in 3D. Voxels the closing added are kept only where
    they end up enclosed, so the closing seals gaps in the shell without growing the bones or
    bridging them.

    Returns:
        The bone mask and the interior mask (enclosed, below the edge threshold).
    """
    cross = ndimage.generate_binary_structure(3, 1)
    # pad by repetition: a closing erodes the array's border, where bones leave the field
    sealed = ndimage.binary_closing(np.pad(shell, 1, mode="edge"), cross)[1:-1, 1:-1, 1:-1]
    filled = sealed.copy()
    for axis in range(3):  # a gap in the shell of one slice is often closed across the others
        view = np.moveaxis(filled, axis, 0)
        for k, image in enumerate(np.moveaxis(sealed, axis, 0)):
            view[k] |= ndimage.binary_fill_holes(image)
    for axis in range(3):  # cap bones cut by a face of the field of view
        faces = np.moveaxis(filled, axis, 0)
        for k in (0, -1):
            faces[k] = ndimage.binary_fill_holes(faces[k])
    interior = ndimage.binary_fill_holes(filled) & ~sealed
    return shell | interior, interior


def _separate(
    bone: np.ndarray,
    interior: np.ndarray,
    spacing_zyx: np.ndarray,
    voxel_mm3: float,
    anchors: np.ndarray | None = None,
) -> np.ndarray:
    """Regions of the bone mask: one per enclosed interior, grown over the cortex.

    Markers are the interiors of at least :data:`MIN_MARKER_MM3`; each cortex voxel goes to
    the interior nearest to it within the bone (a watershed of the distance to the markers),
    so a fused wall between two bones is split down its middle; each of ``anchors``'
    connected parts is a marker too. Bone without a marker (no interior at this resolution)
    becomes one region per connected component.
    """
    markers, _ = ndimage.label(interior)
    sizes = np.bincount(markers.ravel())
    small = sizes * voxel_mm3 < MIN_MARKER_MM3
    small[0] = True
    markers[small[markers]] = 0
    if anchors is not None:  # each anchor a marker of its own, apart from the interiors
        own, _ = ndimage.label(anchors)
        markers[anchors] = 0
        markers[own > 0] = own[own > 0] + sizes.size
    distance = ndimage.distance_transform_edt(markers == 0, sampling=spacing_zyx)
    regions = watershed(distance, markers, mask=bone)
    unmarked, _ = ndimage.label(bone & (regions == 0))
    regions[unmarked > 0] = unmarked[unmarked > 0] + int(markers.max()) + 1
    return regions


def _region_table(regions: np.ndarray, volume: Volume) -> list[_Region]:
    """Regions of at least :data:`MIN_BONE_MM3`, largest first, with centroid and extent."""
    grid = volume.grid
    counts = np.bincount(regions.ravel())
    table = []
    for label, box in enumerate(ndimage.find_objects(regions), start=1):
        if box is None or counts[label] * grid.voxel_volume_mm3 < MIN_BONE_MM3:
            continue
        index = np.argwhere(regions[box] == label) + [s.start for s in box]
        world = grid.index_to_world(index[:, ::-1])
        table.append(
            _Region(
                label,
                counts[label] * grid.voxel_volume_mm3,
                world.mean(axis=0),
                world.min(axis=0),
                world.max(axis=0),
            )
        )
    return sorted(table, key=lambda r: -r.volume_mm3)


def _name_bones(
    regions: np.ndarray, volume: Volume, side: Literal["right", "left"] | None
) -> dict[int, str]:
    """Region label -> bone name, by anatomy (module docstring, step 4)."""
    table = _region_table(regions, volume)
    if not table:
        raise ValueError(f"a volume without bone: no bone region of at least {MIN_BONE_MM3:g} mm^3")
    pairs = [
        (upper, lower)
        for upper in table
        for lower in table
        if upper.centroid[2] > lower.hi[2] and lower.centroid[2] < upper.lo[2]
    ]
    if not pairs:
        big = table[0]
        raise ValueError(
            f"no bone found above or below the largest bone (z {big.lo[2]:.0f} to "
            f"{big.hi[2]:.0f} mm): the volume must hold both the femur and the tibia"
        )
    femur, tibia = max(pairs, key=lambda p: p[0].volume_mm3 + p[1].volume_mm3)
    joint_z = femur.lo[2]
    rest = [r for r in table if r.label not in (femur.label, tibia.label)]

    anterior_of = min(femur.centroid[1], tibia.centroid[1]) - _ANTERIOR_MARGIN_MM
    patellae = [
        r for r in rest if r.centroid[1] < anterior_of and r.centroid[2] > tibia.centroid[2]
    ]
    if not patellae:
        raise ValueError(
            f"no patella found: no bone anterior of y = {anterior_of:.0f} mm above the tibia"
        )
    patella = patellae[0]

    lateral = {"right": -1.0, "left": 1.0}
    fibulae = [
        r
        for r in rest
        if r is not patella
        and r.centroid[2] < joint_z
        and r.centroid[1] > tibia.centroid[1]
        and abs(r.centroid[0] - tibia.centroid[0]) > _LATERAL_MARGIN_MM
        and (side is None or lateral[side] * (r.centroid[0] - tibia.centroid[0]) > 0.0)
    ]
    if not fibulae:
        where = "" if side is None else f" ({'-' if side == 'right' else '+'}x for a {side} knee)"
        raise ValueError(
            f"no fibula found below the joint line (z {joint_z:.0f} mm), posterior and "
            f"lateral{where} of the tibia"
        )
    named = {
        femur.label: "femur",
        tibia.label: "tibia",
        patella.label: "patella",
        fibulae[0].label: "fibula",
    }
    _merge_fragments(regions, named)
    return named


def _merge_fragments(regions: np.ndarray, named: dict[int, str]) -> None:
    """Join unnamed regions to the named one they touch most (in place); drop the others."""
    for label, box in enumerate(ndimage.find_objects(regions), start=1):
        if box is None or label in named:
            continue
        wide = tuple(slice(max(s.start - 1, 0), s.stop + 1) for s in box)
        block = regions[wide]
        own = block == label
        neighbours = block[ndimage.binary_dilation(own) & ~own]
        touching = neighbours[np.isin(neighbours, list(named))]
        block[own] = np.bincount(touching).argmax() if touching.size else 0


def _body_mask(relative: np.ndarray) -> np.ndarray:
    """The leg: largest region above half the soft-tissue level, filled per axial slice."""
    tissue, n = ndimage.label(relative > _BODY_LEVEL)
    if n == 0:
        return tissue > 0
    largest = tissue == 1 + int(np.argmax(np.bincount(tissue.ravel())[1:]))
    return np.stack([ndimage.binary_fill_holes(image) for image in largest])


def _unit_masks(labels: Volume) -> dict[str, np.ndarray]:
    """Binary mask per :data:`BONE_UNITS` entry; ValueError when one is empty."""
    if labels.unit != "label":
        raise ValueError(f"expected a label volume, got unit {labels.unit!r}")
    masks = {name: np.isin(labels.data, values) for name, values in BONE_UNITS.items()}
    for name, mask in masks.items():
        if not mask.any():
            raise ValueError(f"no {name} in the labels (values {BONE_UNITS[name]})")
    return masks
