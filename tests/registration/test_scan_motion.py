"""The patient's motion estimated from a scan's own projections (registration.scan_motion), on a
small case: the knee phantom scanned through 90 views of 128 x 128 pixels of 4.8 mm, standing
still or swaying; reconstructed on 2 mm voxels. (bench/motion.py measures the full sizes.)"""

from __future__ import annotations

import numpy as np
import pytest

from configs import CONFIGS
from recon.config import load_protocol
from recon.fdk import fdk_reconstruct
from recon.volume import VolumeGrid
from registration.labels import LABELS
from registration.scan_motion import MIN_VIEWS, MotionSettings, estimate_motion
from sim.phantoms.knee import KneePhantomSpec, rasterize_knee
from sim.scan import simulate_knee_scan
from sim.sway import SwaySpec

SPEC = KneePhantomSpec()
GRID = VolumeGrid.centered((70, 70, 80), 2.0, (0.0, -4.0, 490.0))
SETTINGS = MotionSettings(voxel_mm=2.0, two_body_rounds=1)


def _protocol():
    base = load_protocol(CONFIGS / "protocols" / "demo_knee.yaml")
    detector = base.detector.model_copy(update={"rows": 128, "cols": 128, "pixel_pitch_mm": 4.8})
    orbit = base.orbit.model_copy(update={"views": 90})
    return base.model_copy(update={"detector": detector, "orbit": orbit})


def _scan(peak_mm: float, seed: int = 0):
    sway = SwaySpec(peak_mm=peak_mm, seed=seed)
    return simulate_knee_scan(_protocol(), SPEC, voxel_mm=1.0, seed=seed, sway=sway)


@pytest.fixture(scope="module")
def truth() -> tuple[np.ndarray, np.ndarray]:
    labels, mu = rasterize_knee(SPEC, GRID)
    return labels > 0, mu


def _rmse(volume: np.ndarray, truth, mask) -> float:
    inside, mu = truth
    return float(np.sqrt(np.mean((volume - mu)[inside & mask] ** 2)))


def test_a_still_scan_comes_back_still_and_its_volume_is_plain_fdk(truth):
    """Nothing moved: the estimate stays within a fraction of a voxel of the average pose, and
    the volume through it is plain FDK's to 1 % RMSE against the phantom."""
    scan = _scan(0.0)
    estimate = estimate_motion(scan.projections, scan.geometry, GRID, settings=SETTINGS)
    assert max(estimate.peak_mm.values()) < 0.5  # a quarter of a 2 mm voxel
    plain = fdk_reconstruct(scan.projections, scan.geometry, GRID)
    through = fdk_reconstruct(scan.projections, scan.geometry, GRID, motion=estimate.motion)
    mask = plain.mask
    a, b = _rmse(plain.volume.data, truth, mask), _rmse(through.volume.data, truth, mask)
    assert abs(b - a) <= 0.01 * a


def test_a_swaying_scan_is_compensated(truth):
    """4 mm of sway at the knee: the compensated volume recovers at least half the RMSE the
    motion cost (1.03-1.43 measured over seeds 1-3 on this coarse case, whose 2 mm voxels hide
    most of the blur: the moving scan's RMSE is 4-6 % above the still one's), and the motion
    found peaks at 2-8 mm over the bones' surfaces (5.0-6.4 measured: the shafts' far ends
    move 1.2-1.6 times as far as the knee)."""
    still = _scan(0.0, seed=1)
    moving = _scan(4.0, seed=1)
    estimate = estimate_motion(
        moving.projections, moving.geometry, GRID, times_s=moving.times_s, settings=SETTINGS
    )
    plain = fdk_reconstruct(still.projections, still.geometry, GRID)
    blurred = fdk_reconstruct(moving.projections, moving.geometry, GRID)
    through = fdk_reconstruct(moving.projections, moving.geometry, GRID, motion=estimate.motion)
    mask = plain.mask
    r = [_rmse(v.volume.data, truth, mask) for v in (plain, blurred, through)]
    assert r[1] > 1.03 * r[0]  # the sway shows
    assert (r[1] - r[2]) / (r[1] - r[0]) >= 0.5
    assert 2.0 <= max(estimate.peak_mm.values()) <= 8.0
    assert estimate.compensable


def test_bad_scans_are_refused_before_any_work():
    scan = _scan(0.0)
    few = scan.geometry[: MIN_VIEWS - 1]
    with pytest.raises(ValueError, match=f"at least {MIN_VIEWS}"):
        estimate_motion(scan.projections[: MIN_VIEWS - 1], few, GRID)
    times = np.arange(len(scan.geometry), dtype=float)
    times[10] = times[9]
    with pytest.raises(ValueError, match="view 10"):
        estimate_motion(scan.projections, scan.geometry, GRID, times_s=times)


def test_a_volume_without_bone_is_refused():
    """A leg of water alone: nothing to register, said in words."""
    scan = _scan(0.0)
    labels, _ = rasterize_knee(SPEC, GRID)
    water = np.where(labels > 0, 0.02, 0.0).astype(np.float32)
    from recon.project import JosephProjector

    projections = JosephProjector(water, GRID).project(scan.geometry)
    with pytest.raises(ValueError, match="no bone to register"):
        estimate_motion(projections, scan.geometry, GRID, settings=SETTINGS)


def test_a_knee_with_metal_is_refused():
    """The knee phantom with a block of metal (20 x 20 x 12 mm at 20 x water's attenuation) in
    its tibia: refused in words naming the metal (the still knee without it is estimated:
    test_a_still_scan_comes_back_still_and_its_volume_is_plain_fdk)."""
    scan = _scan(0.0)
    labels, mu = rasterize_knee(SPEC, GRID)
    metal = mu.copy()
    z, y, x = np.argwhere(labels == LABELS["tibia"]).mean(axis=0).astype(int)
    metal[z - 3 : z + 3, y - 5 : y + 5, x - 5 : x + 5] = 0.4
    from recon.project import JosephProjector

    projections = JosephProjector(metal, GRID).project(scan.geometry)
    with pytest.raises(ValueError, match=r"metal in the field \(\d+ cm\^3"):
        estimate_motion(projections, scan.geometry, GRID, settings=SETTINGS)


@pytest.mark.parametrize(
    ("name", "value", "words"),
    [
        ("voxel_mm", 0.0, r"voxel_mm must be >= 0.05 mm, got 0.0"),
        ("margin_mm", float("nan"), r"margin_mm must be >= 0.0 mm, got nan"),
        ("blend_mm", -1.0, r"blend_mm must be >= 0.1 mm, got -1.0"),
        ("fit_pixel", 0.05, r"fit_pixel must be >= 0.1 voxels, got 0.05"),
        ("two_body_rounds", -1, r"two_body_rounds must be >= 0, got -1"),
    ],
)
def test_bad_settings_name_the_field_the_value_and_the_limit(name, value, words):
    with pytest.raises(ValueError, match=words):
        MotionSettings(**{name: value})
