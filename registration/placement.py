"""Implant components placed in the static scan: each component's mesh registered to the metal
of the reconstruction (3D-3D).

The metal (recon.mar's mask) falls into connected regions. Each mesh, the largest first, takes
the free region it fits best:

1. **Start.** The region's principal axes against the mesh's, under each of the 24 proper
   rotations that map axes onto axes (signs and order: a component's axes can be near equal,
   and a box that cuts a tray's stem turns the region's), each fitted coarsely first.
2. **Cost.** Points on the mesh's surface against the distance map of the region's surface.
   The map is linearly interpolated, and a robust (soft L1, 1 mm) least-squares problem over
   the rotation vector and translation is solved from the best three coarse fits
   (scipy.optimize.least_squares). Points outside the scan's grid, whose metal it does not
   see, are left out.
3. **Check.** The mean distance of the surface to the metal's, and the region's volume over
   the mesh's. A mesh that is not the component in the scan (wrong component or size) is
   refused, naming its file and both figures.
4. **Side.** The mesh's mirror image is fitted to the same region. A component of the other
   side fits a nearly symmetric design almost as well as the right one (the simulated femoral
   component mirrored: 1.07 mm against 0.69 through NMAR), within the check above; its mirror
   image, the right one, fits clearly better, and the mesh is refused, naming both distances.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from scipy import ndimage
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from recon.volume import VolumeGrid

SURFACE_POINTS = 3000
"""Points of a mesh's surface the fit uses."""
MAX_SURFACE_DISTANCE_VOXELS = 1.75
"""A placed mesh's surface lies within this many voxels of the metal's on average (measured
on the simulated knee replacement through NMAR at 0.8 mm: 0.68 mm for the femoral component,
1.09 for the tray; the femoral component 10 % too large: 1.69)."""
VOLUME_RATIO = (0.7, 1.6)
"""The metal region's volume over the mesh's (NMAR's metal is the component grown by its
blur: 1.26-1.37 measured; the femoral component 10 % too small: 1.87)."""
COARSE_POINTS = 300
"""The points every start is first fitted with."""
COARSE_EVALUATIONS = 60
"""The most evaluations of the cost a start's first fit takes."""
STARTS_REFINED = 3
"""The best starts after that refined with every point."""
FORWARD_STEP = float(np.sqrt(np.finfo(float).eps))
"""Relative step of the fit's forward differences (scipy's for '2-point')."""
MARGIN_MM = 15.0
"""The distance map reaches this far beyond the region."""
MIRROR_BETTER = 0.9
"""A mesh whose mirror image lies at most this fraction of its own mean surface distance from
the metal is of the other side; a symmetric design, whose mirror image fits as well, passes.
Measured on the simulated knee replacement, mirror image over own: through NMAR at 0.8 mm
(90 views), 1.56 for the femoral component and 1.21 for the tray, so 0.64 and 0.82 for
components of the other side; on the truth's metal 2.0 and 1.38."""
MIRROR = np.diag([-1.0, 1.0, 1.0])
"""A reflection of a mesh's frame (any one will do: the fit finds the rotation)."""


@dataclass(frozen=True)
class Placement:
    """A component placed in the static scan.

    Attributes:
        body: The tracked body it stands for (femur, tibia, patella).
        path: Its mesh file.
        T_world_body: Its mesh's frame in the world (4x4, mm).
        surface_distance_mm: The mean distance of its surface to the metal's, mm.
        volume_ratio: The metal region's volume over the mesh's.
    """

    body: str
    path: str
    T_world_body: np.ndarray
    surface_distance_mm: float
    volume_ratio: float


