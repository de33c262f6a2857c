"""The fluoroscopy panel's distortion from a dewarp grid's image, and dewarping with it."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from calibration.dewarp_grid import DewarpGridSpec, fit_distortion
from recon.distortion import Distortion, panel_mm
from recon.geometry import DetectorSpec
from sim.fluoro import DISTORTION_MAX_MM, add_fluoro_noise, distort, lateral_view
from sim.fluoro import simulate_dewarp_grid as grid_image
from sim.phantoms.knee import KneePhantomSpec

PANEL, PITCH = 512, 0.6
VIEW = lateral_view(KneePhantomSpec(), DetectorSpec(rows=PANEL, cols=PANEL, pixel_pitch_mm=PITCH))
GRID = DewarpGridSpec()
HALF_DIAGONAL_MM = math.hypot(0.5 * (PANEL - 1), 0.5 * (PANEL - 1)) * PITCH


def radial(max_mm: float, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where sim.fluoro.distort images the ideal panel point (x, y), mm:
    ``r + max_mm (r / R)^3``, R the half diagonal."""
    gain = 1.0 + max_mm * np.hypot(x, y) ** 2 / HALF_DIAGONAL_MM**3
    return x * gain, y * gain


@pytest.fixture(scope="module")
def pincushion(seed: int) -> Distortion:
    """The grid through the simulated fluoroscope's whole image model (its pincushion)."""
    return fit_distortion(grid_image(GRID, VIEW, seed=1 + seed), VIEW, GRID)


def _interior() -> tuple[np.ndarray, np.ndarray]:
    """Panel points inside the lattice of balls seen whole (the fit's support), mm."""
    v, u = np.mgrid[24 : PANEL - 24 : 4, 24 : PANEL - 24 : 4]
    return panel_mm(u, v, PANEL, PANEL, PITCH)


def _warp_error_px(fitted: Distortion, max_mm: float) -> float:
    x, y = _interior()
    wx, wy = fitted.warp(x, y)
    tx, ty = radial(max_mm, x, y)
    return float(np.hypot(wx - tx, wy - ty).max()) / PITCH


def test_the_fit_recovers_the_simulated_pincushion(pincushion: Distortion, measured) -> None:
    """~840 ball centroids of ~0.03 px noise (the residual) pin 21 coefficients per axis: the
    warp's error is a few hundredths of a pixel, against the 1 px it corrects."""
    assert pincushion.balls > 800
    measured("fit_residual_rms_px", pincushion.rms_mm / PITCH, below=0.05)
    measured("warp_error_px", _warp_error_px(pincushion, DISTORTION_MAX_MM), below=0.05)
    displacement_error = abs(pincushion.max_displacement_mm - DISTORTION_MAX_MM)
    measured("max_displacement_error_mm", displacement_error, below=0.1)


@pytest.mark.parametrize("max_mm", [-0.9, 0.0])
def test_barrel_and_no_distortion(max_mm: float, seed: int, measured) -> None:
    ideal = grid_image(GRID, VIEW, realism="ideal")
    image = add_fluoro_noise(ideal, 1.0e5, np.random.default_rng(2 + seed))[1]
    fitted = fit_distortion(distort(image, max_mm / PITCH) if max_mm else image, VIEW, GRID)
    measured("warp_error_px", _warp_error_px(fitted, max_mm), below=0.05)


def test_a_warp_from_the_native_pitch_dewarps_a_binned_read_out(seed: int, measured) -> None:
    """The warp is in mm: fitted at 1024 pixels of 0.3 mm it equals the one fitted at 512
    pixels of 0.6 mm to a few hundredths of a 0.6 mm pixel."""
    native = lateral_view(KneePhantomSpec(), DetectorSpec(rows=1024, cols=1024, pixel_pitch_mm=0.3))
    fitted = fit_distortion(grid_image(GRID, native, seed=5 + seed), native, GRID)
    measured("warp_error_px", _warp_error_px(fitted, DISTORTION_MAX_MM), below=0.05)


def test_dewarping_undoes_the_distortion(
    pincushion: Distortion, tmp_path, seed: int, measured
) -> None:
    """A smooth image (8 px blur), distorted then dewarped, comes back to within a tenth of
    what the distortion changed (the warp's error is ~1/50 of the distortion; the
    simulator's bilinear and our cubic resampling add less)."""
    rng = np.random.default_rng(0 + seed)
    image = gaussian_filter(rng.standard_normal((PANEL, PANEL)), 8.0).astype(np.float32)
    distorted = distort(image, DISTORTION_MAX_MM / PITCH)
    inner = (slice(24, -24), slice(24, -24))
    before = np.sqrt(np.mean((distorted - image)[inner] ** 2))
    after = np.sqrt(np.mean((pincushion.undistort(distorted, PITCH) - image)[inner] ** 2))
    measured("dewarp_residual_over_distortion", after / before, below=0.1)
    stack = pincushion.undistort(np.stack([distorted, distorted]), PITCH)
    assert stack.shape == (2, PANEL, PANEL) and stack.dtype == np.float32
    again = Distortion.read(pincushion.write(tmp_path / "distortion.json"))
    assert np.array_equal(again.coefficients, pincushion.coefficients)
    assert again.summary() == pincushion.summary()


def test_bad_input_is_refused_in_words(pincushion: Distortion, tmp_path) -> None:
    with pytest.raises(ValueError, match=r"\(256, 256\) does not match the view's panel"):
        fit_distortion(np.zeros((256, 256)), VIEW, GRID)
    plate_only = grid_image(GRID.model_copy(update={"ball_mu_per_mm": 1e-6}), VIEW, seed=3)
    with pytest.raises(ValueError, match="balls found"):
        fit_distortion(plate_only, VIEW, GRID)
    with pytest.raises(ValueError, match="do not match the distortion's panel"):
        pincushion.undistort(np.zeros((3, 256, 256)), PITCH)
    junk = tmp_path / "junk.json"
    junk.write_text('{"width_mm": 2}', encoding="utf-8")
    with pytest.raises(ValueError, match=r"junk\.json: not a distortion file"):
        Distortion.read(junk)
