"""recon.ramp: FDK's row filtering (two rows per complex FFT) against a direct convolution,
and the panel rows FDK keeps (recon.fdk.rows_seen) against every voxel's projection."""

from __future__ import annotations

import numpy as np
import pytest

from recon.fdk import ramp_filter_response, rows_seen
from recon.geometry import DetectorSpec, circular_orbit, helical_orbit
from recon.ramp import RowFilter
from recon.volume import VolumeGrid


def ram_lak_kernel(cols: int) -> np.ndarray:
    """The spatial band-limited ramp (Kak & Slaney eq. 61, unit pitch), taps -cols+1..cols-1."""
    n = np.arange(-cols + 1, cols)
    h = np.zeros(n.size)
    h[n == 0] = 0.25
    odd = n % 2 == 1
    h[odd] = -1.0 / (np.pi * n[odd]) ** 2
    return h


@pytest.mark.parametrize("rows", [6, 7])  # an odd row count leaves the last one unpaired
def test_rows_are_weighted_filtered_and_paired_as_a_direct_convolution(rows):
    """Each output row is the linear convolution of its weighted row with the spatial Ram-Lak
    kernel, then times the support; each pixel's quad holds it, its right-hand neighbour and
    the two below them (0 past the last column and row). float32 FFTs of 128 points: agreement
    to 1e-5 of the row's largest value."""
    rng = np.random.default_rng(3)
    n, cols = 3, 40
    images = rng.random((n, rows, cols), dtype=np.float32)
    panels = np.array([(900.0 + 50 * k, 17.3, 2.4 + k, 0.8, 0.6) for k in range(n)])
    scale = np.array([0.5, 1.0, 2.0], np.float32)
    columns = rng.random((n, cols), dtype=np.float32)
    support = rng.random((1, rows, cols), dtype=np.float32)
    response = ramp_filter_response(128, 1.0, "ram-lak", 1.0)

    quads = RowFilter(cols, response)(images, panels, scale, support, columns)

    h = ram_lak_kernel(cols)
    assert quads.shape == (n, rows, cols, 4)
    for k in range(n):
        d, u0, v0, pu, pv = panels[k]
        du = (np.arange(cols) - u0) * pu
        dv = (np.arange(rows) - v0) * pv
        cosine = d / np.sqrt(d**2 + du[None, :] ** 2 + dv[:, None] ** 2)
        weighted = images[k] * cosine * scale[k] * columns[k]
        filtered = np.zeros((rows + 1, cols + 1))
        for r in range(rows):
            filtered[r, :cols] = np.convolve(weighted[r], h)[cols - 1 : 2 * cols - 1]
        filtered[:rows, :cols] *= support[0]
        tol = 1e-5 * np.abs(filtered).max()
        np.testing.assert_allclose(quads[k, ..., 0], filtered[:-1, :-1], atol=tol)
        np.testing.assert_allclose(quads[k, ..., 1], filtered[:-1, 1:], atol=tol)
        np.testing.assert_allclose(quads[k, ..., 2], filtered[1:, :-1], atol=tol)
        np.testing.assert_allclose(quads[k, ..., 3], filtered[1:, 1:], atol=tol)
        assert not quads[k, -1, :, 2:].any() and not quads[k, :, -1, 1::2].any()


def test_a_ramp_shorter_than_twice_the_row_is_refused():
    with pytest.raises(ValueError, match="wraps around"):
        RowFilter(100, ramp_filter_response(128, 1.0, "ram-lak", 1.0))


@pytest.mark.parametrize(
    "orbit",
    [
        lambda panel: circular_orbit(24, 600, 1000, panel, isocenter_mm=(0, 0, 30)),
        lambda panel: helical_orbit(
            24, 600, 1000, panel, 360, -60, 60, passes=2, isocenter_mm=(0, 0, 30)
        ),
    ],
)
def test_the_rows_kept_hold_every_voxels_bilinear_taps(orbit):
    """For a batch of views, every voxel centre of the grid that projects onto the panel does
    so between row r0 and row r1 - 2 (so that its lower and upper tap rows are kept), and a
    grid smaller than the field of view keeps fewer rows than the panel's."""
    panel = DetectorSpec(rows=160, cols=120, pixel_pitch_mm=1.0)
    geometry = orbit(panel)
    grid = VolumeGrid.centered((20, 24, 28), 2.0, (3.0, -4.0, 30.0))
    x, y, z = grid.axes_mm()
    points = np.stack(np.meshgrid(x, y, z, indexing="ij"), axis=-1).reshape(-1, 3)
    for start in range(0, len(geometry), 4):
        batch = geometry[start : start + 4]
        r0, r1 = rows_seen(batch, grid)
        assert 0 < r1 - r0 < panel.rows
        for view in batch:
            v = view.project(points)[:, 1]
            v = v[(v >= 0) & (v < panel.rows - 1)]
            assert r0 <= np.floor(v).min() and np.floor(v).max() + 1 <= r1 - 1
