"""Tests of sim.phantoms: exact ellipsoid integrals, Shepp–Logan, the standing knee phantom."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from pydantic import ValidationError
from scipy import ndimage
from scipy.spatial.transform import Rotation

from recon.config import ConfigError, load_config
from recon.geometry import DetectorSpec, circular_orbit
from recon.volume import VolumeGrid
from registration.labels import LABELS
from sim.phantoms import (
    Ellipsoid,
    KneePhantomSpec,
    attenuation_per_mm,
    ellipsoid_line_integrals,
    knee_bone_poses,
    knee_grid,
    knee_landmarks,
    knee_sdf,
    label_points,
    project_ellipsoids,
    rasterize_ellipsoids,
    rasterize_knee,
    shepp_logan_3d,
)

CONFIG = Path(__file__).resolve().parents[2] / "configs" / "phantoms" / "knee.yaml"


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    c = abs(float(np.dot(a, b))) / (np.linalg.norm(a) * np.linalg.norm(b))
    return math.degrees(math.acos(min(1.0, c)))


# -- ellipsoids ----------------------------------------------------------------------------


def test_sphere_chords_are_exact():
    rng = np.random.default_rng(1)
    center, r, value = np.array([10.0, -5.0, 3.0]), 25.0, 0.02
    sphere = Ellipsoid(center, (r, r, r), value=value)
    n = 500
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    other = np.cross(direction, rng.normal(size=(n, 3)))
    other /= np.linalg.norm(other, axis=1, keepdims=True)
    d = rng.uniform(0.0, 30.0, n)  # distance of the line from the centre, some miss
    closest = center + d[:, None] * other
    got = ellipsoid_line_integrals(
        [sphere], closest - 100.0 * direction, closest + 100.0 * direction
    )
    expected = value * 2.0 * np.sqrt(np.maximum(r * r - d * d, 0.0))
    np.testing.assert_allclose(got, expected, rtol=1e-10, atol=1e-12)


def test_chords_are_clipped_to_the_segment():
    sphere = Ellipsoid((0.0, 0.0, 0.0), (10.0, 10.0, 10.0), value=1.0)
    starts = np.array([[0.0, 0.0, 0.0], [-3.0, 0.0, 0.0], [-50.0, 0.0, 0.0], [-50.0, 4, 0]])
    ends = np.array([[0.0, 0.0, 40.0], [4.0, 0.0, 0.0], [-20.0, 0.0, 0.0], [50.0, 4, 0]])
    got = ellipsoid_line_integrals([sphere], starts, ends)
    # from the centre out: r; inside: the whole segment; short of the sphere: 0; through
    np.testing.assert_allclose(got, [10.0, 7.0, 0.0, 2.0 * math.sqrt(84.0)], rtol=1e-12)


def test_rotated_ellipsoid_matches_numerical_integration():
    rot = Rotation.from_euler("zyx", [30.0, 20.0, -40.0], degrees=True)
    center, axes = np.array([4.0, -2.0, 7.0]), np.array([30.0, 12.0, 7.0])
    e = Ellipsoid(center, axes, rot, value=1.5)
    # along the ellipsoid's own first axis through its centre: exactly 2a
    a_dir = rot.apply([1.0, 0.0, 0.0])
    along = ellipsoid_line_integrals([e], center - 80 * a_dir, center + 80 * a_dir)
    assert along[0] == pytest.approx(1.5 * 2 * 30.0, rel=1e-12)
    # random segments vs midpoint-rule integration of the indicator (independent transform:
    # Rotation.inv().apply); each chord has 2 ends, each misplaced by at most one step
    rng = np.random.default_rng(2)
    starts = center + rng.uniform(-60, 60, (40, 3))
    ends = center + rng.uniform(-60, 60, (40, 3))
    got = ellipsoid_line_integrals([e], starts, ends)
    m = 20000
    t = (np.arange(m) + 0.5) / m
    for s, q, g in zip(starts, ends, got, strict=True):
        pts = s + t[:, None] * (q - s)
        inside = np.sum((rot.inv().apply(pts - center) / axes) ** 2, axis=1) <= 1.0
        length = np.linalg.norm(q - s)
        assert abs(g - 1.5 * inside.mean() * length) <= 1.5 * 2 * length / m + 1e-9


def test_projection_of_a_sphere_at_the_isocentre():
    det = DetectorSpec(rows=31, cols=41, pixel_pitch_mm=2.0)
    iso = np.array([0.0, 0.0, 480.0])
    geo = circular_orbit(4, sid_mm=500.0, sdd_mm=1000.0, detector=det, isocenter_mm=iso)
    r, value = 40.0, 0.02
    proj = project_ellipsoids([Ellipsoid(iso, (r, r, r), value=value)], geo)
    assert proj.shape == (4, 31, 41) and proj.dtype == np.float32
    # the central pixel's ray passes through the isocentre: a full diameter
    np.testing.assert_allclose(proj[:, 15, 20], value * 2 * r, rtol=1e-6)
    # every pixel: 2 sqrt(r^2 - d^2), d = distance of the pixel's ray from the centre
    for k, view in enumerate(geo):
        vv, uu = np.mgrid[0:31, 0:41]
        px = view.pixel_to_world(uu, vv)
        ray = px - view.source_mm
        ray /= np.linalg.norm(ray, axis=-1, keepdims=True)
        d = np.linalg.norm(np.cross(iso - view.source_mm, ray), axis=-1)
        expected = value * 2 * np.sqrt(np.maximum(r * r - d * d, 0.0))
        np.testing.assert_allclose(proj[k], expected, atol=2e-6)


def test_rasterised_ellipsoid_volume_and_orientation():
    rot = Rotation.from_euler("xyz", [10.0, 25.0, 40.0], degrees=True)
    axes = np.array([20.0, 14.0, 9.0])
    e = Ellipsoid((1.3, -0.7, 0.4), axes, rot, value=1.0)
    grid = VolumeGrid.centered((56, 56, 56), 1.0)
    vol = rasterize_ellipsoids([e], grid, supersample=4)
    assert vol.dtype == np.float32 and vol.shape == grid.shape
    # the errors of the sub-cells the surface cuts (each at most h^3) largely cancel: ~0.02 %
    assert vol.sum() * grid.voxel_volume_mm3 == pytest.approx(e.volume_mm3, rel=1e-3)
    assert vol.max() == pytest.approx(1.0) and vol.min() == 0.0
    # the long axis of the rasterised body is the ellipsoid's first axis
    x, y, z = grid.axes_mm()
    pts = np.stack(np.meshgrid(x, y, z, indexing="ij"), -1).transpose(2, 1, 0, 3).reshape(-1, 3)
    w = vol.reshape(-1).astype(np.float64)
    mean = (w[:, None] * pts).sum(0) / w.sum()
    cov = ((w[:, None] * (pts - mean)).T @ (pts - mean)) / w.sum()
    np.testing.assert_allclose(mean, e.center_mm, atol=0.02)
    # uniform solid ellipsoid: variance a^2 / 5 along each own axis
    np.testing.assert_allclose(np.linalg.eigvalsh(cov)[::-1], axes**2 / 5, rtol=0.01)
    assert _angle_deg(np.linalg.eigh(cov)[1][:, -1], rot.apply([1.0, 0.0, 0.0])) < 0.5


def test_partial_volume_of_a_small_sphere():
    # a 2.5 mm sphere on a 1 mm grid: centre sampling alone errs by up to 10 % depending on
    # where the centre falls; 8 x 8 x 8 sub-samples per voxel keep it within 0.5 %
    grid = VolumeGrid.centered((12, 12, 12), 1.0)
    for center in np.random.default_rng(3).uniform(-0.5, 0.5, (10, 3)):
        e = Ellipsoid(center, (2.5, 2.5, 2.5))
        vol = rasterize_ellipsoids([e], grid, supersample=8)
        assert vol.sum() == pytest.approx(e.volume_mm3, rel=5e-3)
        assert np.count_nonzero((vol > 0) & (vol < 1)) > 30  # surface voxels are fractional


def _value_at(phantom, point) -> float:
    """Phantom value at one point: a 1-voxel grid centred there, no sub-sampling."""
    grid = VolumeGrid(shape=(1, 1, 1), spacing_mm=(0.01, 0.01, 0.01), origin_mm=point)
    return float(rasterize_ellipsoids(phantom, grid)[0, 0, 0])


@pytest.mark.parametrize(("modified", "skull", "brain"), [(True, 1.0, 0.2), (False, 2.0, 1.02)])
def test_shepp_logan_values_and_axes(modified, skull, brain):
    c, s = np.array([5.0, -3.0, 200.0]), 100.0
    phantom = shepp_logan_3d(s, c, modified=modified)
    assert len(phantom) == 10
    assert _value_at(phantom, c) == pytest.approx(brain, abs=1e-6)
    # skull: inside the outer ellipsoid (z semi-axis 0.90) but not the inner one (0.88)
    assert _value_at(phantom, c + np.array([0, 0, 0.89]) * s) == pytest.approx(skull, abs=1e-6)
    # head-foot along world z: the outer semi-axes are x 0.69, y 0.92, z 0.90
    assert _value_at(phantom, c + np.array([0, 0.91, 0]) * s) == pytest.approx(skull, abs=1e-6)
    assert _value_at(phantom, c + np.array([0, 0, 0.91]) * s) == 0.0
    assert _value_at(phantom, c + np.array([0.70, 0, 0]) * s) == 0.0
    # ellipsoid e at (0, 0.35, -0.25) adds 0.2 (modified) or 0.02 (original)
    extra = 0.2 if modified else 0.02
    assert _value_at(phantom, c + np.array([0, 0.35, -0.25]) * s) == pytest.approx(
        brain + extra, abs=1e-6
    )


# -- knee phantom ----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def knees():
    """Right and left knees at zero flexion on the default 1 mm field of view."""
    right = KneePhantomSpec()
    grid = knee_grid(right, spacing_mm=1.0)
    out = {"grid": grid}
    for side in ("right", "left"):
        spec = right.model_copy(update={"side": side})
        out[side] = (spec, *rasterize_knee(spec, grid, supersample=2))
    return out


def _centroid(grid: VolumeGrid, mask: np.ndarray) -> np.ndarray:
    iz, iy, ix = np.nonzero(mask)
    return grid.index_to_world(np.stack((ix, iy, iz), axis=1)).mean(axis=0)


def test_knee_grid_covers_the_knee(knees):
    grid = knees["grid"]
    assert grid.size_xyz == (140, 140, 160)
    np.testing.assert_allclose(grid.center_mm, (0.0, -4.0, 490.0))


def test_knee_labels_and_plausible_bone_volumes(knees):
    grid, (_, labels, mu) = knees["grid"], knees["right"]
    assert labels.dtype == np.uint8 and mu.dtype == np.float32
    assert set(np.unique(labels)) == set(LABELS.values())
    volume_cm3 = {
        name: np.count_nonzero(labels == LABELS[name]) * grid.voxel_volume_mm3 / 1000
        for name in ("femur", "tibia", "fibula", "patella")
    }
    # within this field of view (joint line -70 mm .. +90 mm): distal femur (~9 cm of
    # metaphysis and condyles, 75-85 mm wide at the epicondyles) 150-260 cm3; proximal tibia
    # (~7 cm below a 75 x 50 mm plateau) 100-200 cm3; fibular head and neck 5-20 cm3; an
    # adult patella (about 45 x 50 x 22 mm) 10-25 cm3
    ranges = {"femur": (150, 260), "tibia": (100, 200), "fibula": (5, 20), "patella": (10, 25)}
    for name, (lo, hi) in ranges.items():
        assert lo <= volume_cm3[name] <= hi, (name, volume_cm3[name])


def test_knee_attenuation_values(knees):
    grid, (spec, labels, mu) = knees["grid"], knees["right"]
    table = attenuation_per_mm(70.0)
    assert table["water"] == pytest.approx(0.1937 / 10)
    order = ["air", "fat", "marrow", "water", "muscle", "cancellous_bone", "cortical_bone"]
    assert all(table[a] < table[b] for a, b in itertools.pairwise(order))
    lm = knee_landmarks(spec)
    index = np.round(grid.world_to_index(lm["tibial_plateau_center"] - (0, 0, 20))).astype(int)
    assert mu[index[2], index[1], index[0]] == pytest.approx(table["cancellous_bone"], rel=1e-6)
    assert mu[0, 0, 0] == pytest.approx(table["air"], rel=1e-6)  # grid corner, outside the leg
    # between the skin and the bones, 30 mm anterior-lateral of the plateau: muscle
    index = np.round(grid.world_to_index(lm["tibial_plateau_center"] + (-25, -40, -40)))
    assert labels[int(index[2]), int(index[1]), int(index[0])] == LABELS["soft_tissue"]
    assert mu[int(index[2]), int(index[1]), int(index[0])] == pytest.approx(table["muscle"])


def test_femur_above_tibia_and_joint_space(knees):
    grid, (spec, labels, _) = knees["grid"], knees["right"]
    femur, tibia = labels == LABELS["femur"], labels == LABELS["tibia"]
    assert _centroid(grid, femur)[2] > _centroid(grid, tibia)[2] + 50
    # no 26-connected contact between femur and tibia (nor femur and patella)
    grown = ndimage.binary_dilation(femur, ndimage.generate_binary_structure(3, 3))
    assert not np.any(grown & tibia)
    assert not np.any(grown & (labels == LABELS["patella"]))
    # bone-free gap below the medial condyle's lowest point: joint_space_mm within a voxel
    lm = knee_landmarks(spec)
    ix, iy, _ = np.round(grid.world_to_index(lm["medial_condyle_lowest"])).astype(int)
    column = labels[:, iy, ix]
    z_femur = grid.axes_mm()[2][np.nonzero(column == LABELS["femur"])[0].min()]
    z_tibia = grid.axes_mm()[2][np.nonzero(column == LABELS["tibia"])[0].max()]
    assert abs((z_femur - z_tibia - 1.0) - spec.joint_space_mm) <= 1.0
    # the lowest femur voxel is the medial condyle landmark, within a voxel
    iz = np.nonzero(femur.any(axis=(1, 2)))[0].min()
    assert abs(grid.axes_mm()[2][iz] - lm["medial_condyle_lowest"][2]) <= 1.0


@pytest.mark.parametrize("side", ["right", "left"])
def test_fibula_is_lateral_and_posterior(knees, side):
    grid, (_, labels, _) = knees["grid"], knees[side]
    fibula = _centroid(grid, labels == LABELS["fibula"])
    tibia = _centroid(grid, labels == LABELS["tibia"])
    lateral = -1.0 if side == "right" else 1.0  # patient's right is world -x
    assert lateral * (fibula[0] - tibia[0]) > 20.0
    assert fibula[1] - tibia[1] > 10.0


def test_left_knee_is_the_mirror_of_the_right(knees):
    grid, (_, right, mu_r), (_, left, mu_l) = knees["grid"], knees["right"], knees["left"]
    mirrored = right[:, :, ::-1]
    assert np.count_nonzero(left != mirrored) <= 1e-5 * left.size
    for name in ("femur", "tibia", "fibula", "patella"):
        a = _centroid(grid, left == LABELS[name])
        b = _centroid(grid, mirrored == LABELS[name])
        assert np.all(np.abs(a - b) <= 1.0)
    assert float(np.abs(mu_l - mu_r[:, :, ::-1]).mean()) < 1e-6


@pytest.mark.parametrize("side", ["right", "left"])
def test_landmarks_lie_on_the_bones(side):
    spec = KneePhantomSpec(side=side, flexion_deg=40.0)
    lm = knee_landmarks(spec)
    medial = 1.0 if side == "right" else -1.0  # medial is toward the other leg
    for key, bone in (
        ("medial_condyle_lowest", "femur"),
        ("lateral_condyle_lowest", "femur"),
        ("medial_epicondyle", "femur"),
        ("lateral_epicondyle", "femur"),
        ("medial_plateau_lowest", "tibia"),
        ("lateral_plateau_lowest", "tibia"),
    ):
        assert abs(knee_sdf(spec, bone, lm[key])[0]) < 0.05, key
    for key in ("medial_condyle_lowest", "medial_epicondyle", "medial_plateau_lowest"):
        assert medial * (lm[key][0] - lm["knee_center"][0]) > 15.0, key
    for key in ("lateral_condyle_lowest", "lateral_epicondyle", "lateral_plateau_lowest"):
        assert medial * (lm[key][0] - lm["knee_center"][0]) < -15.0, key
    # nothing of the femur lies below the condyles' lowest points (flexed 40 degrees)
    u = np.linspace(-60.0, 60.0, 121)
    uu, vv = np.meshgrid(u, u)
    below = np.stack((uu.ravel(), vv.ravel() + lm["knee_center"][1], np.full(uu.size, 0.0)), axis=1)
    below[:, 2] = lm["medial_condyle_lowest"][2] - 0.05
    assert knee_sdf(spec, "femur", below).min() > 0.0
    np.testing.assert_allclose(np.linalg.norm(lm["femoral_mechanical_axis"]), 1.0)
    assert _angle_deg(lm["femoral_mechanical_axis"], lm["femoral_anatomical_axis"]) == (
        pytest.approx(6.0)
    )
    assert lm["tibial_plateau_center"][2] == pytest.approx(spec.joint_line_height_mm)


@pytest.mark.parametrize("flexion", [0.0, 60.0])
def test_flexion_between_the_long_axes(flexion):
    spec = KneePhantomSpec(flexion_deg=flexion)
    poses = knee_bone_poses(spec)
    for T in poses.values():
        np.testing.assert_allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-12)
    femur, tibia = poses["femur"], poses["tibia"]
    cos = float(femur[:3, 2] @ tibia[:3, 2])
    assert math.degrees(math.acos(min(1.0, cos))) == pytest.approx(flexion, abs=1e-6)
    # about the TEA: the femoral x axis stays the tibial x axis
    np.testing.assert_allclose(femur[:3, 0], tibia[:3, 0], atol=1e-12)
    # flexion swings the femoral shaft posteriorly (+y)
    assert femur[1, 2] >= 0.0


@pytest.mark.parametrize("flexion", [0.0, 30.0])
def test_patella_rides_in_the_trochlear_groove(flexion):
    spec = KneePhantomSpec(flexion_deg=flexion)
    T = knee_bone_poses(spec)["patella"]
    u = np.arange(-26.0, 26.0, 0.5)
    local = np.stack(np.meshgrid(u, np.arange(-5.0, 25.0, 0.5), u, indexing="ij"), -1)
    pts = local.reshape(-1, 3) @ T[:3, :3].T + T[:3, 3]
    femur, patella = knee_sdf(spec, "femur", pts), knee_sdf(spec, "patella", pts)
    near = (femur > -0.5) & (patella > -0.5)
    # the facets are offset radially (about the TEA) by the joint space, so the closest
    # approach is across the steeper lateral facet (22 degrees): joint_space * cos(22 deg)
    gap = float((femur + patella)[near].min())
    assert gap == pytest.approx(spec.joint_space_mm * math.cos(math.radians(22.0)), abs=0.05)
    # the patella slides distally along the femur as the knee flexes
    T_femur_patella = np.linalg.inv(knee_bone_poses(spec)["femur"]) @ T
    elevation = math.degrees(math.atan2(T_femur_patella[2, 3], -T_femur_patella[1, 3]))
    assert elevation == pytest.approx(10.0 - 0.7 * flexion)


def test_femoral_shaft_pca_follows_flexion():
    spec = KneePhantomSpec(flexion_deg=60.0)
    lm = knee_landmarks(spec)
    grid = VolumeGrid.centered((60, 110, 80), 1.5, lm["knee_center"] + (0.0, 60.0, 35.0))
    labels, _ = rasterize_knee(spec, grid, supersample=1)
    iz, iy, ix = np.nonzero(labels == LABELS["femur"])
    pts = grid.index_to_world(np.stack((ix, iy, iz), axis=1))
    # the shaft beyond the metaphyseal flare, cut by spheres about the knee centre (not by
    # the grid's faces, whose oblique cut would tilt the principal axis)
    r = np.linalg.norm(pts - lm["knee_center"], axis=1)
    shaft = pts[(r > 90.0) & (r < 140.0)]
    assert len(shaft) > 5000
    axis = np.linalg.eigh(np.cov((shaft - shaft.mean(0)).T))[1][:, -1]
    tibial_axis = knee_bone_poses(spec)["tibia"][:3, 2]
    assert abs(_angle_deg(axis, tibial_axis) - 60.0) < 2.0
    assert _angle_deg(axis, lm["femoral_anatomical_axis"]) < 2.0


def test_point_labels_match_the_raster_without_supersampling():
    spec = KneePhantomSpec(side="left", flexion_deg=20.0)
    grid = VolumeGrid.centered((50, 50, 60), 2.5, (0.0, -4.0, 490.0))
    labels, _ = rasterize_knee(spec, grid, supersample=1)
    x, y, z = grid.axes_mm()
    pts = np.stack(np.meshgrid(z, y, x, indexing="ij"), -1)[..., ::-1].reshape(-1, 3)
    np.testing.assert_array_equal(label_points(spec, pts).reshape(grid.shape), labels)


def test_config_file_is_the_complete_default_spec():
    data = yaml.safe_load(CONFIG.read_text(encoding="utf-8"))
    assert set(data) == set(KneePhantomSpec.model_fields)
    assert load_config(CONFIG, KneePhantomSpec) == KneePhantomSpec()


@pytest.mark.parametrize(
    ("update", "field"),
    [
        ({"flexion_deg": 120.0}, "flexion_deg"),
        ({"cortical_thickness_mm": 0.0}, "cortical_thickness_mm"),
        ({"side": "middle"}, "side"),
        ({"effective_energy_kev": 65.0}, "effective_energy_kev"),
        ({"scale": 1.3}, "soft_tissue_radius_mm"),
        ({"flexon_deg": 10.0}, "flexon_deg"),
    ],
)
def test_bad_spec_names_the_field(tmp_path, update, field):
    with pytest.raises(ValidationError, match=field):
        KneePhantomSpec(**update)
    bad = tmp_path / "knee.yaml"
    bad.write_text(yaml.safe_dump({**yaml.safe_load(CONFIG.read_text(encoding="utf-8")), **update}))
    with pytest.raises(ConfigError, match=field) as info:
        load_config(bad, KneePhantomSpec)
    assert str(bad) in str(info.value)
