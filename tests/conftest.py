"""Shared fixtures: small analytic phantoms that build in milliseconds."""

from __future__ import annotations

import numpy as np
import pytest

from recon.volume import VolumeGrid


def ball(
    grid: VolumeGrid, center_mm, radius_mm: float, value: float = 1.0, supersample: int = 3
) -> np.ndarray:
    """A ball rasterised with partial-volume (supersampled) edges, float32 [z, y, x]."""
    out = np.zeros(grid.shape, dtype=np.float32)
    x, y, z = grid.axes_mm()
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    cx, cy, cz = center_mm
    for ox in offsets:
        for oy in offsets:
            for oz in offsets:
                dx = (x + ox * grid.spacing_mm[0] - cx) ** 2
                dy = (y + oy * grid.spacing_mm[1] - cy) ** 2
                dz = (z + oz * grid.spacing_mm[2] - cz) ** 2
                out += (dz[:, None, None] + dy[None, :, None] + dx[None, None, :]) < radius_mm**2
    return out * np.float32(value / supersample**3)


def cylinder(
    grid: VolumeGrid,
    center_mm,
    radius_mm: float,
    half_height_mm: float,
    value: float = 1.0,
    supersample: int = 3,
) -> np.ndarray:
    """An upright (z) cylinder with partial-volume edges, float32 [z, y, x]."""
    out = np.zeros(grid.shape, dtype=np.float32)
    x, y, z = grid.axes_mm()
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    cx, cy, cz = center_mm
    for ox in offsets:
        for oy in offsets:
            r2 = (x[None, :] + ox * grid.spacing_mm[0] - cx) ** 2 + (
                y[:, None] + oy * grid.spacing_mm[1] - cy
            ) ** 2
            inside_xy = r2 < radius_mm**2
            for oz in offsets:
                inside_z = np.abs(z + oz * grid.spacing_mm[2] - cz) < half_height_mm
                out += inside_z[:, None, None] & inside_xy[None, :, :]
    return out * np.float32(value / supersample**3)


@pytest.fixture(scope="session")
def make_ball():
    return ball


@pytest.fixture(scope="session")
def make_cylinder():
    return cylinder
