"""Volumes in world coordinates: an axis-aligned voxel grid and a value array on it.

Arrays are indexed ``[z, y, x]``; spacing and origin are given in ``(x, y, z)`` order like ITK,
the origin being the centre of voxel ``[0, 0, 0]``. The world frame is DICOM/ITK LPS
(docs/conventions.md), and grids are axis-aligned in it (identity direction).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

Unit = Literal["1/mm", "HU", "label"]
"""What a volume's values are: linear attenuation (1/mm), Hounsfield units or labels."""


def _triple(name: str, value, positive: bool = False) -> tuple[float, float, float]:
    arr = np.asarray(value, dtype=np.float64).reshape(-1)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be 3 finite numbers (x, y, z), got {value!r}")
    if positive and np.any(arr <= 0):
        raise ValueError(f"{name} must be > 0 mm on every axis, got {arr.tolist()}")
    return tuple(float(x) for x in arr)


@dataclass(frozen=True)
class VolumeGrid:
    """Axis-aligned voxel grid in world mm.

    Attributes:
        shape: voxels (nz, ny, nx), the array's shape.
        spacing_mm: voxel size (sx, sy, sz), mm.
        origin_mm: world position of the centre of voxel [0, 0, 0], (x, y, z) mm.
    """

    shape: tuple[int, int, int]
    spacing_mm: tuple[float, float, float]
    origin_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        shape = tuple(int(n) for n in self.shape)
        if len(shape) != 3 or any(n <= 0 for n in shape) or shape != tuple(self.shape):
            raise ValueError(f"shape must be 3 positive integers (nz, ny, nx), got {self.shape!r}")
        object.__setattr__(self, "shape", shape)
        object.__setattr__(self, "spacing_mm", _triple("spacing_mm", self.spacing_mm, True))
        object.__setattr__(self, "origin_mm", _triple("origin_mm", self.origin_mm))

    @classmethod
    def centered(
        cls,
        size_xyz: Sequence[int],
        spacing_mm: float | Sequence[float],
        center_mm: Sequence[float] = (0.0, 0.0, 0.0),
    ) -> VolumeGrid:
        """Grid of ``size_xyz`` = (nx, ny, nz) voxels whose centre lies at ``center_mm``.

        Examples:
            >>> grid = VolumeGrid.centered((4, 3, 2), 0.5, (0.0, 0.0, 480.0))
            >>> grid.shape, grid.origin_mm  # arrays are [z, y, x]; the first voxel's centre
            ((2, 3, 4), (-0.75, -0.5, 479.75))
        """
        nx, ny, nz = (int(n) for n in size_xyz)
        spacing = _triple(
            "spacing_mm",
            [spacing_mm] * 3 if np.isscalar(spacing_mm) else spacing_mm,
            positive=True,
        )
        center = _triple("center_mm", center_mm)
        origin = tuple(
            c - 0.5 * (n - 1) * s for c, n, s in zip(center, (nx, ny, nz), spacing, strict=True)
        )
        return cls(shape=(nz, ny, nx), spacing_mm=spacing, origin_mm=origin)

    @property
    def size_xyz(self) -> tuple[int, int, int]:
        """Voxels along (x, y, z)."""
        return self.shape[2], self.shape[1], self.shape[0]

    def __str__(self) -> str:
        """The grid in a user's words, x y z order: voxels, their size, the first's centre."""
        size = " x ".join(str(n) for n in self.size_xyz)
        spacing = " x ".join(f"{s:g}" for s in self.spacing_mm)
        origin = ", ".join(f"{o:g}" for o in self.origin_mm)
        return f"{size} voxels (x y z) of {spacing} mm, the first centred at ({origin}) mm"

    @property
    def center_mm(self) -> np.ndarray:
        """World position of the grid centre, (x, y, z) mm."""
        return np.array(
            [
                o + 0.5 * (n - 1) * s
                for o, n, s in zip(self.origin_mm, self.size_xyz, self.spacing_mm, strict=True)
            ]
        )

    @property
    def voxel_volume_mm3(self) -> float:
        return math.prod(self.spacing_mm)

    def axes_mm(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World coordinates of voxel centres along x, y and z (three 1-D arrays)."""
        return tuple(
            o + s * np.arange(n)
            for o, s, n in zip(self.origin_mm, self.spacing_mm, self.size_xyz, strict=True)
        )

    def corners_mm(self) -> np.ndarray:
        """The 8 outer corners of the grid (voxel edges, not centres), world mm (8, 3)."""
        lo = np.array(self.origin_mm) - 0.5 * np.array(self.spacing_mm)
        hi = lo + np.array(self.size_xyz) * np.array(self.spacing_mm)
        return np.array(
            [[x, y, z] for z in (lo[2], hi[2]) for y in (lo[1], hi[1]) for x in (lo[0], hi[0])]
        )

    def world_to_index(self, points_mm: np.ndarray) -> np.ndarray:
        """Continuous voxel indices (i_x, i_y, i_z) of world points.

        Args:
            points_mm: World points (mm), shape (..., 3).

        Returns:
            Voxel indices (voxels; 0 at the first voxel's centre), shape (..., 3).

        Examples:
            >>> grid = VolumeGrid.centered((4, 3, 2), 0.5)
            >>> grid.world_to_index([0.0, 0.0, 0.0]).tolist()  # the centre, between voxels
            [1.5, 1.0, 0.5]
        """
        return (np.asarray(points_mm, dtype=np.float64) - self.origin_mm) / self.spacing_mm

    def index_to_world(self, index_xyz: np.ndarray) -> np.ndarray:
        """World points of continuous voxel indices (i_x, i_y, i_z).

        Args:
            index_xyz: Voxel indices (voxels; 0 at the first voxel's centre), shape (..., 3).

        Returns:
            World points (mm), shape (..., 3).
        """
        return np.asarray(index_xyz, dtype=np.float64) * self.spacing_mm + self.origin_mm


@dataclass(frozen=True)
class Volume:
    """Values on a grid: ``data`` indexed [z, y, x] with ``unit`` stated."""

    data: np.ndarray
    grid: VolumeGrid
    unit: Unit = "1/mm"

    def __post_init__(self) -> None:
        if tuple(self.data.shape) != self.grid.shape:
            raise ValueError(
                f"data shape {self.data.shape} does not match grid shape {self.grid.shape}"
            )
        if self.unit not in ("1/mm", "HU", "label"):
            raise ValueError(f"unit must be '1/mm', 'HU' or 'label', got {self.unit!r}")
