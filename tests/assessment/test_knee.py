"""assessment: landmarks, Grood-Suntay angles, TP-condyle distances and flags on the phantom,
whose anatomy and motion are known by construction."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from assessment.anatomy import bone_surface, femur_anatomy, mirror_x, tibia_anatomy
from assessment.knee import assess_knee
from recon.volume import Volume, VolumeGrid
from registration.labels import LABELS
from registration.poses import BodyPose, read_poses, write_poses
from sim.motion import flexion_extension
from sim.phantoms.knee import KneePhantomSpec, knee_landmarks, rasterize_knee

# a standing scan long enough to hold 150 mm of each shaft, as the clinical spirals do
CENTER_MM = np.array([0.0, -4.0, 490.0])


@pytest.fixture(scope="module")
def knees(seed):
    """Both knees rasterised at 1 mm; a seed other than 0 shifts the voxel lattice by a random
    fraction of a voxel along each axis (where the voxel edges cut the bones)."""
    shift = np.random.default_rng(seed).uniform(-0.5, 0.5, 3) if seed else np.zeros(3)
    grid = VolumeGrid.centered((140, 140, 320), 1.0, tuple(CENTER_MM + shift))
    out = {}
    for side in ("right", "left"):
        spec = KneePhantomSpec(side=side)
        labels, _ = rasterize_knee(spec, grid, supersample=1)
        out[side] = (spec, Volume(labels, grid, "label"))
    return out


def poses_of(motion, bones=("femur", "tibia")):
    return [
        BodyPose(int(f), b, motion.poses[b][i]) for i, f in enumerate(motion.frames) for b in bones
    ]


def test_landmarks_are_found_where_the_phantom_put_them(knees, measured):
    """Epicondyles within 2 mm (1 mm voxels, rounded tips), TEA and long axes within 0.5 deg,
    the TP plane normal within 1 deg of the plateau's."""
    spec, labels = knees["right"]
    truth = knee_landmarks(spec)
    femur = femur_anatomy(labels, LABELS["femur"])
    tibia = tibia_anatomy(labels, LABELS["tibia"])
    epicondyles = max(
        np.abs(femur.medial_epicondyle_mm - truth["medial_epicondyle"]).max(),
        np.abs(femur.lateral_epicondyle_mm - truth["lateral_epicondyle"]).max(),
    )
    measured("epicondyle_error_mm", epicondyles, below=2.0)
    tea = truth["lateral_epicondyle"] - truth["medial_epicondyle"]
    angle = np.degrees(np.arccos(femur.lateral_axis @ tea / np.linalg.norm(tea)))
    measured("tea_angle_deg", angle, below=0.5)
    tilt = max(np.degrees(np.arccos(a[2])) for a in (femur.proximal_axis, tibia.proximal_axis))
    measured("shaft_tilt_deg", tilt, below=0.5)  # the phantom's shafts stand vertical
    normal = truth["tibial_plateau_normal"]
    measured("plateau_normal_deg", np.degrees(np.arccos(tibia.plateau_normal @ normal)), below=1.0)
    lowest = femur.medial_condyle_mm[np.argmin(femur.medial_condyle_mm[:, 2])]
    measured(
        "lowest_condyle_z_error_mm",
        abs(lowest[2] - truth["medial_condyle_lowest"][2]),
        below=1.0,
    )


def test_flexion_is_recovered_across_the_motion(knees, measured):
    spec, labels = knees["right"]
    motion = flexion_extension(spec, frames=19, max_flexion_deg=90.0)
    kin = assess_knee(labels, poses_of(motion), "right").kinematics
    measured("flexion_error_deg", np.abs(kin.flexion_deg - motion.flexion_deg).max(), below=0.5)
    measured("varus_deg", np.abs(kin.varus_deg).max(), below=0.5)
    measured("internal_rotation_deg", np.abs(kin.internal_rotation_deg).max(), below=0.5)
    measured("peak_flexion_error_deg", abs(kin.flexion_deg.max() - 90.0), below=0.5)


def test_a_varus_tilt_of_known_size_gives_the_expected_mld_and_flags_only_its_frames(
    knees, measured
):
    """Tilting the femur by delta about the AP axis through the knee centre drops the medial
    condyle by x_m sin(delta) and lifts the lateral one as much: with the condyles 23 mm
    either side of the centre, MLD changes by -46 sin(delta) = -2.41 mm at 3 degrees."""
    spec, labels = knees["right"]
    plain = flexion_extension(spec, frames=20, max_flexion_deg=90.0)
    tilted = flexion_extension(
        spec, frames=20, max_flexion_deg=90.0, varus_deg=3.0, varus_frames=(8, 11)
    )
    base = assess_knee(labels, poses_of(plain), "right").kinematics
    kin = assess_knee(labels, poses_of(tilted), "right").kinematics
    change = kin.mld_mm - base.mld_mm
    expected = -46.0 * np.sin(np.radians(3.0))
    measured("mld_change_error_mm", np.abs(change[8:12] - expected).max(), below=0.2)
    measured("mld_change_elsewhere_mm", np.abs(np.delete(change, range(8, 12))).max(), below=0.2)
    assert np.flatnonzero(kin.flagged).tolist() == [8, 9, 10, 11]
    measured("varus_error_deg", np.abs(kin.varus_deg[8:12] - 3.0).max(), below=0.1)


