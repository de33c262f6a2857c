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
from recon.project import ROWS_PER_JOB, pixel_quads, quad_pairs, row_gather
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

    def of_views(self, index: np.ndarray) -> BodyMotion:
        """The same bodies and blend, on the views ``index`` alone."""
        return BodyMotion(self.bodies, self.poses[index], self.weights, self.grid)

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


@numba.njit(fastmath=True, error_model="numpy", boundscheck=False, inline="always")
def _blended_samples(n, pu, pv, pw, umax, vmax, cols, scale, idx, fu, fv, wt):  # pragma: no cover
    """Detector samples of a row's ``n`` voxels from their blended homogeneous projections
    ``(pu, pv, pw)``, for :func:`recon.project.row_gather`: weight ``scale / w^2`` on the
    panel, 0 off it (where the index is clamped onto it)."""
    zero = np.float32(0.0)
    for k in range(n):
        inv = np.float32(1.0) / pw[k]
        u = pu[k] * inv
        v = pv[k] * inv
        inside = (u >= zero) & (v >= zero) & (u <= umax) & (v <= vmax)
        u = min(max(u, zero), umax)
        v = min(max(v, zero), vmax)
        iu = min(np.int32(u), np.int32(cols - 2))
        iv = min(np.int32(v), np.int32(vmax - 1))
        fu[k] = u - np.float32(iu)
        fv[k] = v - np.float32(iv)
        idx[k] = np.uint32(iv * np.int32(cols) + iu)
        wt[k] = inv * inv * scale if inside else zero


@numba.njit(
    parallel=True, fastmath=True, cache=True, error_model="numpy", boundscheck=False, nogil=True
)
def _field_kernel(quads, scale, mats, weights, origin, spacing, out):  # pragma: no cover
    """out[z, y, x] += sum over views of scale * bilinear(image) / w^2 at the blended
    projection ``sum_b weights[b, z, y, x] * mats[view, b] @ (x, y, z, 1)``, 0 off the panel;
    the images as recon.project.quad_pairs, (views, rows, cols, 2). Rows
    are taken :data:`recon.project.ROWS_PER_JOB` at a time, view by view, as the plain
    backprojector takes them."""
    n_views, rows, cols = quads.shape[:3]
    n_bodies = mats.shape[1]
    nz, ny, nx = out.shape
    umax = np.float32(cols - 1.0)
    vmax = np.float32(rows - 1.0)
    flat = quads.reshape(n_views, rows * cols * 2)
    blocks = (ny + ROWS_PER_JOB - 1) // ROWS_PER_JOB
    for job in numba.prange(nz * blocks):
        z = job // blocks
        y0 = (job - z * blocks) * ROWS_PER_JOB
        y1 = min(ny, y0 + ROWS_PER_JOB)
        wz = origin[2] + z * spacing[2]
        acc = np.zeros((ROWS_PER_JOB, nx), dtype=np.float32)
        pu = np.empty(nx, dtype=np.float32)
        pv = np.empty(nx, dtype=np.float32)
        pw = np.empty(nx, dtype=np.float32)
        idx = np.zeros(nx + 1, dtype=np.uint32)  # any entry is a valid pixel index
        fu = np.empty(nx, dtype=np.float32)
        fv = np.empty(nx, dtype=np.float32)
        wt = np.empty(nx, dtype=np.float32)
        upper = np.empty(nx + 1, dtype=np.complex64)
        lower = np.empty(nx + 1, dtype=np.complex64)
        for view in range(n_views):
            image = flat[view]
            for y in range(y0, y1):
                wy = origin[1] + y * spacing[1]
                pu[:] = 0.0
                pv[:] = 0.0
                pw[:] = 0.0
                for b in range(n_bodies):
                    m = mats[view, b]
                    h0 = np.float32(m[0, 0] * origin[0] + m[0, 1] * wy + m[0, 2] * wz + m[0, 3])
                    h1 = np.float32(m[1, 0] * origin[0] + m[1, 1] * wy + m[1, 2] * wz + m[1, 3])
                    h2 = np.float32(m[2, 0] * origin[0] + m[2, 1] * wy + m[2, 2] * wz + m[2, 3])
                    s0 = np.float32(m[0, 0] * spacing[0])
                    s1 = np.float32(m[1, 0] * spacing[0])
                    s2 = np.float32(m[2, 0] * spacing[0])
                    share = weights[b, z, y]
                    xf = np.float32(0.0)  # a float counter vectorises better than converting x
                    for x in range(nx):
                        a = share[x]
                        pu[x] += a * (h0 + xf * s0)
                        pv[x] += a * (h1 + xf * s1)
                        pw[x] += a * (h2 + xf * s2)
                        xf += np.float32(1.0)
                _blended_samples(nx, pu, pv, pw, umax, vmax, cols, scale[view], idx, fu, fv, wt)
                row_gather(nx, image, idx, fu, fv, wt, upper, lower, acc[y - y0])
        for y in range(y0, y1):
            for x in range(nx):
                out[z, y, x] += acc[y - y0, x]


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
        quad_pairs(quads),
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
