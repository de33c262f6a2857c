"""Patient motion during a scan, as FDK compensates it: per-view rigid poses of a few bodies
blended into a smooth motion field, its backprojector, and its file.

A scan's motion is ``T_world_body`` per view and body (4x4, mm): where the body, reconstructed
in its reference pose, stood when the view was taken. One body moving rigidly is compensated
exactly by reconstructing through the views carried by ``inv(T)``. Several bodies (the thigh
and the shank of a standing patient) move apart; between them the tissue follows a blend: each
voxel ``x`` has weights ``w_b(x)`` (a partition of unity, smooth across the joint) and stood
at ``sum_b w_b(x) T_b x`` in view ``i``, so it projects through ``P_i`` there. As ``P`` is linear
in homogeneous coordinates this is ``sum_b w_b(x) (P_i T_b) x``: per voxel, a blend of the
bodies' moved matrices, which :func:`backproject_field` evaluates in the FDK backprojection.

File (``<volume>_motion.csv``): one row per view and body, ``view,body,t00,...,t33``, the 4x4
``T_world_body`` row-major.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numba
import numpy as np

from recon.geometry import Geometry
from recon.project import pixel_quads
from recon.volume import VolumeGrid

MOTION_COLUMNS = ("view", "body", *(f"t{r}{c}" for r in range(4) for c in range(4)))
"""The motion file's header."""


@dataclass(frozen=True)
class BodyMotion:
    """Per-view rigid poses of the bodies of a scan, and how they blend on a grid.

    Attributes:
        bodies: body names (K,).
        poses: ``T_world_body`` per view and body, (N, K, 4, 4), mm.
        weights: float32 (K, nz, ny, nx), each voxel's share of each body (summing to 1), on
            ``grid``; None for one body (and for a record of poses alone, e.g. a
            simulation's truth, which FDK cannot compensate).
        grid: the grid of ``weights``.
    """

    bodies: tuple[str, ...]
    poses: np.ndarray
    weights: np.ndarray | None = None
    grid: VolumeGrid | None = None

    def __post_init__(self) -> None:
        poses = np.asarray(self.poses, dtype=np.float64)
        k = len(self.bodies)
        if poses.ndim != 4 or poses.shape[1:] != (k, 4, 4):
            raise ValueError(f"poses must be (views, {k}, 4, 4), got {poses.shape}")
        if not np.isfinite(poses).all():
            raise ValueError("poses contain NaN or infinite values")
        if (self.weights is None) != (self.grid is None):
            raise ValueError("weights and their grid come together")
        if self.weights is not None and self.weights.shape != (k, *self.grid.shape):
            raise ValueError(f"weights must be ({k}, *{self.grid.shape}), got {self.weights.shape}")
        object.__setattr__(self, "poses", poses)

    def __len__(self) -> int:
        return len(self.poses)

    def on(self, grid: VolumeGrid) -> np.ndarray:
        """The weights resampled onto ``grid`` (trilinear, held at the edges), (K, *shape)."""
        if self.weights is None:
            if len(self.bodies) > 1:
                raise ValueError(f"{len(self.bodies)} bodies without weights cannot be blended")
            return np.ones((1, *grid.shape), np.float32)
        if grid == self.grid:
            return self.weights
        from scipy import ndimage

        zyx = [
            (np.asarray(a) - o) / s
            for a, o, s in zip(
                grid.axes_mm()[::-1],
                self.grid.origin_mm[::-1],
                self.grid.spacing_mm[::-1],
                strict=True,
            )
        ]
        coords = np.meshgrid(*zyx, indexing="ij")
        out = np.stack(
            [ndimage.map_coordinates(w, coords, order=1, mode="nearest") for w in self.weights]
        )
        return (out / np.maximum(out.sum(axis=0), 1e-6)).astype(np.float32)

    def displacement_mm(self, points: dict[str, np.ndarray]) -> np.ndarray:
        """Displacement of each body's points (world mm, reference pose) per view, (N, K):
        the largest over the body's points."""
        out = np.zeros((len(self), len(self.bodies)))
        for k, body in enumerate(self.bodies):
            p = np.asarray(points[body], dtype=np.float64)
            moved = (
                np.einsum("nij,pj->npi", self.poses[:, k, :3, :3], p)
                + self.poses[:, k, None, :3, 3]
            )
            out[:, k] = np.linalg.norm(moved - p[None], axis=2).max(axis=1)
        return out