def _axes(points: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Centroid and principal axes (columns, largest spread first) of weighted points."""
    w = np.ones(len(points)) if weights is None else weights
    centre = (w[:, None] * points).sum(axis=0) / w.sum()
    d = points - centre
    return centre, _right_handed(np.linalg.eigh((w[:, None] * d).T @ d / w.sum())[1][:, ::-1])


def _right_handed(axes: np.ndarray) -> np.ndarray:
    """``axes`` (columns) with the last reversed if they form a left-handed frame, so that the
    fit's starts (:data:`AXIS_ROTATIONS` between two such frames) are rotations."""
    return axes * [1.0, 1.0, -1.0] if np.linalg.det(axes) < 0 else axes


def _rotations() -> tuple[np.ndarray, ...]:
    """The 24 proper rotations that map the coordinate axes onto themselves."""
    out = []
    for order in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            m = np.zeros((3, 3))
            m[list(order), range(3)] = signs
            if np.linalg.det(m) > 0:
                out.append(m)
    return tuple(out)


AXIS_ROTATIONS = _rotations()
"""The 24 proper rotations that map the coordinate axes onto themselves (the fit's starts)."""


class _RegionFit:
    """A metal region's surface distance map, and the fit of a mesh's points to it."""

    def __init__(self, region: np.ndarray, grid: VolumeGrid) -> None:
        spacing = np.asarray(grid.spacing_mm[::-1])
        pad = np.ceil(MARGIN_MM / spacing).astype(int)
        box = ndimage.find_objects(region.astype(np.int8))[0]
        lo = [max(s.start - p, 0) for s, p in zip(box, pad, strict=True)]
        hi = [min(s.stop + p, n) for s, p, n in zip(box, pad, region.shape, strict=True)]
        crop = region[tuple(slice(a, b) for a, b in zip(lo, hi, strict=True))]
        surface = crop & ~ndimage.binary_erosion(crop)
        self.distance = ndimage.distance_transform_edt(~surface, sampling=spacing)
        self.low_zyx = np.asarray(lo)
        self.grid = grid
        self.volume_mm3 = float(region.sum()) * grid.voxel_volume_mm3
        k, j, i = np.nonzero(region)
        self.centre, self.axes = _axes(grid.index_to_world(np.column_stack((i, j, k))))

    def _indices(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The points' voxel indices (3, N) [z, y, x], and which of them the scan's grid holds."""
        zyx = self.grid.world_to_index(points_world)[:, ::-1].T
        seen = np.all((zyx >= -0.5) & (zyx <= np.asarray(self.grid.shape)[:, None] - 0.5), axis=0)
        return zyx, seen

    def distances(self, points_world: np.ndarray) -> np.ndarray:
        """The distance of each point to the region's surface (linear interpolation; a point
        off the map takes the map's largest value, one outside the scan's grid, where its
        metal is not seen, 0), mm."""
        zyx, seen = self._indices(points_world)
        d = ndimage.map_coordinates(
            self.distance,
            zyx - self.low_zyx[:, None],
            order=1,
            mode="constant",
            cval=float(self.distance.max()),
        )
        return np.where(seen, d, 0.0)

    def mean_distance(self, points_world: np.ndarray) -> float:
        """The mean distance of the points the scan sees to the region's surface, mm (inf if
        it sees under half of them)."""
        seen = self._indices(points_world)[1]
        if seen.mean() < 0.5:
            return float("inf")
        return float(self.distances(points_world)[seen].mean())

    def fit(
        self, points: np.ndarray, centre: np.ndarray, axes: np.ndarray
    ) -> tuple[np.ndarray, float]:
        """The best pose of ``points`` (mesh frame) in the region, and its mean distance."""

        def pose(x: np.ndarray) -> np.ndarray:
            T = np.eye(4)
            T[:3, :3] = Rotation.from_rotvec(x[:3]).as_matrix()
            T[:3, 3] = x[3:]
            return T

        def moved(x: np.ndarray, p: np.ndarray) -> np.ndarray:
            T = pose(x)
            return p @ T[:3, :3].T + T[:3, 3]

        def jacobian(x: np.ndarray, p: np.ndarray) -> np.ndarray:
            """Forward differences of the distances (scipy's '2-point' steps), the point set at
            ``x`` and its six moves looked up in the map at once."""
            steps = FORWARD_STEP * np.where(x >= 0, 1.0, -1.0) * np.maximum(1.0, np.abs(x))
            steps = (x + steps) - x  # exactly representable
            at = [moved(x + d, p) for d in np.vstack((np.zeros(6), np.diag(steps)))]
            here, *there = self.distances(np.concatenate(at)).reshape(7, len(p))
            return ((np.array(there) - here) / steps[:, None]).T

        def fitted(p: np.ndarray, x0: np.ndarray, evaluations: int | None) -> np.ndarray:
            return least_squares(
                lambda x: self.distances(moved(x, p)),
                x0,
                jac=lambda x: jacobian(x, p),
                loss="soft_l1",
                f_scale=1.0,
                max_nfev=evaluations,
            ).x

        coarse = points[:: max(1, len(points) // COARSE_POINTS)]
        starts = []
        for flip in AXIS_ROTATIONS:
            R = self.axes @ flip @ axes.T
            x = np.concatenate((Rotation.from_matrix(R).as_rotvec(), self.centre - R @ centre))
            x = fitted(coarse, x, COARSE_EVALUATIONS)
            starts.append((self.mean_distance(moved(x, coarse)), x))
        starts.sort(key=lambda s: s[0])
        best_x, best = None, np.inf
        for _, x0 in starts[:STARTS_REFINED]:
            x = fitted(points, x0, None)
            mean = self.mean_distance(moved(x, points))
            if mean < best:
                best_x, best = x, mean
        return pose(best_x), best


def place_components(
    meshes: dict[str, tuple[trimesh.Trimesh, Path | str]],
    metal: np.ndarray,
    grid: VolumeGrid,
) -> dict[str, Placement]:
    """Place each component's mesh on the metal of a static scan.

    Args:
        meshes: Body -> (its component's closed mesh in mm, its file).
        metal: The scan's metal, bool [z, y, x] (recon.mar's mask).
        grid: The scan's grid.

    Returns:
        Body -> its placement.

    Raises:
        ValueError: fewer metal regions than meshes, or a mesh that does not fit its metal
            (naming the file, the distance and the volume ratio measured).
    """
    regions, n = ndimage.label(np.asarray(metal, dtype=bool))
    if n < len(meshes):
        raise ValueError(
            f"the scan's metal has {n} separate region(s) for {len(meshes)} component(s)"
        )
    fits = [_RegionFit(regions == k, grid) for k in range(1, n + 1)]
    tolerance = MAX_SURFACE_DISTANCE_VOXELS * max(grid.spacing_mm)
    placed: dict[str, Placement] = {}
    free = set(range(n))
    for body, (mesh, path) in sorted(meshes.items(), key=lambda item: -item[1][0].volume):
        points = np.asarray(
            mesh.vertices[:: max(1, len(mesh.vertices) // SURFACE_POINTS)], dtype=float
        )
        centre, axes = _axes(np.asarray(mesh.triangles_center), np.asarray(mesh.area_faces))
        candidates = [k for k in free if fits[k].volume_mm3 >= 0.5 * mesh.volume]
        if not candidates:
            raise ValueError(f"{path}: no metal region left of half its volume ({body})")
        trials = [(fits[k].fit(points, centre, axes), k) for k in candidates]
        (T, distance), k = min(trials, key=lambda t: t[0][1])
        ratio = fits[k].volume_mm3 / float(mesh.volume)
        if distance > tolerance or not VOLUME_RATIO[0] <= ratio <= VOLUME_RATIO[1]:
            raise ValueError(
                f"{path} ({body}) does not fit the scan's metal: its surface lies "
                f"{distance:.2f} mm from the metal's on average (at most {tolerance:.2f}), "
                f"the metal region holds {ratio:.2f} x its volume (expected "
                f"{VOLUME_RATIO[0]:g}-{VOLUME_RATIO[1]:g}): the wrong component, size or side?"
            )
        mirrored = (points @ MIRROR, MIRROR @ centre, _right_handed(MIRROR @ axes))
        _, other_side = fits[k].fit(*mirrored)
        if other_side <= MIRROR_BETTER * distance:
            raise ValueError(
                f"{path} ({body}) fits the scan's metal better mirrored: its surface lies "
                f"{distance:.2f} mm from the metal's on average, its mirror image's "
                f"{other_side:.2f} (at most {MIRROR_BETTER:g} x is the other side): a "
                "component of the other side?"
            )
        free.discard(k)
        placed[body] = Placement(body, str(path), T, distance, ratio)
    return placed
