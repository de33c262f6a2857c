"""Panel corrections: the simulated sensor's offset, gain, defects and lag measured from dark and
flood frames, and undone down to the photons' own noise."""

from __future__ import annotations

import datetime as dt

import numpy as np
import pytest

from scanner.corrections import Corrector, MapsError, PanelMaps, derive_maps, find_maps
from sim.panel import PanelSensor, SimPanelSpec

ROWS, COLS = 96, 128
FLOOD_PHOTONS = 2.0e5  # an unattenuated pixel's photons per frame
FRAMES = 16
SPEC = SimPanelSpec()
MAS = 0.765


def calibrated(seed: int) -> tuple[PanelSensor, PanelMaps, np.random.Generator]:
    """A sensor, and maps derived from its darks and floods as cbct detector-calibrate takes
    them (darks, floods, then darks)."""
    sensor = PanelSensor(SPEC, ROWS, COLS, SPEC.flood_adu / FLOOD_PHOTONS, seed=seed)
    rng = np.random.default_rng(seed)

    def flood() -> np.ndarray:
        return sensor.read(rng.poisson(FLOOD_PHOTONS, (ROWS, COLS)), rng)

    darks = np.stack([sensor.read(None, rng) for _ in range(FRAMES)])
    floods = np.stack([flood() for _ in range(FRAMES)])
    after = np.stack([sensor.read(None, rng) for _ in range(2)])
    maps = derive_maps(darks, floods, after, serial=SPEC.serial, mode="m", kv=110, mas=MAS)
    return sensor, maps, rng


def knee_like(rows: int = ROWS, cols: int = COLS) -> np.ndarray:
    """Line integrals of an ellipse of up to 4 (a thick leg) in air."""
    v, u = np.mgrid[:rows, :cols]
    r2 = ((u - cols / 2) / (0.3 * cols)) ** 2 + ((v - rows / 2) / (0.45 * rows)) ** 2
    return 4.0 * np.sqrt(np.clip(1.0 - r2, 0.0, None))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_defects_and_lag_are_found(seed):
    sensor, maps, _ = calibrated(seed)
    found = maps.defects
    assert found[sensor.dead].all() and found[sensor.hot].all()  # every dead and hot pixel
    weak = np.flatnonzero(np.median(sensor.gain, axis=1) < 0.5 * np.median(sensor.gain))
    assert found[weak].all()  # the weak row (a third of its gain)
    planted = sensor.dead | sensor.hot
    planted[weak] = True
    # false alarms: pixels whose gain is a > 8 robust-sigma outlier of the 5 % spread and ramp
    assert (found & ~planted).mean() < 1e-3
    # the lag: measured from one dark after 15 floods, to the gain map's noise and one count
    assert maps.lag == pytest.approx(SPEC.lag, abs=0.002)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_corrected_frames_are_the_photons_line_integrals_to_their_noise(seed):
    """Frames of a leg after one another (lag carries over): the corrected line integrals
    differ from the truth by the noise the photons and the read-out put in, no more, and with
    no bias; uncorrected ones are far off."""
    sensor, maps, rng = calibrated(seed)
    corrector = Corrector(maps)
    p = knee_like()
    good = ~maps.defects
    errors, sigmas, raw_errors = [], [], []
    for k in range(6):
        shifted = np.roll(p, 7 * k, axis=1)  # the leg moves across the panel frame to frame
        expected = FLOOD_PHOTONS * np.exp(-shifted)
        raw = sensor.read(rng.poisson(expected), rng)
        ours = corrector.line_integrals(raw, 110, MAS)
        errors.append((ours - shifted)[good])
        # per pixel: Poisson, read-out and rounding noise of the frame, the flood map's own
        # (over 15 floods) and the lag removal's share of the frame before
        adu = SPEC.flood_adu / FLOOD_PHOTONS * np.median(sensor.gain)
        signal = adu * expected
        read = (SPEC.read_noise_adu**2 + 1 / 12) / signal**2
        sigma2 = 1 / expected + read + 1 / (15 * FLOOD_PHOTONS) + SPEC.lag**2 / expected
        sigmas.append(np.sqrt(sigma2)[good])
        raw_errors.append(np.abs(-np.log(raw / raw.max()) - shifted)[good].mean())
    z = np.concatenate(errors) / np.concatenate(sigmas)
    assert np.sqrt(np.mean(z**2)) < 1.1  # the noise, not more (1.0 when the model is exact)
    assert abs(z.mean()) < 5 / np.sqrt(z.size)  # no bias
    assert min(raw_errors) > 0.05  # offset, gain and lag left in are far above it