def write_motion_csv(path: Path, motion: BodyMotion) -> Path:
    """Write ``view,body,t00..t33`` rows (:data:`MOTION_COLUMNS`)."""
    with open(path, "w", newline="", encoding="utf-8") as f:
        out = csv.writer(f)
        out.writerow(MOTION_COLUMNS)
        for i, per_view in enumerate(motion.poses):
            for body, T in zip(motion.bodies, per_view, strict=True):
                out.writerow([i, body, *(f"{v:.9g}" for v in T.ravel())])
    return Path(path)


def read_motion_csv(path: Path) -> tuple[tuple[str, ...], np.ndarray]:
    """The bodies and the poses (N, K, 4, 4) of a motion file; ValueError naming the row of
    a malformed one."""
    with open(path, newline="", encoding="utf-8") as f:
        rows = list(csv.reader(f))
    if not rows or tuple(rows[0]) != MOTION_COLUMNS:
        raise ValueError(f"{path}: the header must be {','.join(MOTION_COLUMNS)}")
    bodies: list[str] = []
    poses: dict[tuple[int, str], np.ndarray] = {}
    for n, row in enumerate(rows[1:], start=2):
        try:
            view, body, values = int(row[0]), row[1], np.array(row[2:], dtype=np.float64)
        except (ValueError, IndexError) as err:
            raise ValueError(f"{path}, row {n}: {err}") from None
        if values.shape != (16,) or not np.isfinite(values).all():
            raise ValueError(f"{path}, row {n}: 16 finite numbers expected")
        if body not in bodies:
            bodies.append(body)
        poses[(view, body)] = values.reshape(4, 4)
    views = sorted({v for v, _ in poses})
    if views != list(range(len(views))):
        raise ValueError(f"{path}: views must run 0..N-1 without gaps")
    missing = [(v, b) for v in views for b in bodies if (v, b) not in poses]
    if missing:
        raise ValueError(f"{path}: no pose for view {missing[0][0]}, body {missing[0][1]}")
    return tuple(bodies), np.array([[poses[(v, b)] for b in bodies] for v in views])


def moved_matrices(geometry: Geometry, poses: np.ndarray) -> np.ndarray:
    """``P_i T_ib`` per view and body, (N, K, 3, 4): the view matrices that place each body."""
    return np.einsum("nrk,nbkc->nbrc", geometry.matrices, poses)


