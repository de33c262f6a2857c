"""A knee replacement assessed from its components: the grand-challenge knee (sim.tka) moved
through its measured gait, whose joint angles are known by construction."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from assessment.components import assess_components
from assessment.screening import LIFTED_MM
from registration.poses import BodyPose, write_poses
from sim.tka import load_tka, read_gait, tka_motion
from study.cli import app

DATA = Path(__file__).resolve().parents[3] / "shared" / "data" / "grand-challenge-tka"
pytestmark = pytest.mark.skipif(not DATA.is_dir(), reason=f"no grand-challenge data at {DATA}")
FRAMES = 12


@pytest.fixture(scope="module")
def knee():
    knee = load_tka(DATA)
    gait = read_gait(DATA / "kinematics" / "fluoroscopic_gait.sto")
    motion = tka_motion(knee, gait, FRAMES, np.array([0.0, 0.0, 490.0]))
    samples = np.linspace(0, len(gait["time"]) - 1, FRAMES)
    angles = {k: np.interp(samples, np.arange(len(v)), v) for k, v in gait.items()}
    return knee, motion, angles


def _poses(motion, femur=None) -> list[BodyPose]:
    femur = motion.poses["femur_r"] if femur is None else femur
    return [BodyPose(int(f), "femur", femur[i]) for i, f in enumerate(motion.frames)] + [
        BodyPose(int(f), "tibia_fibula", motion.poses["tibia_r"][i])
        for i, f in enumerate(motion.frames)
    ]


def test_the_components_give_the_gaits_angles(knee):
    """The components' anatomical frames are the model's bodies': Grood-Suntay flexion,
    varus and internal rotation are the knee joint's three rotations (z, then x, then y:
    the same decomposition), to rounding."""
    knee, motion, gait = knee
    result = assess_components(
        knee.meshes["femoral_component"], knee.meshes["tibial_insert"], _poses(motion)
    )
    kin = result.kinematics
    np.testing.assert_allclose(kin.flexion_deg, -np.degrees(gait["knee_rot_r"]), atol=1e-9)
    np.testing.assert_allclose(kin.varus_deg, np.degrees(gait["knee_flex_r"]), atol=1e-9)
    np.testing.assert_allclose(
        np.abs(kin.internal_rotation_deg), np.abs(np.degrees(gait["knee_add_r"])), atol=1e-9
    )
    normal = result.tibia.plateau_normal
    assert normal[1] > 0.99  # the insert's top faces up the tibia's axis


def test_lifting_the_femoral_component_lifts_both_condyles_off_the_plateau(knee):
    """The femoral component moved 2 mm along the plateau's normal: both TP-condyle distances
    and both gaps grow by 2 mm, the MLD does not change; the swing frames whose condyles then
    stand more than 5 mm above the insert are no longer measured."""
    knee, motion, _ = knee
    femoral, insert = knee.meshes["femoral_component"], knee.meshes["tibial_insert"]
    before = assess_components(femoral, insert, _poses(motion))
    lift = np.einsum("fij,j->fi", motion.poses["tibia_r"][:, :3, :3], before.tibia.plateau_normal)
    lifted = motion.poses["femur_r"].copy()
    lifted[:, :3, 3] += 2.0 * lift
    after = assess_components(femoral, insert, _poses(motion, lifted)).kinematics
    kin = before.kinematics
    # lifted more than LIFTED_MM on both condyles, a frame is no longer measured
    off = (kin.medial_gap_mm + 2.0 > LIFTED_MM) & (kin.lateral_gap_mm + 2.0 > LIFTED_MM)
    assert 0 < off.sum() < FRAMES and np.array_equal(~after.measured, off)
    assert all(e.what == "femoral component lifted off the insert" for e in after.excluded if e)
    kept = after.measured
    np.testing.assert_allclose(after.medial_gap_mm[kept] - kin.medial_gap_mm[kept], 2.0, atol=1e-6)
    np.testing.assert_allclose(
        after.medial_distance_mm[kept] - kin.medial_distance_mm[kept], 2.0, atol=1e-9
    )
    np.testing.assert_allclose(
        after.lateral_distance_mm[kept] - kin.lateral_distance_mm[kept], 2.0, atol=1e-9
    )


def test_cbct_assess_takes_the_components_and_refuses_a_left_knee(knee, tmp_path):
    """``cbct assess --implant ... --insert ...`` writes the report from the components'
    poses (its 3D view shows them); a left knee is refused by name, before anything is
    written."""
    knee, motion, _ = knee
    meshes = {}
    for part in ("femoral_component", "tibial_tray", "tibial_insert"):
        meshes[part] = tmp_path / f"{part}.stl"
        knee.meshes[part].export(meshes[part])
    centroids = {
        "femur": knee.meshes["femoral_component"].centroid,
        "tibia_fibula": knee.meshes["tibial_tray"].centroid,
    }
    poses = write_poses(tmp_path / "poses.csv", _poses(motion), centroids)
    args = ["assess", "--poses", str(poses), "--implant", f"femur={meshes['femoral_component']}"]
    args += ["--implant", f"tibia={meshes['tibial_tray']}"]
    args += ["--insert", str(meshes["tibial_insert"])]
    result = CliRunner().invoke(app, [*args, "--out", str(tmp_path / "out")])
    assert result.exit_code == 0, result.output
    assert f"{FRAMES} frames" in result.output
    page = (tmp_path / "out" / "report.html").read_text(encoding="utf-8")
    assert 'id="view3d"' in page and "the insert" in page
    left = CliRunner().invoke(app, [*args, "--side", "left", "--out", str(tmp_path / "left")])
    assert left.exit_code == 2 and "only right knees" in left.output
    assert not (tmp_path / "left").exists()
    alone = CliRunner().invoke(app, ["assess", "--poses", str(poses), "--out", str(tmp_path / "x")])
    assert alone.exit_code == 2 and "--labels" in alone.output


def test_the_components_under_their_own_names_assess_as_under_their_bones(knee):
    """The body playing each role is read by its role: poses named femoral_component and
    tibial_tray give the kinematics of the same poses named femur and tibia_fibula."""
    knee, motion, _ = knee
    parts = (knee.meshes["femoral_component"], knee.meshes["tibial_insert"])
    older = assess_components(*parts, _poses(motion)).kinematics
    names = {"femur": "femoral_component", "tibia_fibula": "tibial_tray"}
    renamed = [BodyPose(p.frame, names[p.body], p.T_world_body) for p in _poses(motion)]
    ours = assess_components(*parts, renamed).kinematics
    np.testing.assert_array_equal(ours.flexion_deg, older.flexion_deg)
    np.testing.assert_array_equal(ours.medial_distance_mm, older.medial_distance_mm)
