"""Tests of sim.motion.squat_motion and sim.fluoro: exact knee flexion and coupled motions,
the moved-view invariance, frames that match direct projections of the phantom, the image
model's noise and distortion, and the files a sequence is saved to."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage
from scipy.spatial.transform import Rotation

from recon.config import load_protocol
from recon.geometry import DetectorSpec, Geometry
from recon.io import read_projections
from recon.project import forward_project
from recon.rtk_xml import read_rtk_geometry
from recon.volume import VolumeGrid
from registration.labels import LABELS
from registration.poses import poses_by_frame, read_poses
from sim.fluoro import (
    FLUORO_EXPOSURE,
    add_fluoro_noise,
    distort,
    lateral_view,
    move_view,
    save_sequence,
    simulate_fluoroscopy,
)
from sim.motion import BONES, KneeMotion, flexion_extension, squat_motion
from sim.phantoms.knee import (
    KneePhantomSpec,
    knee_bone_poses,
    knee_landmarks,
    rasterize_knee,
)
from sim.scan import ELECTRONIC_NOISE_PHOTONS

PROTOCOL = (
    Path(__file__).resolve().parents[2] / "configs" / "protocols" / "knee_fluoroscopy_lateral.yaml"
)
PANEL = DetectorSpec(rows=128, cols=128, pixel_pitch_mm=2.4)  # the 307 mm panel, 8 x 8 binned
SPEC = KneePhantomSpec()


def _rigid(rotvec_deg, translation_mm) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec_deg, degrees=True).as_matrix()
    T[:3, 3] = translation_mm
    return T


def _world_frames(motion, spec):
    reference = knee_bone_poses(spec)
    return {b: motion.poses[b] @ reference[b] for b in ("femur", "tibia")}


def _flexion_deg(femur: np.ndarray, tibia: np.ndarray) -> np.ndarray:
    """Angle from the femoral to the tibial long axis about the TEA (femur x), per frame."""
    fz, tz, tea = femur[:, :3, 2], tibia[:, :3, 2], femur[:, :3, 0]
    sine = np.einsum("ij,ij->i", np.cross(fz, tz), tea)
    return np.degrees(np.arctan2(sine, np.einsum("ij,ij->i", fz, tz)))


@pytest.fixture(scope="module")
def squat_sequence():
    """Ideal frames of a 5-frame squat 0 -> 90 -> 0 degrees, 1 mm voxels, 128^2 panel."""
    motion = squat_motion(SPEC, frames=5)
    return motion, simulate_fluoroscopy(
        SPEC, motion, lateral_view(SPEC, PANEL), voxel_mm=1.0, realism="ideal"
    )


# -- motion ------------------------------------------------------------------------------------


@pytest.mark.parametrize("side", ["right", "left"])
@pytest.mark.parametrize("seed", [None, 3])
def test_squat_flexion_is_exact_and_the_whole_leg_moves(side, seed):
    spec = KneePhantomSpec(side=side)
    motion = squat_motion(spec, frames=13, hyperextension_deg=5.0, seed=seed)
    world = _world_frames(motion, spec)
    np.testing.assert_allclose(
        _flexion_deg(world["femur"], world["tibia"]), motion.flexion_deg, rtol=0, atol=1e-6
    )
    assert motion.flexion_deg[0] == pytest.approx(motion.flexion_deg[-1])
    assert motion.flexion_deg[0] < 0.0 < motion.flexion_deg.max() <= 90.0
    peak = int(np.argmax(motion.flexion_deg))
    for bone in ("femur", "tibia", "fibula", "patella", "tibia_fibula"):
        assert np.abs(motion.poses[bone][peak] - np.eye(4)).max() > 0.1, bone
    np.testing.assert_array_equal(motion.poses["tibia_fibula"], motion.poses["tibia"])
    np.testing.assert_allclose(motion.poses["fibula"], motion.poses["tibia"], atol=1e-9)
    # the shank leans forward about the ankle: the knee moves anteriorly (-y)
    lean = Rotation.from_matrix(motion.poses["tibia"][peak][:3, :3]).magnitude()
    assert math.degrees(lean) > 5.0
    ankle = knee_landmarks(spec)["ankle_center"]
    T = motion.poses["tibia"][peak]
    np.testing.assert_allclose(T[:3, :3] @ ankle + T[:3, 3], ankle, atol=1e-9)
    assert motion.knee_center_mm[peak, 1] < motion.knee_center_mm[0, 1] - 30.0


def test_squat_rollback_and_tibial_rotation_have_the_documented_sizes():
    motion = squat_motion(SPEC, frames=7, rollback_mm_per_deg=0.12, tibial_rotation_deg=5.0)
    world = _world_frames(motion, SPEC)
    relative = np.linalg.inv(world["tibia"]) @ world["femur"]  # femur in the tibia's frame
    flexion = motion.flexion_deg
    np.testing.assert_allclose(motion.rollback_mm, 0.12 * flexion, atol=1e-12)
    np.testing.assert_allclose(motion.tibial_rotation_deg, 5.0 * flexion / 90.0, atol=1e-12)
    # the TEA midpoint rolls back along the tibia's posterior axis: 10.8 mm at 90 degrees
    origin0 = relative[0, :3, 3]
    np.testing.assert_allclose(relative[:, 1, 3] - origin0[1], 0.12 * flexion, atol=1e-9)
    np.testing.assert_allclose(relative[:, [0, 2], 3], relative[:1, [0, 2], 3].repeat(7, 0))
    assert relative[np.argmax(flexion), 1, 3] - origin0[1] == pytest.approx(10.8)
    # tibial internal rotation about its long axis: the TEA turns by the rotation, and the
    # tibia's anterior axis (-y) turns medially (+x for a right knee) in the femur's frame
    tea_angle = np.degrees(np.arctan2(-relative[:, 1, 0], relative[:, 0, 0]))
    np.testing.assert_allclose(tea_angle, motion.tibial_rotation_deg, atol=1e-9)
    tibia_in_femur = np.linalg.inv(world["femur"]) @ world["tibia"]
    assert tibia_in_femur[np.argmax(flexion), 0, 1] < -0.08  # -y_tibia . x_femur > 0
    # the femur's world origin is the knee centre reported by the motion
    np.testing.assert_allclose(world["femur"][:, :3, 3], motion.knee_center_mm, atol=1e-9)


def test_squat_seeds_vary_the_motion_repeatably():
    a, b, a_again = (squat_motion(SPEC, frames=21, seed=s) for s in (1, 2, 1))
    np.testing.assert_array_equal(a.flexion_deg, a_again.flexion_deg)
    assert not np.allclose(a.flexion_deg, b.flexion_deg)
    for m in (a, b):
        assert 81.0 <= m.flexion_deg.max() <= 90.0
        assert 0.8 * 5.0 <= m.tibial_rotation_deg.max() / (m.flexion_deg.max() / 90.0) <= 6.0
    with pytest.raises(ValueError, match="max_flexion_deg"):
        squat_motion(SPEC, max_flexion_deg=120.0)


def test_flexion_extension_keeps_the_tibia_still():
    motion = flexion_extension(SPEC, frames=5, max_flexion_deg=60.0)
    np.testing.assert_allclose(motion.poses["tibia"], np.broadcast_to(np.eye(4), (5, 4, 4)))
    world = _world_frames(motion, SPEC)
    np.testing.assert_allclose(_flexion_deg(world["femur"], world["tibia"]), motion.flexion_deg)
    assert not motion.rollback_mm.any() and not motion.tibial_rotation_deg.any()


# -- geometry ----------------------------------------------------------------------------------


def test_lateral_view_is_the_protocol_view():
    protocol = load_protocol(PROTOCOL)
    geometry = protocol.orbit.geometry(protocol.detector)
    view = lateral_view(SPEC, protocol.detector)
    assert len(geometry) == 30 and all(v == view for v in geometry)
    assert protocol.exposure == FLUORO_EXPOSURE
    assert view.source_mm[0] == pytest.approx(800.0)  # medial (+x) for a right knee
    assert view.e_v.tolist() == [0.0, 0.0, 1.0] and view.sdd_mm == pytest.approx(1200.0)
    centre = knee_landmarks(SPEC)["tibial_plateau_center"]
    np.testing.assert_allclose(view.project(centre)[0], [511.5, 511.5], atol=1e-9)
    left = lateral_view(KneePhantomSpec(side="left"), protocol.detector)
    assert left.source_mm[0] == pytest.approx(-800.0)


def test_moving_the_volume_equals_moving_the_view_the_other_way():
    view = lateral_view(SPEC, PANEL)
    rng = np.random.default_rng(4)
    points = rng.uniform(-60.0, 60.0, (50, 3)) + np.array([0.0, 0.0, 480.0])
    T = _rigid([4.0, -7.0, 20.0], [3.0, -12.0, 5.0])
    moved = points @ T[:3, :3].T + T[:3, 3]
    np.testing.assert_allclose(
        view.project(moved), move_view(view, np.linalg.inv(T)).project(points), atol=1e-9
    )
    # projections: a 90-degree turn about z plus a whole-voxel shift maps the lattice onto
    # itself, so the moved volume is sampled exactly; an anisotropic blob catches wrong turns
    grid = VolumeGrid.centered((41, 41, 41), 2.0, (0.0, 0.0, 480.0))
    ax, ay, az = grid.axes_mm()
    z, y, x = np.meshgrid(az, ay, ax, indexing="ij")
    pts = np.stack((x, y, z - 480.0), axis=-1)

    def blob(p: np.ndarray) -> np.ndarray:
        q = (p - [6.0, -4.0, 3.0]) / [8.0, 3.5, 5.0]
        return (0.02 * np.exp(-0.5 * (q**2).sum(axis=-1))).astype(np.float32)

    T = _rigid([0.0, 0.0, 90.0], [4.0, -6.0, 2.0])  # about the grid centre
    moved_blob = blob((pts - T[:3, 3]) @ T[:3, :3])  # f(T^-1 p) in centred coordinates
    about_center = np.eye(4)
    about_center[:3, 3] = grid.center_mm
    T_world = about_center @ T @ np.linalg.inv(about_center)
    direct = forward_project(moved_blob, grid, Geometry([view]))
    via_view = forward_project(blob(pts), grid, Geometry([move_view(view, np.linalg.inv(T_world))]))
    assert direct.max() > 0.1
    np.testing.assert_allclose(direct, via_view, rtol=0, atol=1e-5)


# -- rendering -----------------------------------------------------------------------------------


def test_reference_frame_is_the_projection_of_the_reference_phantom(squat_sequence):
    motion, seq = squat_sequence
    assert motion.flexion_deg[0] == 0.0 and seq.frames.shape == (5, 128, 128)
    reference = forward_project(seq.attenuation.data, seq.attenuation.grid, Geometry([seq.view]))
    assert reference.max() > 3.0  # a lateral knee: ~4 units through the condyles
    np.testing.assert_allclose(seq.frames[0], reference[0], rtol=0, atol=1e-4)
    assert seq.counts is None and seq.photons_per_pixel == 0.0
    np.testing.assert_allclose(seq.times_s, np.arange(5) / 15.0)
    # every frame keeps the knee in the field
    uv = seq.view.project(motion.knee_center_mm)
    assert np.all((uv > 10.0) & (uv < 117.0))


def test_a_rigid_motion_of_the_whole_leg_renders_as_the_moved_phantom():
    """All bones and the soft tissue moved by one T: the frame is the reference phantom seen
    through the view moved by T^-1 (the soft tissue is resampled, so to interpolation error)."""
    view = lateral_view(SPEC, PANEL)
    knee = knee_landmarks(SPEC)["knee_center"]
    T = _rigid([8.0, 0.0, -3.0], [3.0, -7.0, 4.0])
    T[:3, 3] += knee - T[:3, :3] @ knee  # turn about the knee centre
    poses = {b: np.stack((np.eye(4), T)) for b in (*BONES, "tibia_fibula")}
    zeros = np.zeros(2)
    centers = np.stack((knee, T[:3, :3] @ knee + T[:3, 3]))
    motion = KneeMotion(np.arange(2), zeros, zeros, poses, zeros, zeros, centers)
    seq = simulate_fluoroscopy(SPEC, motion, view, voxel_mm=1.0, realism="ideal")
    volume, grid = seq.attenuation.data, seq.attenuation.grid
    direct = forward_project(volume, grid, Geometry([move_view(view, np.linalg.inv(T))]))[0]
    error = np.abs(seq.frames[1] - direct)
    assert error.mean() < 0.005 and np.percentile(error, 99) < 0.05, error.max()
    backwards = forward_project(volume, grid, Geometry([move_view(view, T)]))[0]
    assert np.abs(seq.frames[1] - backwards).mean() > 10.0 * error.mean()


def test_bones_appear_where_the_true_poses_put_them():
    """A flexion-extension frame at 60 degrees matches the phantom rasterised at 60 degrees
    better than at 57 or 63 degrees inside the bones' shadow (median absolute difference: the
    soft tissue's shape differs between the two models, the bones do not)."""
    view = lateral_view(SPEC, PANEL)
    motion = flexion_extension(SPEC, frames=3, max_flexion_deg=60.0)  # 0, 60, 0 degrees
    seq = simulate_fluoroscopy(SPEC, motion, view, voxel_mm=1.0, realism="ideal")
    grid = seq.attenuation.grid
    direct, shadow = {}, None
    for flexion in (60.0, 57.0, 63.0):
        labels, mu = rasterize_knee(SPEC.model_copy(update={"flexion_deg": flexion}), grid, 2)
        direct[flexion] = forward_project(mu, grid, Geometry([view]))[0]
        if shadow is None:
            bones = (labels >= LABELS["femur"]).astype(np.float32)
            shadow = forward_project(bones, grid, Geometry([view]))[0] > 0.0
    errors = {f: float(np.median(np.abs(seq.frames[1] - d)[shadow])) for f, d in direct.items()}
    assert errors[60.0] < 0.7 * min(errors[57.0], errors[63.0]), errors