def test_defective_pixels_are_filled_from_good_neighbours():
    sensor, maps, rng = calibrated(0)
    p = knee_like()
    raw = sensor.read(rng.poisson(FLOOD_PHOTONS * np.exp(-p)), rng)
    ours = Corrector(maps).line_integrals(raw, 110, MAS)
    # inside the leg a filled pixel is its good neighbours' mean: right to 6 noise SDs of the
    # thickest path, 6 / sqrt(2e5 exp(-4)) = 0.1 (the mean's curvature error is far below)
    inside = (p > 2.0) & maps.defects
    assert inside.sum() > 20
    assert np.abs(ours - p)[inside].max() < 6 * np.sqrt(np.exp(4.0) / FLOOD_PHOTONS)


def test_i0_from_air_follows_the_tubes_output():
    """A pulse 4 % stronger than the flood's technique says: with air in the frame the line
    integrals stay right; without air, the flood (scaled by mAs) is used and they are off by
    ln(1.04)."""
    sensor, maps, rng = calibrated(1)
    p = knee_like()
    raw = sensor.read(rng.poisson(1.04 * FLOOD_PHOTONS * np.exp(-p)), rng)
    corrector = Corrector(maps)
    ours = corrector.line_integrals(raw, 110, MAS)
    inside = (p > 1.0) & ~maps.defects
    assert abs(np.median((ours - p)[inside])) < 0.005
    no_air = p + 1.0
    raw = sensor.read(rng.poisson(1.04 * FLOOD_PHOTONS * np.exp(-no_air)), rng)
    ours = corrector.line_integrals(raw, 110, MAS)
    assert corrector.flood_views == 1 and corrector.air_views == 1
    assert np.median((ours - no_air)[~maps.defects]) == pytest.approx(-np.log(1.04), abs=0.005)


def test_maps_are_found_only_for_their_panel_mode_and_age(tmp_path):
    _, maps, _ = calibrated(0)
    path = maps.save(tmp_path)
    assert path == tmp_path / SPEC.serial / "m.npz"
    with pytest.raises(MapsError, match="never overwritten"):
        maps.save(tmp_path)
    loaded = find_maps(tmp_path, SPEC.serial, "m", max_age_days=7)
    assert np.array_equal(loaded.defects, maps.defects) and loaded.lag == maps.lag
    with pytest.raises(MapsError, match=r"panel 'OTHER-1'.*SIM-PANEL-0001/m\.npz"):
        find_maps(tmp_path, "OTHER-1", "m", max_age_days=7)
    with pytest.raises(MapsError, match=r"mode '512x512 Mono16'"):
        find_maps(tmp_path, SPEC.serial, "512x512 Mono16", max_age_days=7)
    later = dt.datetime.fromisoformat(maps.made) + dt.timedelta(days=8)
    with pytest.raises(MapsError, match=r"8\.0 days old, the limit is 7 days"):
        find_maps(tmp_path, SPEC.serial, "m", max_age_days=7, now=later)


def test_floods_without_x_rays_are_refused():
    sensor = PanelSensor(SPEC, ROWS, COLS, 0.2, seed=0)
    rng = np.random.default_rng(0)
    darks = np.stack([sensor.read(None, rng) for _ in range(5)])
    with pytest.raises(MapsError, match="no X-rays reached the panel"):
        derive_maps(darks, darks, darks[:1], serial="s", mode="m", kv=110, mas=MAS)