@numba.njit(parallel=True, fastmath=True, cache=True, error_model="numpy", nogil=True)
def _field_kernel(quads, scale, mats, weights, origin, spacing, out):  # pragma: no cover
    """out[z, y, x] += sum over views of scale * bilinear(image) / w^2 at the blended
    projection ``sum_b weights[b, z, y, x] * mats[view, b] @ (x, y, z, 1)``, 0 off the panel;
    the images as recon.project.pixel_quads, (views, rows, cols, 4)."""
    n_views, rows, cols = quads.shape[:3]
    n_bodies = mats.shape[1]
    nz, ny, nx = out.shape
    umax = np.float32(cols - 1.0)
    vmax = np.float32(rows - 1.0)
    for job in numba.prange(nz * ny):
        z = job // ny
        y = job - z * ny
        wz = origin[2] + z * spacing[2]
        wy = origin[1] + y * spacing[1]
        acc = np.zeros(nx, dtype=np.float32)
        h = np.empty((n_bodies, 3), dtype=np.float32)
        s = np.empty((n_bodies, 3), dtype=np.float32)
        for view in range(n_views):
            image = quads[view]
            sc = scale[view]
            for b in range(n_bodies):
                m = mats[view, b]
                for r in range(3):
                    h[b, r] = m[r, 0] * origin[0] + m[r, 1] * wy + m[r, 2] * wz + m[r, 3]
                    s[b, r] = m[r, 0] * spacing[0]
            for x in range(nx):
                xf = np.float32(x)
                pu = np.float32(0.0)
                pv = np.float32(0.0)
                pw = np.float32(0.0)
                for b in range(n_bodies):
                    wb = weights[b, z, y, x]
                    pu += wb * (h[b, 0] + xf * s[b, 0])
                    pv += wb * (h[b, 1] + xf * s[b, 1])
                    pw += wb * (h[b, 2] + xf * s[b, 2])
                inv = np.float32(1.0) / pw
                u = pu * inv
                v = pv * inv
                if u < 0 or v < 0 or u > umax or v > vmax:
                    continue
                iu = min(np.int32(u), np.int32(cols - 2))
                iv = min(np.int32(v), np.int32(rows - 2))
                fu = u - np.float32(iu)
                fv = v - np.float32(iv)
                q = image[iv, iu]
                r0 = q[0] + fu * (q[1] - q[0])
                r1 = q[2] + fu * (q[3] - q[2])
                acc[x] += (r0 + fv * (r1 - r0)) * inv * inv * sc
        for x in range(nx):
            out[z, y, x] += acc[x]


def backproject_field(
    images: np.ndarray,
    geometry: Geometry,
    grid: VolumeGrid,
    poses: np.ndarray,
    weights: np.ndarray,
    out: np.ndarray,
    scale: np.ndarray | None = None,
) -> None:
    """Accumulate FDK-weighted (``1/w^2``) backprojections of ``images`` through a motion field.

    Args:
        images: float32 (N, rows, cols), one per view of ``geometry``, or their
            recon.project.pixel_quads (N, rows, cols, 4).
        geometry: the views.
        grid: the grid of ``out`` and ``weights``.
        poses: ``T_world_body`` per view and body, (N, K, 4, 4).
        weights: float32 (K, nz, ny, nx), each voxel's share of each body.
        out: float32 volume on ``grid``, added to.
        scale: per-view factors (N,), default 1.
    """
    if out.shape != grid.shape or out.dtype != np.float32:
        raise ValueError(f"out must be float32 of shape {grid.shape}")
    quads = np.asarray(images)
    if quads.shape[:3] != (len(geometry), geometry.rows, geometry.cols):
        raise ValueError(f"images of shape {quads.shape} for {len(geometry)} views")
    if geometry.rows < 2 or geometry.cols < 2:
        raise ValueError("the panel needs at least 2 x 2 pixels")
    if quads.ndim == 3:
        quads = pixel_quads(quads)
    _field_kernel(
        np.ascontiguousarray(quads, dtype=np.float32),
        np.ones(len(geometry), np.float32) if scale is None else np.asarray(scale, np.float32),
        moved_matrices(geometry, np.asarray(poses, dtype=np.float64)),
        np.ascontiguousarray(weights, dtype=np.float32),
        np.array(grid.origin_mm),
        np.array(grid.spacing_mm),
        out,
    )


def read_view_times(path: Path) -> np.ndarray:
    """Per-view times (s) from a CSV's ``clock_s`` or ``time_s`` column, in row order;
    ValueError naming the file and the row of a bad one."""
    with open(path, newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    column = next((c for c in ("clock_s", "time_s") if rows and c in rows[0]), None)
    if column is None:
        raise ValueError(f"{path}: no clock_s or time_s column (one time per view, s)")
    times = []
    for n, row in enumerate(rows, start=2):
        try:
            times.append(float(row[column]))
        except (TypeError, ValueError):
            raise ValueError(f"{path}, row {n}: {column} {row[column]!r} is not a time") from None
    return np.array(times)