# -- image model ---------------------------------------------------------------------------------


def test_quantum_noise_is_poisson_plus_readout():
    rng = np.random.default_rng(0)
    p = np.full((300, 300), 1.5, dtype=np.float32)
    counts, noisy = add_fluoro_noise(p, 2000.0, rng)
    mean = 2000.0 * math.exp(-1.5)
    assert counts.mean() == pytest.approx(mean, rel=0.005)
    assert counts.var() == pytest.approx(mean + ELECTRONIC_NOISE_PHOTONS**2, rel=0.03)
    np.testing.assert_allclose(noisy, -np.log(counts / 2000.0), rtol=1e-5)
    assert noisy.mean() == pytest.approx(1.5, abs=0.005)
    with pytest.raises(ValueError, match="photons"):
        add_fluoro_noise(p, 0.0, rng)


def _spot_centroid(image: np.ndarray) -> np.ndarray:
    v, u = ndimage.center_of_mass(image)
    return np.array([u, v])


@pytest.mark.parametrize("max_px", [1.0, 2.0])
def test_distortion_moves_points_radially_by_the_stated_amount(max_px):
    rows, cols = 200, 240
    centre = np.array([(cols - 1) / 2, (rows - 1) / 2])
    half_diagonal = float(np.hypot(*centre))
    v, u = np.mgrid[0:rows, 0:cols]
    for fraction in (0.0, 0.85):
        spot_uv = centre + fraction * centre  # along the diagonal toward the last corner
        image = np.exp(-0.5 * ((u - spot_uv[0]) ** 2 + (v - spot_uv[1]) ** 2) / 2.0**2)
        shift = _spot_centroid(distort(image, max_px)) - _spot_centroid(image)
        r = fraction * half_diagonal
        expected = max_px * (r / half_diagonal) ** 3 * (spot_uv - centre) / max(r, 1e-12)
        np.testing.assert_allclose(shift, expected, atol=0.03)
    assert distort(np.ones((3, 8, 8)), max_px).shape == (3, 8, 8)


