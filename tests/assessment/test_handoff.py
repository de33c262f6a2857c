"""The hand-off to ITK, Autoscoper and 3D Slicer, read back by other readers (SimpleITK, numpy,
an XML parser, trimesh) against poses.csv."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np
import pytest
import SimpleITK as sitk
import trimesh
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from assessment.handoff import Motion, pose_of_itk, read_tra, write_handoff
from assessment.slicer_scene import read_sequence, referenced_files, transform_name
from recon.io import write_volume
from recon.volume import Volume, VolumeGrid
from registration.poses import BodyPose, read_poses, write_poses
from study.cli import app

BONES = ("femur", "patella", "tibia_fibula")
FRAMES = np.array([0, 1, 2, 4])  # frame 3 untracked


def random_poses(seed: int = 0) -> list[BodyPose]:
    rng = np.random.default_rng(seed)
    poses = []
    for frame in FRAMES:
        for bone in BONES:
            T = np.eye(4)
            T[:3, :3] = Rotation.from_rotvec(rng.normal(0, 0.4, 3)).as_matrix()
            T[:3, 3] = rng.normal(0, 40, 3)
            poses.append(BodyPose(int(frame), bone, T))
    return poses


@pytest.fixture(scope="module")
def handoff(tmp_path_factory):
    """poses.csv of random motions, read back, handed off with box models and a volume."""
    tmp = tmp_path_factory.mktemp("handoff")
    centroids = {bone: np.zeros(3) for bone in BONES}
    poses = read_poses(write_poses(tmp / "poses.csv", random_poses(), centroids))
    meshes = {bone: trimesh.creation.box((10 + 5 * k, 20, 30)) for k, bone in enumerate(BONES)}
    grid = VolumeGrid((8, 9, 10), (1.0, 1.0, 2.0), (-5.0, -4.0, -7.0))
    volume = write_volume(tmp / "ct.nii.gz", Volume(np.ones(grid.shape, np.float32), grid))
    out = tmp / "export"
    written = write_handoff(out, Motion.of(poses), meshes, volume)
    return out, poses, meshes, written


def truth(poses: list[BodyPose], bone: str) -> dict[int, np.ndarray]:
    return {p.frame: p.T_world_body for p in poses if p.body == bone}


def test_itk_files_read_back_with_simpleitk_equal_poses_csv(handoff):
    out, poses, _, _ = handoff
    points = np.random.default_rng(1).normal(0, 50, (5, 3))
    for bone in BONES:
        for frame, T in truth(poses, bone).items():
            transform = sitk.ReadTransform(str(out / "itk" / bone / f"frame_{frame:04d}.tfm"))
            np.testing.assert_allclose(pose_of_itk(transform), T, atol=1e-9)
            # ITK's resampling direction: a point of the frame maps back into the static scan
            for p in points:
                moved = T[:3, :3] @ p + T[:3, 3]
                np.testing.assert_allclose(transform.TransformPoint(moved.tolist()), p, atol=1e-9)
    assert not (out / "itk" / "femur" / "frame_0003.tfm").exists()


def test_resampling_the_static_volume_by_the_itk_file_moves_the_bone_to_its_frame(tmp_path):
    """sitk.Resample (ITK's own meaning of the file) puts a bright voxel at T @ p."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    T[:3, 3] = (4.0, -2.0, 3.0)
    poses = [BodyPose(0, "femur", T)]
    write_handoff(tmp_path / "out", Motion.of(poses), {"femur": trimesh.creation.box((1, 1, 1))})
    transform = sitk.ReadTransform(str(tmp_path / "out" / "itk" / "femur" / "frame_0000.tfm"))
    static = np.zeros((21, 21, 21), np.float32)
    p = np.array([3.0, 1.0, -2.0])  # x, y, z mm; origin -10 mm, 1 mm voxels
    static[tuple((p[::-1] + 10).astype(int))] = 1.0
    image = sitk.GetImageFromArray(static)
    image.SetOrigin((-10.0, -10.0, -10.0))
    moved = sitk.GetArrayFromImage(sitk.Resample(image, transform, sitk.sitkNearestNeighbor))
    z, y, x = np.argwhere(moved == 1.0)[0]
    np.testing.assert_allclose(np.array([x, y, z]) - 10.0, T[:3, :3] @ p + T[:3, 3], atol=1e-6)


def test_tra_files_are_row_major_mm_one_line_per_frame_with_nan_for_untracked(handoff):
    out, poses, _, _ = handoff
    for bone in BONES:
        rows = np.loadtxt(out / "autoscoper" / f"{bone}.tra", delimiter=",")
        assert rows.shape == (5, 16)
        assert np.isnan(rows[3]).all()
        for frame, T in truth(poses, bone).items():
            np.testing.assert_allclose(rows[frame][[3, 7, 11]], T[:3, 3], atol=1e-9)
            np.testing.assert_allclose(rows[frame].reshape(4, 4), T, atol=1e-9)
        frames, stack = read_tra(out / "autoscoper" / f"{bone}.tra")
        np.testing.assert_array_equal(frames, FRAMES)
        np.testing.assert_allclose(stack, [truth(poses, bone)[f] for f in frames], atol=1e-9)


def test_the_scene_parses_and_every_file_it_names_is_present(handoff):
    out, _, _, written = handoff
    files = referenced_files(out / "scene.mrml")
    assert len(files) == 1 + 2 * len(BONES)  # volume, a model and a sequence per bone
    assert all(f.is_file() for f in files)
    assert set(files) <= {p.resolve() for p in written} | set(written)
    root = ET.parse(out / "scene.mrml").getroot()
    ids = {node.get("id"): node for node in root}
    refs = {
        node.get("id"): dict(
            part.split(":", 1) for part in node.get("references", "").split(";") if part
        )
        for node in root
    }
    browser = next(node for node in root if node.tag == "SequenceBrowser")
    postfixes = browser.get("virtualNodePostfixes").split()
    assert len(postfixes) == len(BONES)
    for node in root:
        for target in refs[node.get("id")].values():
            assert target in ids, f"{node.get('id')} references a missing node {target}"
    for model in (n for n in root if n.tag == "Model"):
        proxy = refs[model.get("id")]["transform"]
        storage = ids[refs[model.get("id")]["storage"]]
        assert storage.get("coordinateSystem") == "LPS"
        k = next(p for p in postfixes if refs[browser.get("id")][f"dataNodeRef{p}"] == proxy)
        sequence = ids[refs[browser.get("id")][f"sequenceNodeRef{k}"]]
        seq_file = ids[refs[sequence.get("id")]["storage"]].get("fileName")
        assert seq_file == f"motion/{model.get('name')}.seq.mha"


def test_sequences_hold_ras_to_parent_matrices_of_the_poses(handoff):
    out, poses, _, _ = handoff
    C = np.diag([-1.0, -1.0, 1.0, 1.0])
    for bone in BONES:
        text = (out / "motion" / f"{bone}.seq.mha").read_text()
        key = f"Seq_Frame0000_{transform_name(bone)}Transform ="
        first = next(line for line in text.splitlines() if line.startswith(key))
        numbers = np.array([float(x) for x in first.split("=")[1].split()]).reshape(4, 4)
        np.testing.assert_allclose(numbers, C @ truth(poses, bone)[0] @ C, atol=1e-9)
        frames, stack = read_sequence(out / "motion" / f"{bone}.seq.mha")
        np.testing.assert_array_equal(frames, FRAMES)
        for frame, T in zip(frames, stack, strict=True):
            np.testing.assert_allclose(T, truth(poses, bone)[frame], atol=1e-9)
        assert text.rstrip().endswith("ElementDataFile = LOCAL")


def test_models_are_lps_stl_in_the_static_pose(handoff):
    out, _, meshes, _ = handoff
    for bone in BONES:
        path = out / "models" / f"{bone}.stl"
        assert path.read_bytes()[:9] == b"SPACE=LPS"
        loaded = trimesh.load(path)
        np.testing.assert_allclose(loaded.bounds, meshes[bone].bounds, atol=1e-4)


def test_cbct_export_from_files_and_its_refusals(tmp_path):
    grid = VolumeGrid((30, 30, 30), (2.0, 2.0, 2.0), (-29.0, -29.0, -29.0))
    labels = np.zeros(grid.shape, np.uint8)
    labels[18:28, 10:20, 10:20] = 2  # femur
    labels[2:12, 10:20, 10:20] = 3  # tibia
    labels[2:12, 10:20, 22:26] = 4  # fibula
    labels[15:20, 22:26, 12:18] = 5  # patella
    labels_path = write_volume(tmp_path / "labels.nii.gz", Volume(labels, grid, "label"))
    poses_path = write_poses(
        tmp_path / "poses.csv",
        random_poses(2),
        {bone: np.zeros(3) for bone in BONES},
    )
    runner = CliRunner()
    args = ["export", "--poses", str(poses_path), "--labels", str(labels_path)]
    result = runner.invoke(app, [*args, "--out", str(tmp_path / "out")])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "out" / "scene.mrml").is_file()
    assert sorted(p.name for p in (tmp_path / "out" / "models").iterdir()) == [
        f"{b}.stl" for b in BONES
    ]
    again = runner.invoke(app, [*args, "--out", str(tmp_path / "out")])
    assert again.exit_code == 2 and "exists" in again.output
    bad = runner.invoke(app, [*args, "--out", str(tmp_path / "o2"), "--volume", str(poses_path)])
    assert bad.exit_code == 2 and "poses.csv" in bad.output and not (tmp_path / "o2").exists()
    # the scene's volume is a copy: editing it cannot change the study's file behind its sha256
    given = runner.invoke(app, [*args, "--out", str(tmp_path / "o3"), "--volume", str(labels_path)])
    assert given.exit_code == 0, given.output
    static = tmp_path / "o3" / "static.nii.gz"
    assert static.read_bytes() == labels_path.read_bytes()
    assert static.stat().st_ino != labels_path.stat().st_ino
