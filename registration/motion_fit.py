"""The per-view fit of a patient's motion during a scan: every view's rigid pose of each body
(6 parameters each: a rotation vector about the body's centre and a translation of it), by
Gauss-Newton on the line integrals against a volume split into bodies (registration.scan_motion
estimates the motion with it)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.spatial.transform import Rotation

from recon.geometry import Geometry
from recon.project import JosephProjector, row_spans
from recon.volume import VolumeGrid

STEP = np.array([0.3, 0.3, 0.3, *np.radians([0.3, 0.3, 0.3])])
"""Finite-difference steps of the six parameters: mm, and radians."""
LEVER_MM = 50.0
"""Rotations are damped as the displacement they cause this far from the body's centre."""
DAMPING = 1e-6
"""Levenberg-Marquardt damping, relative to the mean of the normal matrix's diagonal."""


def pose_of(theta: np.ndarray, center: np.ndarray) -> np.ndarray:
    """4x4 rigid motion of 6 parameters: a rotation vector (rad) about ``center`` and a
    translation of it (mm)."""
    T = np.eye(4)
    R = Rotation.from_rotvec(theta[3:]).as_matrix()
    T[:3, :3] = R
    T[:3, 3] = center + theta[:3] - R @ center
    return T


def params_of(T: np.ndarray, center: np.ndarray) -> np.ndarray:
    """The 6 parameters of :func:`pose_of` of ``T``."""
    R = T[:3, :3]
    return np.concatenate((T[:3, 3] - center + R @ center, Rotation.from_matrix(R).as_rotvec()))


def recentred(poses: np.ndarray, centers: np.ndarray) -> np.ndarray:
    """Poses (N, K, 4, 4) moved so that each body's mean pose is the identity: the volume
    reconstructed through them shows the patient's average pose."""
    out = np.empty_like(poses)
    for k in range(poses.shape[1]):
        mean = np.mean([params_of(T, centers[k]) for T in poses[:, k]], axis=0)
        out[:, k] = poses[:, k] @ np.linalg.inv(pose_of(mean, centers[k]))
    return out


def cropped(volume: np.ndarray, grid: VolumeGrid) -> tuple[np.ndarray, VolumeGrid]:
    """The slab of axial slices holding any non-zero voxel (a body's part of the volume)."""
    filled = np.flatnonzero(np.abs(volume).max(axis=(1, 2)) > 0)
    if filled.size == 0:
        return volume[:2], VolumeGrid((2, *grid.shape[1:]), grid.spacing_mm, grid.origin_mm)
    z0, z1 = max(int(filled[0]) - 2, 0), min(int(filled[-1]) + 3, volume.shape[0])
    origin = np.asarray(grid.origin_mm) + np.array([0.0, 0.0, z0 * grid.spacing_mm[2]])
    sub = VolumeGrid((z1 - z0, *grid.shape[1:]), grid.spacing_mm, tuple(origin))
    return np.ascontiguousarray(volume[z0:z1]), sub


class ViewFit:
    """Gauss-Newton of every view's body poses against one volume split into bodies."""

    def __init__(
        self,
        volume: np.ndarray,
        grid: VolumeGrid,
        weights: np.ndarray,
        centers: np.ndarray,
        projections: np.ndarray,
        geometry: Geometry,
        trusted: np.ndarray,
    ) -> None:
        self.parts = [JosephProjector(*cropped(volume * w, grid)) for w in weights]
        self.centers, self.projections, self.geometry = centers, projections, geometry
        self.trusted = trusted
        self.spans = [row_spans(mask, 0) for mask in trusted]  # the rays fitted, alone traced

    def view(self, i: int, poses: np.ndarray, iterations: int) -> np.ndarray:
        """The poses (K, 4, 4) of view ``i`` fitted from ``poses``."""
        measured = self.projections[i][self.trusted[i]]
        k = len(self.parts)
        theta = np.concatenate([params_of(T, c) for T, c in zip(poses, self.centers, strict=True)])
        scale = np.tile(np.array([1.0, 1.0, 1.0, LEVER_MM, LEVER_MM, LEVER_MM]), k)
        for _ in range(iterations):
            base = [self._projection(b, i, theta[6 * b : 6 * b + 6]) for b in range(k)]
            residual = measured - sum(base)
            J = np.empty((residual.size, 6 * k), dtype=np.float64)
            for b in range(k):
                for j in range(6):
                    moved = theta[6 * b : 6 * b + 6].copy()
                    moved[j] += STEP[j]
                    image = self._projection(b, i, moved)
                    J[:, 6 * b + j] = (image - base[b]) / (STEP[j] * scale[6 * b + j])
            normal = J.T @ J
            normal[np.diag_indices_from(normal)] += DAMPING * np.trace(normal) / (6 * k)
            theta = theta + np.linalg.solve(normal, J.T @ residual) / scale
        return np.stack([pose_of(theta[6 * b : 6 * b + 6], self.centers[b]) for b in range(k)])

    def _projection(self, b: int, i: int, theta: np.ndarray) -> np.ndarray:
        """Body ``b``'s line integrals through view ``i``'s fitted pixels, at its parameters
        ``theta`` (6,)."""
        pose = pose_of(theta, self.centers[b])
        return self.parts[b].project_moved(self.geometry[i], pose, self.spans[i])[self.trusted[i]]

    def all_views(
        self,
        start: np.ndarray | None,
        iterations: int,
        progress: Callable[[int, int], None] | None,
    ) -> np.ndarray:
        """Every view's poses (N, K, 4, 4), each fitted from ``start``'s; with ``start`` None,
        the first from the identity and each next one from the view before it (the patient
        moves little between views)."""
        n, k = len(self.geometry), len(self.parts)
        out = np.empty((n, k, 4, 4))
        for i in range(n):
            if start is not None:
                first = start[i]
            else:
                first = out[i - 1] if i else np.tile(np.eye(4), (k, 1, 1))
            out[i] = self.view(i, first, iterations)
            if progress is not None:
                progress(i + 1, n)
        return out
