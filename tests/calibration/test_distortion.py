"""The fluoroscopy panel's distortion from a dewarp grid's image, and dewarping with it."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from calibration.distortion import DewarpGridSpec, fit_distortion
from recon.distortion import Distortion
from recon.geometry import DetectorSpec
from sim.fluoro import DISTORTION_MAX_PX, add_fluoro_noise, distort, lateral_view
from sim.fluoro import simulate_dewarp_grid as grid_image
from sim.phantoms.knee import KneePhantomSpec

PANEL = 512
VIEW = lateral_view(
    KneePhantomSpec(), DetectorSpec(rows=PANEL, cols=PANEL, pixel_pitch_mm=307.2 / PANEL)
)
GRID = DewarpGridSpec()


def radial(max_px: float, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where sim.fluoro.distort images the ideal pixel (u, v): ``r + max_px (r / R)^3``."""
    c = 0.5 * (PANEL - 1)
    du, dv = u - c, v - c
    gain = 1.0 + max_px * np.hypot(du, dv) ** 2 / math.hypot(c, c) ** 3
    return c + du * gain, c + dv * gain


@pytest.fixture(scope="module")
def pincushion() -> Distortion:
    """The grid through the simulated fluoroscope's whole image model (its 1 px pincushion)."""
    return fit_distortion(grid_image(GRID, VIEW, seed=1), VIEW, GRID)


def _interior() -> tuple[np.ndarray, np.ndarray]:
    """Pixels inside the lattice of balls seen whole (the fit's support)."""
    v, u = np.mgrid[24 : PANEL - 24 : 4, 24 : PANEL - 24 : 4]
    return u.astype(float), v.astype(float)


def test_the_fit_recovers_the_simulated_pincushion(pincushion: Distortion) -> None:
    """~840 ball centroids of ~0.03 px noise (the residual) pin 21 coefficients per axis: the
    warp's error is a few hundredths of a pixel, against the 1 px it corrects."""
    assert pincushion.balls > 800
    assert pincushion.rms_px < 0.05
    u, v = _interior()
    wu, wv = pincushion.warp(u, v)
    tu, tv = radial(DISTORTION_MAX_PX, u, v)
    assert np.hypot(wu - tu, wv - tv).max() < 0.05
    assert pincushion.max_displacement_px == pytest.approx(DISTORTION_MAX_PX, abs=0.15)


@pytest.mark.parametrize("max_px", [-1.5, 0.0])
def test_barrel_and_no_distortion(max_px: float) -> None:
    ideal = grid_image(GRID, VIEW, realism="ideal")
    image = add_fluoro_noise(ideal, 1.0e5, np.random.default_rng(2))[1]
    fitted = fit_distortion(distort(image, max_px) if max_px else image, VIEW, GRID)
    u, v = _interior()
    wu, wv = fitted.warp(u, v)
    tu, tv = radial(max_px, u, v)
    assert np.hypot(wu - tu, wv - tv).max() < 0.05


def test_dewarping_undoes_the_distortion(pincushion: Distortion, tmp_path) -> None:
    """A smooth image (8 px blur), distorted then dewarped, comes back to within a tenth of
    what the distortion changed (the warp's error is ~1/50 of the distortion; the
    simulator's bilinear and our cubic resampling add less)."""
    rng = np.random.default_rng(0)
    image = gaussian_filter(rng.standard_normal((PANEL, PANEL)), 8.0).astype(np.float32)
    distorted = distort(image, DISTORTION_MAX_PX)
    inner = (slice(24, -24), slice(24, -24))
    before = np.sqrt(np.mean((distorted - image)[inner] ** 2))
    after = np.sqrt(np.mean((pincushion.undistort(distorted) - image)[inner] ** 2))
    assert after < 0.1 * before
    stack = pincushion.undistort(np.stack([distorted, distorted]))
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
        pincushion.undistort(np.zeros((3, 256, 256)))
    junk = tmp_path / "junk.json"
    junk.write_text('{"rows": 2}', encoding="utf-8")
    with pytest.raises(ValueError, match=r"junk\.json: not a distortion file"):
        Distortion.read(junk)
