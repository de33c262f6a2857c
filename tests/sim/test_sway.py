"""The simulated standing patient's sway (sim.sway): sized at the knee, zero mean, thigh and
shank apart, drift and tremor in their bands; the bodies' volumes add up to the phantom."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from recon.volume import Volume
from sim.phantoms.knee import KneePhantomSpec, knee_grid, rasterize_knee
from sim.sway import DRIFT_HZ, TREMOR_HZ, Sway, SwayPivots, SwaySpec, body_volumes

SPEC = KneePhantomSpec()
PIVOTS = SwayPivots.of_knee(SPEC)
T = np.linspace(0.0, 18.0, 721)


@pytest.mark.parametrize("peak", [1.0, 2.0, 4.0])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_sway_peaks_at_its_size_at_the_knee(peak, seed):
    sway = Sway(SwaySpec(peak_mm=peak, seed=seed), PIVOTS, 18.0)
    assert sway.peak_displacement_mm() == pytest.approx(peak, rel=1e-3)
    # the views' sampling of the same motion reaches within 5 % of the peak
    moved = max(d.max() for d in sway.displacement_mm(T).values())
    assert 0.95 * peak <= moved <= peak * (1 + 1e-3)


def test_a_still_patient_stays_at_the_reference_pose():
    poses = Sway(SwaySpec(peak_mm=0.0), PIVOTS, 18.0).poses(T)
    for body in ("thigh", "shank"):
        np.testing.assert_array_equal(poses[body], np.broadcast_to(np.eye(4), (len(T), 4, 4)))


def test_the_angles_have_zero_mean_and_thigh_and_shank_move_apart():
    sway = Sway(SwaySpec(peak_mm=3.0, seed=4), PIVOTS, 18.0)
    fine = np.linspace(0.0, 18.0, 2001)
    for name, angle in sway.angles_deg(fine).items():
        assert abs(angle.mean()) < 1e-9 * max(1.0, np.abs(angle).max()), name
    poses = sway.poses(T)
    relative = np.einsum("nij,njk->nik", np.linalg.inv(poses["shank"]), poses["thigh"])
    # the knee's own wobble: the thigh turns against the shank by a visible fraction of a degree
    turn = np.degrees(Rotation.from_matrix(relative[:, :3, :3]).magnitude())
    assert turn.max() > 0.05


def test_drift_and_tremor_lie_in_their_bands():
    """The shank's AP tilt: its spectrum's strongest line is a drift (0.05-0.3 Hz); with a
    tremor share of 0.3 the 1-4 Hz band holds the next strongest."""
    sway = Sway(SwaySpec(peak_mm=2.0, seed=7, tremor_share=0.3), PIVOTS, 200.0)
    t = np.arange(0.0, 200.0, 0.02)
    ap = sway.angles_deg(t)["ap"]
    power = np.abs(np.fft.rfft(ap * np.hanning(len(ap)))) ** 2
    freq = np.fft.rfftfreq(len(t), 0.02)
    assert DRIFT_HZ[0] - 0.01 <= freq[np.argmax(power)] <= DRIFT_HZ[1] + 0.01
    tremor = (freq >= TREMOR_HZ[0] - 0.05) & (freq <= TREMOR_HZ[1] + 0.05)
    quiet = (freq > DRIFT_HZ[1] + 0.1) & (freq < TREMOR_HZ[0] - 0.1)
    assert power[tremor].max() > 100 * power[quiet].max()


def test_the_bodies_volumes_add_up_to_the_phantom():
    grid = knee_grid(SPEC, spacing_mm=2.0)
    labels, mu = rasterize_knee(SPEC, grid, supersample=1)
    parts = body_volumes(Volume(mu, grid, "1/mm"), Volume(labels, grid, "label"), 480.0)
    np.testing.assert_allclose(parts["thigh"] + parts["shank"], mu, atol=1e-7)
    assert parts["thigh"][labels == 3].max() == 0.0  # the tibia is the shank's
    assert parts["shank"][labels == 2].max() == 0.0  # the femur is the thigh's


def test_bad_sway_sizes_are_refused():
    with pytest.raises(ValueError, match="peak_mm"):
        SwaySpec(peak_mm=-1.0)
    with pytest.raises(ValueError, match="duration_s"):
        Sway(SwaySpec(peak_mm=1.0), PIVOTS, 0.0)
