"""The panel's noise model (sim.scan): counts alone and counts with their logarithm agree."""

from __future__ import annotations

import numpy as np

from sim.scan import ELECTRONIC_NOISE_PHOTONS, add_noise, detected_counts


def test_detected_counts_are_add_noises_counts_with_poisson_and_readout_statistics():
    """detected_counts draws what add_noise draws (bit for bit, same seed); at a constant line
    integral their mean is photons exp(-p) and their variance that mean plus the readout
    variance, within 5 standard errors over 512^2 pixels."""
    p = np.full((512, 512), 1.5, dtype=np.float32)
    photons = 2e4
    counts = detected_counts(p, photons, np.random.default_rng(5))
    with_log, noisy = add_noise(p, photons, np.random.default_rng(5))
    assert counts.dtype == np.float32 and counts.tobytes() == with_log.tobytes()
    log = -np.log(with_log.astype(np.float64) / photons)  # from counts rounded to float32
    assert np.abs(noisy - log).max() < 1e-6  # float32's rounding of counts and of logs
    mean = photons * np.exp(-1.5)
    variance = mean + ELECTRONIC_NOISE_PHOTONS**2
    n = counts.size
    assert abs(counts.mean() - mean) < 5 * np.sqrt(variance / n)
    assert abs(counts.var() - variance) < 5 * variance * np.sqrt(2 / n)