def test_a_left_knee_reads_like_the_mirrored_right_knee(knees):
    right_spec, right_labels = knees["right"]
    left_spec, left_labels = knees["left"]
    kwargs = {"frames": 10, "max_flexion_deg": 90.0, "varus_deg": 2.0, "varus_frames": (3, 5)}
    right = assess_knee(
        right_labels, poses_of(flexion_extension(right_spec, **kwargs)), "right"
    ).kinematics
    left = assess_knee(
        left_labels, poses_of(flexion_extension(left_spec, **kwargs)), "left"
    ).kinematics
    for name in ("flexion_deg", "varus_deg", "internal_rotation_deg", "mld_mm"):
        np.testing.assert_allclose(getattr(left, name), getattr(right, name), atol=1e-6)
    assert (mirror_x(mirror_x(left_labels)).data == left_labels.data).all()


def test_poses_round_trip_and_bad_poses_name_frame_and_body(knees, tmp_path):
    """Poses read back as written, from a file that names its bodies in the ``body`` column
    or, as files did before it, in a ``bone`` column; a bad pose is named by frame and body."""
    spec, labels = knees["right"]
    motion = flexion_extension(spec, frames=4)
    poses = poses_of(motion)
    path = write_poses(tmp_path / "poses.csv", poses, {"femur": np.zeros(3), "tibia": np.zeros(3)})
    text = path.read_text(encoding="utf-8").splitlines()
    assert text[0].startswith("frame,body,t00,")
    older = tmp_path / "older.csv"
    older.write_text("\n".join([text[0].replace(",body,", ",bone,", 1), *text[1:]]) + "\n")
    for back in (read_poses(path), read_poses(older)):
        assert [(p.frame, p.body) for p in back] == [(p.frame, p.body) for p in poses]
        for a, b in zip(back, poses, strict=True):
            np.testing.assert_allclose(a.T_world_body, b.T_world_body, atol=1e-12)
    fields = text[3].split(",")
    fields[2] = "1.5"  # scale the rotation: not rigid
    (tmp_path / "bad.csv").write_text("\n".join([text[0], ",".join(fields)]) + "\n")
    with pytest.raises(ValueError, match=r"bad.csv: frame 1, body femur: pose is not rigid"):
        read_poses(tmp_path / "bad.csv")
    # a file written before the failed and reason columns reads, nothing marked failed; a
    # failed mark and its reason round-trip; a failed value that is not 0 or 1 is refused
    old = "\n".join(",".join(row.split(",")[:-2]) for row in text) + "\n"
    (tmp_path / "old.csv").write_text(old, encoding="utf-8")
    assert not any(p.failed or p.reason for p in read_poses(tmp_path / "old.csv"))
    lost = [replace(poses[0], failed=True, reason="NCC 0.308 below 0.5, out of view"), *poses[1:]]
    marked = read_poses(
        write_poses(tmp_path / "lost.csv", lost, {"femur": np.zeros(3), "tibia": np.zeros(3)})
    )
    assert (marked[0].failed, marked[0].reason) == (True, "NCC 0.308 below 0.5, out of view")
    assert not marked[1].failed
    (tmp_path / "odd.csv").write_text(text[0] + "\n" + text[1].rsplit(",", 2)[0] + ",yes,\n")
    with pytest.raises(ValueError, match=r"odd.csv: line 2: failed: 'yes' is not 0 or 1"):
        read_poses(tmp_path / "odd.csv")
    nan = [BodyPose(0, "femur", np.full((4, 4), np.nan))]
    with pytest.raises(ValueError, match="frame 0, body femur: pose contains NaN"):
        write_poses(tmp_path / "nan.csv", nan, {"femur": np.zeros(3)})
    with pytest.raises(ValueError, match="frame 2, body femur: no pose"):
        assess_knee(labels, poses[:4] + poses[5:], "right")
    without_patella = Volume(np.where(labels.data == 5, 1, labels.data), labels.grid, "label")
    extra = [*poses, BodyPose(0, "patella", np.eye(4))]
    with pytest.raises(ValueError, match="frame 0, body patella: the label volume has no such"):
        assess_knee(without_patella, extra, "right")
    with pytest.raises(ValueError, match="needs the polyethylene insert"):
        assess_knee(labels, poses, "right", tka=True)


def test_a_bone_surface_has_a_unit_outward_normal_at_every_point():
    """A cube of bone beside voxels that touch by edges in a symmetric pattern, where the
    mask's gradient vanishes at a marching-cubes vertex: that vertex has no normal and is
    left out (it made a NaN normal), every other normal is a unit vector pointing out."""
    data = np.zeros((12, 12, 12), np.uint8)
    data[1:6, 1:6, 1:6] = 1
    for z, y, x in (
        (0, 0, 1),
        (0, 2, 0),
        (1, 0, 0),
        (1, 1, 0),
        (1, 1, 2),
        (1, 2, 1),
        (2, 0, 0),
        (2, 0, 1),
        (2, 2, 0),
    ):
        data[8 + z, 8 + y, 8 + x] = 1
    surface = bone_surface(
        Volume(data, VolumeGrid(data.shape, (1.0, 1.0, 1.0), (0.0, 0.0, 0.0)), "label"), 1, "femur"
    )
    assert np.all(np.isfinite(surface.normals))
    np.testing.assert_allclose(np.linalg.norm(surface.normals, axis=1), 1.0, rtol=1e-6)
    cube = np.all(surface.points_mm < 7.0, axis=1)  # the cube's points face away from its centre
    assert np.all(np.sum((surface.points_mm[cube] - 3.0) * surface.normals[cube], axis=1) > 0.0)
