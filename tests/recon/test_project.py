"""recon.project: Joseph forward projector and voxel-driven backprojector."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from recon import project
from recon.geometry import DetectorSpec, Geometry, circular_orbit, helical_orbit
from recon.project import (
    FDK_WEIGHT,
    JosephProjector,
    backproject,
    backproject_weighted,
    centre_chords,
    forward_project,
)
from recon.rtk_peer import rtk_forward_project
from recon.volume import VolumeGrid

PANEL = DetectorSpec(rows=64, cols=80, pixel_pitch_mm=1.0)
ISO = (0.0, 0.0, 480.0)
GRID = VolumeGrid.centered((48, 48, 40), 1.0, ISO)


def smooth_random(shape, sigma, seed):
    field = gaussian_filter(np.random.default_rng(seed).random(shape), sigma)
    return (field - field.mean()).astype(np.float32)


def test_adjoint_identity_holds_to_the_interpolation_error(seed, measured):
    """<A x, y> = <x, A^T y> for smooth non-negative x, y on a wide-fan orbit.

    Joseph's ray-driven A and the voxel-driven A^T discretise the same integral with bilinear
    interpolation on different grids, so they agree to the interpolation error, O(h^2 /
    sigma^2) for fields smooth over sigma = 2-3 samples: we measure 1.7e-3 and allow 5e-3. The
    fan here (SDD 130 mm, 96 mm panel) makes the ray-density factor 1 / cos(theta) worth 2 %
    across the support, and the 1 / w^3 depth weight a factor of ~2, so an error in either
    form breaks the identity by more than the tolerance.
    """
    panel = DetectorSpec(rows=64, cols=96, pixel_pitch_mm=1.0)
    geometry = helical_orbit(
        24, 80, 130, panel, arc_deg=300, z_start_mm=-6, z_end_mm=6, isocenter_mm=ISO
    )
    x = gaussian_filter(_inside_ball(GRID, 16.0), 2).astype(np.float32)
    y = (1 + smooth_random((24, 64, 96), (0, 3, 3), seed=2 + seed)).astype(np.float32)
    lhs = float(np.sum(forward_project(x, GRID, geometry).astype(np.float64) * y))
    adjoint = backproject(y, geometry, GRID)
    rhs = float(np.sum(x.astype(np.float64) * adjoint))
    measured("adjoint_rel_error", abs(rhs / lhs - 1), below=5e-3)
    plain = np.zeros(GRID.shape, dtype=np.float32)  # 1 / w^2 only, as FDK weighs
    backproject_weighted(y, geometry, GRID, FDK_WEIGHT, plain)
    inside = _inside_ball(GRID, 16.0) > 0
    density = adjoint[inside] / plain[inside]
    assert density.min() / density.max() < 1 - 2 * 5e-3


def _inside_ball(grid: VolumeGrid, radius: float) -> np.ndarray:
    x, y, z = grid.axes_mm()
    c = grid.center_mm
    r2 = (z - c[2])[:, None, None] ** 2 + (y - c[1])[None, :, None] ** 2 + (x - c[0]) ** 2
    return (r2 < radius**2).astype(np.float32)


@pytest.mark.parametrize("angle_index", [0, 1, 5, 9])
def test_points_land_on_the_pixels_p_predicts(make_ball, angle_index, measured):
    """A small ball's projected centroid sits where P maps its centre (no flips, no offsets).

    A 1.5 mm ball spans ~3 pixels; its footprint is symmetric to first order, so the centroid
    matches to well under a tenth of a pixel (perspective skews it by ~r^2/SID^2 pixels).
    """
    geometry = circular_orbit(12, 600, 1000, PANEL, isocenter_mm=ISO)
    view = geometry[angle_index]
    errors = []
    for center in ((12.0, -7.0, 489.0), (-15.0, 10.0, 470.0)):
        image = forward_project(
            make_ball(GRID, center, 1.5), GRID, geometry[angle_index : angle_index + 1]
        )[0]
        rows, cols = np.mgrid[: image.shape[0], : image.shape[1]]
        centroid = np.array([(cols * image).sum(), (rows * image).sum()]) / image.sum()
        errors.append(np.abs(centroid - view.project(center)[0]).max())
    measured("centroid_error_px", max(errors), below=0.05)


def test_asymmetric_phantom_seen_from_the_front_is_not_mirrored(make_ball):
    """AP view (angle 0, source anterior): a ball at the patient's left (+x) appears at higher
    u, a ball above the isocentre (+z) at higher v (rows increase upward)."""
    geometry = circular_orbit(4, 600, 1000, PANEL, isocenter_mm=ISO)[:1]
    left = forward_project(make_ball(GRID, (12.0, 0.0, 480.0), 3.0), GRID, geometry)[0]
    up = forward_project(make_ball(GRID, (0.0, 0.0, 492.0), 3.0), GRID, geometry)[0]
    center_u, center_v = (80 - 1) / 2, (64 - 1) / 2
    v_left, u_left = np.unravel_index(np.argmax(left), left.shape)
    v_up, u_up = np.unravel_index(np.argmax(up), up.shape)
    assert u_left > center_u + 15 and abs(v_left - center_v) <= 1
    assert v_up > center_v + 15 and abs(u_up - center_u) <= 1


def test_ball_projections_match_analytic_chords(make_ball, measured):
    """Line integrals of a ball equal 2 sqrt(r^2 - d^2) per unit value.

    Interpolation blurs the voxelised ball by ~h / 2 (h = 1 mm); away from the rim (d < 0.8 r)
    that lowers chords by about |f''| sigma^2 / 2 <= 0.1 mm, and at the grazing rim, where the
    chord grows like 2 sqrt(2 r delta), by at most 2 sqrt(r h) = 7.7 mm.
    """
    geometry = circular_orbit(6, 600, 1000, PANEL, isocenter_mm=ISO)
    center, radius = np.array([3.0, -2.0, 482.0]), 15.0
    proj = forward_project(make_ball(GRID, center, radius, supersample=4), GRID, geometry)
    rmse, worst = [], []
    for i, view in enumerate(geometry):
        u, v = np.meshgrid(np.arange(80), np.arange(64))
        rays = view.pixel_to_world(u, v) - view.source_mm
        rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
        oc = center - view.source_mm
        d2 = oc @ oc - (rays @ oc) ** 2
        chord = 2 * np.sqrt(np.clip(radius**2 - d2, 0, None))
        inner = chord > 2 * radius * np.sqrt(1 - 0.8**2)
        rmse.append(np.sqrt(np.mean((proj[i] - chord)[inner] ** 2)))
        worst.append(np.abs(proj[i] - chord).max())
    measured("chord_rmse_mm", max(rmse), below=0.15)
    measured("chord_max_error_mm", max(worst), below=2 * np.sqrt(radius * 1.0))


def test_matches_rtk_joseph_projector(seed, measured):
    """Same algorithm (Joseph, bilinear): for an object inside the grid (the toolkits treat the
    grid's outer faces differently) differences are float32 rounding."""
    geometry = helical_orbit(
        10, 600, 1000, PANEL, arc_deg=360, z_start_mm=-10, z_end_mm=10, isocenter_mm=ISO
    )
    volume = np.abs(smooth_random(GRID.shape, 2, seed=5 + seed)) * _inside_ball(GRID, 18.0)
    ours = forward_project(volume, GRID, geometry)
    theirs = rtk_forward_project(volume, GRID, geometry)
    rel_rmse = np.sqrt(np.mean((ours - theirs) ** 2)) / np.sqrt(np.mean(theirs**2))
    measured("rel_rmse_vs_rtk", rel_rmse, below=1e-5)


def test_at_the_boundary_ours_is_rtk_on_the_volume_padded_with_zeros(seed, measured):
    """The boundary convention (recon/project.py): voxels are cubes. On a volume whose outer
    voxels are not zero, ours equals RTK's Joseph projector run on the volume padded with two
    layers of zero voxels, to float32 rounding; RTK on the volume as it is stops at the outer
    voxel centres, so through a uniform volume every ray that enters and leaves through the
    two faces across its main axis reads exactly one step along that axis less (the step:
    one voxel's length along the ray, ``h |d| / |d_k|``)."""
    geometry = circular_orbit(5, 600, 1000, PANEL, isocenter_mm=ISO)
    volume = (1.0 + np.abs(smooth_random(GRID.shape, 2, seed=4 + seed))).astype(np.float32)
    ours = forward_project(volume, GRID, geometry)
    pad = 2
    padded_grid = VolumeGrid(
        tuple(n + 2 * pad for n in GRID.shape),
        GRID.spacing_mm,
        tuple(np.asarray(GRID.origin_mm) - pad * np.asarray(GRID.spacing_mm)),
    )
    padded = rtk_forward_project(np.pad(volume, pad), padded_grid, geometry)
    measured("max_diff_vs_rtk_padded_rel", np.abs(ours - padded).max() / ours.max(), below=1e-5)

    mu = 0.02  # 1/mm
    uniform = np.full(GRID.shape, mu, dtype=np.float32)
    lost = forward_project(uniform, GRID, geometry) - rtk_forward_project(uniform, GRID, geometry)
    lo = np.asarray(GRID.origin_mm)  # the outer voxel centres
    hi = lo + (np.asarray(GRID.size_xyz) - 1) * np.asarray(GRID.spacing_mm)
    h = GRID.spacing_mm[0]
    crossing, step_errors = 0, []
    for i, view in enumerate(geometry):
        u, v = np.meshgrid(np.arange(PANEL.cols), np.arange(PANEL.rows))
        rays = view.pixel_to_world(u, v) - view.source_mm
        k = np.argmax(np.abs(rays), axis=-1)
        d_k = np.take_along_axis(rays, k[..., None], axis=-1)[..., 0]
        step = h * np.linalg.norm(rays, axis=-1) / np.abs(d_k)
        # where the ray meets the planes of the outer centres across k: a voxel inside them?
        inside = np.ones(k.shape, dtype=bool)
        for plane in (lo, hi):
            hit = view.source_mm + ((plane[k] - view.source_mm[k]) / d_k)[..., None] * rays
            within = (hit >= lo + h) & (hit <= hi - h)
            np.put_along_axis(within, k[..., None], True, axis=-1)
            inside &= np.all(within, axis=-1)
        crossing += inside.sum()
        expected = mu * step[inside]
        step_errors.append(np.abs(lost[i][inside] - expected) / np.abs(expected))
    assert crossing > 0.3 * lost.size
    measured("lost_step_rel_error", np.concatenate(step_errors).max(), below=1e-4)


def test_centre_chords_are_rtks_ray_box_lengths(measured):
    """Each ray's length between the outer voxel centres is what RTK's Joseph projector reads
    through a volume of ones (it stops there), for views off the grid's mid-plane too; rays
    that pass beside the grid read 0."""
    geometry = helical_orbit(
        8, 600, 1000, PANEL, arc_deg=360, z_start_mm=-30, z_end_mm=30, isocenter_mm=ISO
    )
    chords = centre_chords(geometry, GRID)
    theirs = rtk_forward_project(np.ones(GRID.shape, np.float32), GRID, geometry)
    assert (chords == 0).any() and (chords > 0).mean() > 0.3
    measured("max_diff_rel", np.abs(chords - theirs).max() / theirs.max(), below=1e-5)


def test_bad_input_is_refused_before_projecting():
    geometry = circular_orbit(4, 600, 1000, PANEL, isocenter_mm=ISO)
    with pytest.raises(ValueError, match="does not match grid shape"):
        forward_project(np.zeros((3, 3, 3)), GRID, geometry)
    bad = np.zeros(GRID.shape, dtype=np.float32)
    bad[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        forward_project(bad, GRID, geometry)
    far = VolumeGrid.centered((48, 48, 40), 30.0, ISO)  # 1.4 m wide: reaches behind sources
    with pytest.raises(ValueError, match="behind the source of view 0"):
        forward_project(np.zeros(far.shape), far, geometry)
    with pytest.raises(ValueError, match="the geometry needs"):
        backproject(np.zeros((3, 64, 80)), geometry, GRID)


def test_a_projector_of_a_padded_volume_projects_as_one_that_pads_it():
    """``JosephProjector.of_padded`` holds an array laid out with ``PAD`` zero voxels per side
    as it is and projects as a projector given the bare volume; a layout that does not fit
    the grid is refused with both shapes."""
    volume = np.abs(smooth_random(GRID.shape, 3.0, 5)).astype(np.float32)
    padded = np.pad(volume, JosephProjector.PAD)
    views = circular_orbit(3, 600, 1000, PANEL, isocenter_mm=ISO)
    expected = JosephProjector(volume, GRID).project(views)
    assert expected.max() > 0.0
    assert np.array_equal(JosephProjector.of_padded(padded, GRID).project(views), expected)
    with pytest.raises(ValueError, match=r"float32 of shape .* for grid shape"):
        JosephProjector.of_padded(volume, GRID)
    with pytest.raises(ValueError, match="float64"):
        JosephProjector.of_padded(padded.astype(np.float64), GRID)


def test_projecting_a_moved_volume_equals_projecting_through_the_inversely_moved_view():
    """``project_moved(view, T)`` is the shortcut of ``project`` through
    ``view.transformed(inv(T))``: the same kernel on the same rays, so equal to float32
    rounding; a motion that puts the grid behind the source is refused. Several motions in
    one call (``project_moved_many``) give each one's render to the bit."""
    from scipy.spatial.transform import Rotation

    volume = np.abs(smooth_random(GRID.shape, 3.0, 7))
    projector = JosephProjector(volume, GRID)
    view = circular_orbit(3, 600, 1000, PANEL, isocenter_mm=ISO)[1]
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [7, -12, 25], degrees=True).as_matrix()
    T[:3, 3] = (3.0, -5.0, 8.0)
    T[:3, 3] += np.asarray(ISO) - T[:3, :3] @ np.asarray(ISO)  # about the isocentre
    reference = projector.project(Geometry([view.transformed(np.linalg.inv(T))]))[0]
    unmoved = projector.project(Geometry([view]))[0]
    assert np.abs(reference - unmoved).max() > 0.1 * reference.max() > 0.0  # a real motion
    np.testing.assert_allclose(
        projector.project_moved(view, T), reference, atol=1e-5 * reference.max()
    )
    behind = np.eye(4)
    behind[:3, 3] = 3.0 * (view.source_mm - np.asarray(ISO))  # the grid far beyond the source
    with pytest.raises(ValueError, match="behind the source"):
        projector.project_moved(view, behind)
    # several motions at once: each exactly its own render, the batch refused with one behind
    Ts = np.stack([T, np.eye(4), np.linalg.inv(T)])
    many = projector.project_moved_many(view, Ts)
    assert many.shape == (3, view.rows, view.cols)
    for k, moved in enumerate(Ts):
        assert np.array_equal(many[k], projector.project_moved(view, moved))
    assert np.array_equal(many[1], unmoved)
    with pytest.raises(ValueError, match="behind the source"):
        projector.project_moved_many(view, np.stack([T, behind]))


def test_rotated_ellipsoid_projections_match_its_analytic_line_integrals(measured):
    """A tilted ellipsoid (semi-axes 18, 11, 7 mm) rasterised with partial volume projects to
    its exact chord lengths: away from the rim (chord > 60 % of the longest) within the
    interpolation blur of a 1 mm grid, ~0.1 mm RMS."""
    from scipy.spatial.transform import Rotation

    from sim.phantoms.ellipsoids import Ellipsoid, project_ellipsoids, rasterize_ellipsoids

    shape = Ellipsoid(
        center_mm=(4.0, -3.0, 483.0),
        semi_axes_mm=(18.0, 11.0, 7.0),
        rotation=Rotation.from_euler("xyz", [25, -40, 70], degrees=True),
        value=1.0,
    )
    geometry = helical_orbit(
        5, 600, 1000, PANEL, arc_deg=300, z_start_mm=-4, z_end_mm=4, isocenter_mm=ISO
    )
    ours = forward_project(rasterize_ellipsoids([shape], GRID, supersample=4), GRID, geometry)
    exact = project_ellipsoids([shape], geometry)
    inner = exact > 0.6 * exact.max()
    measured("chord_rmse_mm", np.sqrt(np.mean((ours - exact)[inner] ** 2)), below=0.15)
    # the footprint is where P puts it: the projected centre lies inside the shadow's core
    for i, view in enumerate(geometry):
        u, v = view.project(shape.center_mm)[0]
        assert exact[i, round(v), round(u)] > 0.6 * exact[i].max()


@pytest.mark.parametrize("orbit", ["circular", "helix"])
def test_the_upright_backprojector_is_the_general_one_to_float_rounding(orbit, seed, measured):
    """Orbits about z with upright panels take :func:`recon.project._upright_kernel` (u and w
    computed once per voxel column, v stepped along z); it sums what the general kernel sums,
    with every job shape of :data:`recon.project.UPRIGHT_ROWS_BY_L2` (whatever this host's L2).

    The two place a sample's v by different float32 roundings of the same quotient (a few ulp
    of v <= 64 px: ~2e-5 px), so each sample differs by at most 1e-4 px times the image's
    largest step between neighbouring pixels times its weight; the bound adds that over the
    views. Images vanish near the panel's edge so that no voxel sits within rounding of it.
    """
    if orbit == "circular":
        geometry = circular_orbit(20, 600, 1000, PANEL, isocenter_mm=ISO)
    else:
        geometry = helical_orbit(
            20, 600, 1000, PANEL, arc_deg=360, z_start_mm=-20, z_end_mm=20, isocenter_mm=ISO
        )
    assert project.upright(geometry, GRID)
    images = 1 + smooth_random((20, 64, 80), (0, 2, 2), seed=5 + seed)
    images[:, :3] = images[:, -3:] = images[:, :, :3] = images[:, :, -3:] = 0.0
    quads = project.quad_pairs(project.pixel_quads(images))
    ones, matrices = np.ones(20, np.float32), np.asarray(geometry.matrices)
    origin, spacing = np.array(GRID.origin_mm), np.array(GRID.spacing_mm)
    general = np.zeros(GRID.shape, np.float32)
    project._backproject_kernel(
        quads,
        ones,
        matrices,
        np.asarray(geometry.sources_mm),
        np.zeros(3),
        FDK_WEIGHT,
        np.ones((1, 80), np.float32),
        False,
        origin,
        spacing,
        general,
    )
    step = max(np.abs(np.diff(images, axis=a)).max() for a in (1, 2))
    depth = np.einsum("vk,ck->vc", matrices[:, 2], _corners(GRID))
    bound = 1e-4 * step * float(np.sum(1.0 / depth.min(axis=1) ** 2))
    assert general.max() > 100 * bound  # the volumes hold something
    upright = np.zeros(GRID.shape, np.float32)
    backproject_weighted(images, geometry, GRID, FDK_WEIGHT, upright)  # this host's shape
    worst = np.abs(upright - general).max()
    for _, (z_rows, y_rows) in project.UPRIGHT_ROWS_BY_L2:
        upright = np.zeros(GRID.shape, np.float32)
        project._upright_kernel(quads, ones, matrices, origin, spacing, z_rows, y_rows, upright)
        worst = max(worst, np.abs(upright - general).max())
    measured("upright_max_diff_over_bound", worst / bound, below=1.0)


def test_a_tilted_orbit_is_not_upright():
    """An orbit whose axis leans 2 degrees from z moves u and w along z by far more than the
    tolerance: the general kernel takes it."""
    from scipy.spatial.transform import Rotation

    geometry = circular_orbit(8, 600, 1000, PANEL, isocenter_mm=ISO)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("x", 2, degrees=True).as_matrix()
    T[:3, 3] = np.asarray(ISO) - T[:3, :3] @ np.asarray(ISO)
    tilted = Geometry([v.transformed(T) for v in geometry])
    assert project.upright(geometry, GRID) and not project.upright(tilted, GRID)


def _corners(grid: VolumeGrid) -> np.ndarray:
    return np.hstack((grid.corners_mm(), np.ones((8, 1))))


def test_column_weights_count_as_the_product_image_does(seed):
    """The views' count (COUNT_WEIGHT) of a shared row profile times per-view column weights
    is the count of the product images: the bilinear footprint of a row profile times a column
    profile is the product of their linear interpolations, so the two differ by float32
    rounding of each sample's weight (a few ulp) summed over the views."""
    geometry = circular_orbit(20, 600, 1000, PANEL, isocenter_mm=ISO)
    rng = np.random.default_rng(seed)
    rows = rng.uniform(0.2, 1.0, 64).astype(np.float32)
    columns = rng.uniform(0.0, 1.0, (20, 80)).astype(np.float32)
    axis = np.array([0.0, 0.0, 1.0])
    product = np.zeros(GRID.shape, np.float32)
    images = rows[None, :, None] * columns[:, None, :]
    backproject_weighted(images, geometry, GRID, project.COUNT_WEIGHT, product, axis)
    apart = np.zeros(GRID.shape, np.float32)
    shared = np.repeat(rows[None, :, None], 80, axis=2)
    backproject_weighted(shared, geometry, GRID, project.COUNT_WEIGHT, apart, axis, None, columns)
    assert product.max() > 0
    np.testing.assert_allclose(apart, product, rtol=1e-5, atol=1e-6 * product.max())
