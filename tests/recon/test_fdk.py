"""recon.fdk: weighted FDK on circular, short-scan and reverse-spiral orbits."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from recon.fdk import (
    FDKAccumulator,
    default_grid,
    estimate_orbit,
    fdk_reconstruct,
    ramp_filter_response,
)
from recon.geometry import (
    DetectorSpec,
    Geometry,
    View,
    circular_orbit,
    helical_orbit,
    short_scan_arc_deg,
)
from recon.project import forward_project
from recon.rtk_peer import rtk_fdk, rtk_shepp_logan
from recon.volume import VolumeGrid

PANEL = DetectorSpec(rows=96, cols=128, pixel_pitch_mm=1.0)
ISO = (0.0, 0.0, 480.0)
FINE = VolumeGrid.centered((160, 160, 144), 0.5, ISO)  # phantoms are projected from here
GRID = VolumeGrid.centered((80, 80, 72), 1.0, ISO)  # and reconstructed here
MU = 0.02  # 1/mm, water-like


def region(grid: VolumeGrid, radius: float, half_height: float) -> np.ndarray:
    x, y, z = grid.axes_mm()
    r2 = (y - ISO[1])[:, None] ** 2 + (x - ISO[0])[None, :] ** 2
    return (np.abs(z - ISO[2]) < half_height)[:, None, None] & (r2 < radius**2)[None]


@pytest.fixture(scope="module")
def cylinder_pair(make_ball, make_cylinder):
    """A water cylinder (r 30 mm, 56 mm tall) with a denser ball, fine and coarse versions."""

    def build(grid, supersample):
        vol = make_cylinder(grid, ISO, 30.0, 28.0, MU, supersample)
        return vol + make_ball(grid, (10.0, -5.0, 486.0), 6.0, MU, supersample)

    return build(FINE, 2), build(GRID, 3)


def test_ramp_response_is_the_band_limited_ramp(measured):
    """The zero-padded Ram-Lak kernel's response is |f| (cycles per pixel) up to Nyquist, up to
    the kernel's finite support: within 1 / n_fft of the ideal ramp."""
    n = 512
    response = ramp_filter_response(n, 1.0, "ram-lak", 1.0)
    f = np.fft.rfftfreq(n)
    measured("ramp_response_max_error", np.abs(response - f).max(), below=1.0 / n)
    hann = ramp_filter_response(n, 1.0, "hann", 1.0)
    assert hann[-1] == pytest.approx(0.0, abs=1e-12)
    window = 0.5 * (1 + np.cos(np.pi * 0.25))  # Hann at a quarter of the band
    assert hann[n // 8] == pytest.approx(response[n // 8] * window, rel=1e-12)
    half = ramp_filter_response(n, 1.0, "shepp-logan", 0.5)
    assert np.all(half[f > 0.25] == 0)


def test_full_circle_reconstructs_the_attenuation(cylinder_pair, measured):
    fine, truth = cylinder_pair
    geometry = circular_orbit(180, 600, 1000, PANEL, isocenter_mm=ISO)
    result = fdk_reconstruct(forward_project(fine, FINE, geometry), geometry, GRID)
    inner = region(GRID, 25.0, 10.0) & (truth == MU)
    values = result.volume.data[inner]
    measured("water_mean_rel_error", abs(values.mean() / MU - 1), below=3e-3)
    measured("water_std_over_mu", values.std() / MU, below=0.01)
    ball_core = truth == 2 * MU
    ball_mean = result.volume.data[ball_core].mean()
    measured("ball_mean_rel_error", abs(ball_mean / (2 * MU) - 1), below=0.02)
    coverage_error = np.abs(result.coverage_deg[inner] / 360.0 - 1).max()
    measured("coverage_rel_error", coverage_error, below=1e-3)
    assert result.orbit.closed and len(result.orbit.passes) == 1


def test_not_flipped_the_dense_ball_comes_back_where_it_was(cylinder_pair, measured):
    fine, _ = cylinder_pair
    geometry = circular_orbit(90, 600, 1000, PANEL, isocenter_mm=ISO)
    volume = fdk_reconstruct(forward_project(fine, FINE, geometry), geometry, GRID).volume.data
    excess = (volume - MU > 0.5 * MU) * region(GRID, 28, 26)
    z, y, x = (np.nonzero(excess)[k].mean() for k in range(3))
    world = GRID.index_to_world([x, y, z])
    error = np.abs(np.asarray(world) - [10.0, -5.0, 486.0]).max()
    measured("centroid_error_mm", error, below=0.25)  # a quarter voxel


def test_short_scan_with_parker_weights_is_flat_without_them_it_is_shaded(cylinder_pair, measured):
    fine, truth = cylinder_pair
    arc = short_scan_arc_deg(1000, PANEL) + 4
    geometry = circular_orbit(110, 600, 1000, PANEL, arc_deg=arc, isocenter_mm=ISO)
    proj = forward_project(fine, FINE, geometry)
    inner = region(GRID, 25.0, 10.0) & (truth == MU)
    parker = fdk_reconstruct(proj, geometry, GRID)
    plain = fdk_reconstruct(proj, geometry, GRID, redundancy="none")
    parker_std = parker.volume.data[inner].std()
    measured("water_mean_rel_error", abs(parker.volume.data[inner].mean() / MU - 1), below=5e-3)
    measured("water_std_over_mu", parker_std / MU, below=0.01)
    # unweighted, the rays the short scan sees twice shade the water (3.2 x Parker's std)
    measured("unweighted_over_parker_std", plain.volume.data[inner].std() / parker_std, above=2)
    # a complete short scan covers each voxel's lines once: 180 degrees
    coverage_error = np.abs(parker.coverage_deg[inner] / 180.0 - 1).max()
    measured("coverage_rel_error", coverage_error, below=2e-3)


def test_matches_rtk_fdk_where_the_data_are_complete(cylinder_pair, measured):
    """Same discretisation as RTK (spatial Ram-Lak kernel, bilinear voxel-driven backprojection,
    Parker weights): inside the field both agree to float32 rounding (measured 6e-7 and 2e-5
    relative RMSE); the coverage normalisation is the identity there."""
    fine, _ = cylinder_pair
    full = circular_orbit(90, 600, 1000, PANEL, isocenter_mm=ISO)
    arc = short_scan_arc_deg(1000, PANEL) + 4
    short = circular_orbit(90, 600, 1000, PANEL, arc_deg=arc, isocenter_mm=ISO)
    inner = region(GRID, 30.0, 20.0)
    for name, geometry, parker in (("full", full, False), ("short", short, True)):
        proj = forward_project(fine, FINE, geometry)
        ours = fdk_reconstruct(proj, geometry, GRID, window="ram-lak", edge_taper_px=0).volume
        theirs = rtk_fdk(proj, geometry, GRID, parker=parker)
        diff = ours.data[inner] - theirs[inner]
        rel_rmse = np.sqrt(np.mean(diff**2)) / np.sqrt(np.mean(theirs[inner] ** 2))
        measured(f"rel_rmse_vs_rtk_{name}", rel_rmse, below=1e-4)


def test_reverse_spiral_is_normalised_along_z(cylinder_pair, measured):
    """Two passes, +-20 mm of travel, a 38 mm tall field at the isocentre: voxels away from the
    middle see fewer views. The coverage normalisation keeps the axial profile flat (measured
    within 1.5 %); RTK's plain FDK, given the same views, sags to a third at z = 25 mm."""
    fine, truth = cylinder_pair
    panel = DetectorSpec(rows=64, cols=128, pixel_pitch_mm=1.0)  # short panel: partial views
    geometry = helical_orbit(
        180, 600, 1000, panel, arc_deg=360, z_start_mm=-20, z_end_mm=20, passes=2, isocenter_mm=ISO
    )
    orbit = estimate_orbit(geometry)
    assert [b - a for a, b in orbit.passes] == [90, 90]
    proj = forward_project(fine, FINE, geometry)
    ours = fdk_reconstruct(proj, geometry, GRID, window="ram-lak").volume.data
    theirs = rtk_fdk(proj, geometry, GRID)
    z = GRID.axes_mm()[2] - ISO[2]
    core = region(GRID, 20.0, 40.0) & ~(truth > MU)
    profile = np.array([ours[k][core[k]].mean() for k in range(len(z))])
    rtk_profile = np.array([theirs[k][core[k]].mean() for k in range(len(z))])
    ends = (np.abs(z) > 15) & (np.abs(z) < 25)
    measured("profile_ends_rel_error", np.abs(profile[ends] / MU - 1).max(), below=0.02)
    measured("rtk_profile_ends_sag", (1 - rtk_profile[ends] / MU).min(), above=0.3)
    middle = np.abs(z) < 25
    measured("profile_rel_error", np.abs(profile[middle] / MU - 1).max(), below=0.02)


def test_voxels_no_view_covers_enough_are_masked(cylinder_pair):
    fine, _ = cylinder_pair
    geometry = circular_orbit(60, 600, 1000, PANEL, isocenter_mm=ISO)
    wide = VolumeGrid.centered((120, 120, 20), 1.0, ISO)  # corners outside the fan
    result = fdk_reconstruct(forward_project(fine, FINE, geometry), geometry, wide)
    x, y, _ = wide.axes_mm()
    radius = np.hypot(x[None, :], y[:, None])
    fov = 600 * np.sin(np.arctan(0.5 * 128 / 1000))
    # outside the field a voxel at radius r is seen from 4 arcsin(fov / r) of the turn:
    # below the default 170 degrees beyond r = fov / sin(42.5 deg)
    outside = radius > fov / np.sin(np.radians(42.5)) + 2
    assert outside.any() and not result.mask[:, outside].any()
    assert (result.volume.data[:, outside] == 0).all()
    assert result.mask[:, radius < fov - 8].all()


def test_progress_reports_every_batch(cylinder_pair):
    fine, _ = cylinder_pair
    geometry = circular_orbit(40, 600, 1000, PANEL, isocenter_mm=ISO)
    calls = []
    fdk_reconstruct(
        forward_project(fine, FINE, geometry),
        geometry,
        GRID,
        batch_views=16,
        progress=lambda done, total: calls.append((done, total)),
    )
    assert calls == [(16, 40), (32, 40), (40, 40)]


def test_views_added_in_any_order_give_the_same_volume(cylinder_pair):
    """The accumulator behind streaming: batches in reverse order and of other sizes sum to the
    offline volume within float32 rounding of the sums; a view is never added twice, and no view
    after the result (normalised in the accumulator's own sum)."""
    fine, _ = cylinder_pair
    geometry = helical_orbit(
        48, 600, 1000, PANEL, arc_deg=360, z_start_mm=-10, z_end_mm=10, passes=2, isocenter_mm=ISO
    )
    proj = forward_project(fine, FINE, geometry)
    offline = fdk_reconstruct(proj, geometry, GRID).volume.data
    acc = FDKAccumulator(geometry, GRID)
    for start in (40, 35, 12, 0, 13):  # 40-47, 35-39, 12, 0-11, 13-34
        stop = {40: 48, 35: 40, 12: 13, 0: 12, 13: 35}[start]
        acc.add(start, proj[start:stop], geometry[start:stop])
    with pytest.raises(ValueError, match=r"view\(s\) \[12\] were added already"):
        acc.add(12, proj[12:13])
    streamed = acc.result().volume.data
    assert np.abs(offline).max() > 0.5 * MU
    assert np.abs(streamed - offline).max() <= 1e-5 * np.abs(offline).max()
    with pytest.raises(RuntimeError, match="result was taken"):
        acc.add(12, proj[12:13])
    with pytest.raises(RuntimeError, match="result was taken"):
        acc.result()
    same = fdk_reconstruct(proj, geometry, GRID, orbit_geometry=geometry).volume.data
    np.testing.assert_array_equal(same, offline)  # the orbit given is the geometry's own


def test_default_grid_covers_the_field_of_view():
    geometry = circular_orbit(60, 600, 1000, PANEL, isocenter_mm=ISO)
    grid = default_grid(geometry)
    np.testing.assert_allclose(grid.center_mm, ISO, atol=1e-6)
    assert grid.spacing_mm[0] == pytest.approx(0.6)  # 1 mm pixels at magnification 5/3
    fov = 600 * np.sin(np.arctan(64 / 1000))
    assert grid.size_xyz[0] * 0.6 == pytest.approx(2 * fov, abs=0.6)


def test_bad_input_is_refused_before_reconstructing():
    geometry = circular_orbit(20, 600, 1000, PANEL, isocenter_mm=ISO)
    proj = np.zeros((20, 96, 128), dtype=np.float32)
    with pytest.raises(ValueError, match="geometry has 20 views"):
        fdk_reconstruct(proj[:19], geometry, GRID)
    bad = proj.copy()
    bad[7, 3, 3] = np.nan
    with pytest.raises(ValueError, match=r"view\(s\) \[7\]"):
        fdk_reconstruct(bad, geometry, GRID)
    elsewhere = VolumeGrid.centered((10, 10, 10), 1.0, (0, 0, 0))  # 480 mm below the orbit
    with pytest.raises(ValueError, match="no view sees"):
        fdk_reconstruct(proj, geometry, elsewhere)
    with pytest.raises(ValueError, match="filter window"):
        fdk_reconstruct(proj, geometry, GRID, window="hamming")
    short = circular_orbit(20, 600, 1000, PANEL, arc_deg=182, isocenter_mm=ISO)
    with pytest.raises(ValueError, match="shorter than 180 deg plus the fan"):
        fdk_reconstruct(proj, short, GRID)
    with pytest.raises(ValueError, match="at least 3 views"):
        fdk_reconstruct(proj[:2], geometry[:2], GRID)


def _turned(geometry, turn_deg: float, mirror: bool = False):
    """The same views with every panel turned by ``turn_deg`` in its plane about its centre
    (and mirrored: e_u reversed)."""
    views = []
    for v in geometry:
        R = Rotation.from_rotvec(np.radians(turn_deg) * v.normal).as_matrix()
        e_u, e_v = R @ v.e_u, R @ v.e_v
        views.append(
            View.from_center(v.source_mm, v.detector_center_mm, -e_u if mirror else e_u, e_v, SL)
        )
    return Geometry(views)


SL = DetectorSpec(rows=96, cols=96, pixel_pitch_mm=1.6)
SL_GRID = VolumeGrid.centered((64, 64, 64), 1.0, (0.0, 0.0, 0.0))


@pytest.mark.parametrize(
    ("turn_deg", "mirror", "exact"), [(90.0, False, True), (90.0, True, True), (30.0, False, False)]
)
def test_a_panel_turned_in_its_plane_reconstructs_like_an_upright_one(
    turn_deg, mirror, exact, measured
):
    """RTK's analytic Shepp-Logan projections (data made elsewhere) through a circular orbit
    whose panel is upright, turned a quarter (rows along the axis, RTK stores SID < 0 for
    it), mirrored, or turned 30 degrees, against RTK's drawn phantom. A quarter turn and a
    mirror are exact re-indexings: the same RMSE. A 30 degree turn is resampled (cubic, at
    half the pitch, same band in cycles/mm): no worse than the upright panel by 2 %."""
    upright = circular_orbit(120, 600, 1000, SL)
    x, y, z = SL_GRID.axes_mm()
    inside = (np.abs(z) < 24)[:, None, None] & (np.hypot(*np.meshgrid(x, y)) < 24)[None]

    def rmse(geometry):
        projections, truth = rtk_shepp_logan(geometry, SL_GRID, 28.0)
        volume = fdk_reconstruct(projections, geometry, SL_GRID).volume.data
        return float(np.sqrt(np.mean((volume - truth)[inside] ** 2)))

    reference, turned = rmse(upright), rmse(_turned(upright, turn_deg, mirror))
    if exact:
        measured("rmse_turned_rel_change", abs(turned / reference - 1), below=1e-5)
    else:
        measured("rmse_turned_excess", turned / reference - 1.0, below=0.02)
