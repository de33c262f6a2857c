"""Tests of registration.similarity: NCC, gradient NCC, the high-pass filter, the turned blur."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from registration.similarity import (
    BlurredHighpass,
    gradient_ncc,
    highpass,
    ncc,
    turned_gaussian,
)


@pytest.fixture
def image() -> np.ndarray:
    rng = np.random.default_rng(0)
    y, x = np.mgrid[:64, :80]
    return (np.sin(x / 5.0) * np.cos(y / 7.0) + 0.1 * rng.standard_normal((64, 80))).astype(
        np.float32
    )


def test_ncc_is_one_for_identical_images_and_minus_one_for_inverted(image) -> None:
    mask = np.ones(image.shape, bool)
    assert ncc(image, image, mask) == pytest.approx(1.0, abs=1e-6)
    assert ncc(image, -image, mask) == pytest.approx(-1.0, abs=1e-6)
    assert gradient_ncc(image, image, mask) == pytest.approx(1.0, abs=1e-6)


@pytest.mark.parametrize(("gain", "offset"), [(3.0, 0.0), (0.01, 5.0), (250.0, -40.0)])
def test_ncc_is_invariant_to_affine_intensity_changes(image, gain, offset) -> None:
    rng = np.random.default_rng(1)
    other = image + 0.3 * rng.standard_normal(image.shape).astype(np.float32)
    mask = np.zeros(image.shape, bool)
    mask[10:50, 5:70] = True
    reference = ncc(image, other, mask)
    assert 0.2 < reference < 0.99
    assert ncc(gain * image + offset, other, mask) == pytest.approx(reference, abs=1e-5)
    assert gradient_ncc(gain * image + offset, other, mask) == pytest.approx(
        gradient_ncc(image, other, mask), abs=1e-5
    )


def test_ncc_only_sees_the_mask(image) -> None:
    mask = np.zeros(image.shape, bool)
    mask[:, :40] = True
    scrambled = image.copy()
    scrambled[:, 40:] = np.random.default_rng(2).standard_normal((64, 40))
    assert ncc(image, scrambled, mask) == pytest.approx(1.0, abs=1e-6)


def test_highpass_removes_smooth_backgrounds_and_keeps_edges() -> None:
    y, x = np.mgrid[:128, :128].astype(np.float32)
    ramp = 0.02 * x + 0.01 * y + 3.0
    assert np.abs(highpass(ramp, 4.0)[20:-20, 20:-20]).max() < 1e-3
    step = (x > 64).astype(np.float32)
    out = highpass(step, 4.0)
    assert out[64, 60:69].max() > 0.3  # the edge survives
    assert np.abs(out[64, :40]).max() < 1e-3  # far from it, nothing


@pytest.mark.parametrize("sigma_px", [0.7, 3.3, 8.0])
def test_highpass_is_scipys_gaussian_filter_to_the_bit(image, sigma_px) -> None:
    """The filter of every registration evaluation is scipy's, edges included (a kernel of
    another rounding, radius or edge mode would show)."""
    for img in (image, image[:23, 5:], image.astype(np.float64)):
        expected = img.astype(np.float32) - gaussian_filter(
            img.astype(np.float32), sigma_px, mode="nearest"
        )
        out = highpass(img, sigma_px)
        assert out.dtype == np.float32
        np.testing.assert_array_equal(out, expected)


def test_turned_gaussian_is_the_axis_aligned_blur_at_0_and_90_degrees(image) -> None:
    s_u, s_v = 2.5, 1.0
    axis_aligned = gaussian_filter(image, (s_v, s_u), mode="nearest")  # (rows = v, cols = u)
    inner = np.s_[12:-12, 12:-12]  # away from the edges, where the two extend differently
    assert np.abs(turned_gaussian(image, (s_u, s_v), 0.0) - axis_aligned)[inner].max() < 1e-3
    turned = turned_gaussian(image, (s_v, s_u), np.pi / 2)  # u's sigma now lies along v
    assert np.abs(turned - axis_aligned)[inner].max() < 1e-3


def test_turned_gaussian_spreads_a_point_along_the_turned_axis() -> None:
    """A point's blur has covariance R diag(s_u^2, s_v^2) R^T, R the turn in the (u, v) plane."""
    impulse = np.zeros((97, 97), dtype=np.float32)
    impulse[48, 48] = 1.0
    s_u, s_v, angle = 4.0, 1.5, np.radians(30.0)
    psf = turned_gaussian(impulse, (s_u, s_v), angle).astype(np.float64)
    v, u = np.mgrid[:97, :97] - 48.0
    total = psf.sum()
    moments = np.array(
        [[(psf * u * u).sum(), (psf * u * v).sum()], [(psf * u * v).sum(), (psf * v * v).sum()]]
    )
    c, s = np.cos(angle), np.sin(angle)
    turn = np.array([[c, -s], [s, c]])
    expected = turn @ np.diag([s_u**2, s_v**2]) @ turn.T
    assert total == pytest.approx(1.0, abs=1e-4)  # the blur keeps the intensity
    np.testing.assert_allclose(moments / total, expected, atol=0.02)


@pytest.mark.parametrize(
    ("shape", "blur_px", "sigma_px"), [((90, 71), 1.3, 4.0), ((40, 57), 0.0, 2.0)]
)
def test_the_blurred_highpass_by_fft_is_scipys_blur_then_highpass(shape, blur_px, sigma_px):
    """A render that vanishes before its crop's edges (a mesh's, zero over a margin wider than
    both kernels' reach): the one-pass FFT filter gives what scipy's blur then high-pass do,
    to float32 rounding (1e-6 of values of order 1)."""
    rng = np.random.default_rng(3)
    render = np.zeros(shape, np.float32)
    render[18:-18, 18:-18] = rng.random((shape[0] - 36, shape[1] - 36))
    blurred = gaussian_filter(render, blur_px, mode="constant") if blur_px else render
    expected = highpass(blurred, sigma_px)
    got = BlurredHighpass(shape, blur_px, sigma_px)(render)
    assert got.dtype == np.float32 and got.shape == shape
    np.testing.assert_allclose(got, expected, atol=1e-6)