def test_independent_realism_changes_the_frames_like_a_detector(squat_sequence):
    _, ideal = squat_sequence
    two = squat_motion(SPEC, frames=2, max_flexion_deg=30.0)
    seq = simulate_fluoroscopy(SPEC, two, ideal.view, voxel_mm=1.0, seed=1)
    assert seq.realism == "independent" and seq.counts is not None
    assert seq.photons_per_pixel == pytest.approx(1.96e4 * 64)  # 2.4 mm pixels = 64 x 0.3 mm
    np.testing.assert_allclose(
        seq.frames, -np.log(seq.counts / seq.photons_per_pixel), rtol=1e-5, atol=1e-5
    )
    # frame 0 is the reference pose in both; beam hardening and scatter lower the thick parts
    thick = ideal.frames[0] > 3.0
    drop = (ideal.frames[0] - seq.frames[0])[thick]
    assert 0.25 < drop.mean() < 0.65


# -- files -----------------------------------------------------------------------------------


def test_save_sequence_writes_readable_files(squat_sequence, tmp_path):
    _, seq = squat_sequence
    paths = save_sequence(seq, tmp_path / "fluoro")
    stack = read_projections(paths["frames"])
    np.testing.assert_array_equal(stack.data, seq.frames)
    assert stack.pixel_pitch_mm == (2.4, 2.4)
    geometry = read_rtk_geometry(paths["view"], stack.header)
    assert len(geometry) == 5 and all(v.isclose(seq.view, 1e-6) for v in geometry)
    frames, poses = poses_by_frame(read_poses(paths["poses"]), tuple(seq.poses))
    np.testing.assert_array_equal(frames, np.arange(5))
    for bone, stack_T in poses.items():
        np.testing.assert_allclose(stack_T, seq.poses[bone], atol=1e-12)
    meta = json.loads(paths["sequence"].read_text())
    assert meta["flexion_deg"] == seq.flexion_deg.tolist() and meta["realism"] == "ideal"
    assert "counts" not in paths
    with pytest.raises(FileExistsError):
        save_sequence(seq, tmp_path / "fluoro")
