"""Frames the assessment must not measure (assessment.screening), on the grand-challenge knee
replacement (sim.tka) moved through its measured gait: frames the tracker marked failed, a
component pushed into its insert, a joint that jumps; too few frames left for a flag."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from assessment.components import assess_components
from assessment.flags import describe_flags, measured_text
from assessment.report import summary_rows
from assessment.results import KneeKinematics
from assessment.screening import INSIDE_MM, JUMP_MM, screen
from registration.poses import BodyPose, read_poses, write_poses
from sim.tka import load_tka, read_gait, tka_motion
from study.cli import app

DATA = Path(__file__).resolve().parents[3] / "shared" / "data" / "grand-challenge-tka"
pytestmark = pytest.mark.skipif(not DATA.is_dir(), reason=f"no grand-challenge data at {DATA}")
FRAMES = 12
FAILED = (7, 8, 9, 10, 11)
"""The frames the tracker lost the tray in on the 12-frame quick TKA demo."""


@pytest.fixture(scope="module")
def gait():
    knee = load_tka(DATA)
    gait = read_gait(DATA / "kinematics" / "fluoroscopic_gait.sto")
    motion = tka_motion(knee, gait, FRAMES, np.array([0.0, 0.0, 490.0]))
    parts = knee.meshes["femoral_component"], knee.meshes["tibial_insert"]
    truth = assess_components(*parts, _poses(motion.poses["femur_r"], motion.poses["tibia_r"]))
    return knee, motion, parts, truth


def _poses(femur: np.ndarray, tibia: np.ndarray, failed: tuple[int, ...] = ()) -> list[BodyPose]:
    """The components' poses per frame; the tray marked failed (NCC 0.2) in ``failed``."""
    out = []
    for k in range(len(femur)):
        out.append(BodyPose(k, "femur", femur[k], 0.77))
        lost = k in failed
        reason = "NCC 0.200 below 0.5" if lost else ""
        out.append(
            BodyPose(k, "tibia_fibula", tibia[k], 0.2 if lost else 0.77, failed=lost, reason=reason)
        )
    return out


def _tilted(motion, tibia, frames: tuple[int, ...], degrees: float) -> np.ndarray:
    """The femoral component turned by ``degrees`` about the tray's anterior axis through the
    plateau's centre in ``frames``: one condyle sinks, the other rises (a wrong pose a lost
    tray leaves, still touching the insert)."""
    femur = motion.poses["femur_r"].copy()
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_rotvec([np.radians(degrees), 0.0, 0.0]).as_matrix()
    centre = tibia.plateau_center_mm
    turn[:3, 3] = centre - turn[:3, :3] @ centre
    for k in frames:
        tray = motion.poses["tibia_r"][k]
        femur[k] = tray @ turn @ np.linalg.inv(tray) @ femur[k]
    return femur


def test_frames_the_tracker_failed_carry_no_number_and_no_flag(gait):
    """The tray lost in frames 7-11, the femoral component there turned 6 degrees on the
    insert: measured as if good, frames 7, 9 and 11 give |MLD| over 3 mm and flags (8 and 10
    swing, unloaded); marked failed, frames 7-11 hold NaN in every metric, no flag, and the
    summary names them. The other frames are measured exactly as the truth's."""
    _, motion, parts, truth = gait
    femur = _tilted(motion, truth.tibia, FAILED, 6.0)
    blind = assess_components(*parts, _poses(femur, motion.poses["tibia_r"])).kinematics
    assert np.flatnonzero(blind.flagged).tolist() == [7, 9, 11]  # flags from wrong poses
    assert np.abs(blind.mld_mm[[7, 9, 11]]).min() > 3.0
    kin = assess_components(*parts, _poses(femur, motion.poses["tibia_r"], FAILED)).kinematics
    assert np.flatnonzero(~kin.measured).tolist() == list(FAILED)
    assert not kin.flagged[list(FAILED)].any()
    for values in (kin.flexion_deg, kin.mld_mm, kin.medial_gap_mm, kin.translation_mm):
        assert np.isnan(values[list(FAILED)]).all()
    kept = [k for k in range(FRAMES) if k not in FAILED]
    np.testing.assert_allclose(kin.mld_mm[kept], truth.kinematics.mld_mm[kept], atol=1e-9)
    text = "tibial tray not tracked in frames 7–11: metrics from 7 of 12 frames"
    assert measured_text(kin) == text and summary_rows(kin)["Measured"] == text
    assert kin.excluded[7].detail == "NCC 0.200 below 0.5"
    assert any(
        s == "Not measured: tibial tray not tracked in frames 7–11." for s in describe_flags(kin)
    )


def test_a_component_pushed_into_the_insert_is_not_measured(gait):
    """The femoral component pushed 5 mm into the insert along its normal in frames 3 and 4:
    those frames are left out as inside the insert (the tracker did not mark them), every
    other frame is measured as the truth's."""
    _, motion, parts, truth = gait
    femur = motion.poses["femur_r"].copy()
    normal = truth.tibia.plateau_normal
    for k in (3, 4):
        femur[k, :3, 3] -= 5.0 * motion.poses["tibia_r"][k, :3, :3] @ normal
    kin = assess_components(*parts, _poses(femur, motion.poses["tibia_r"])).kinematics
    assert np.flatnonzero(~kin.measured).tolist() == [3, 4]
    exclusion = kin.excluded[3]
    assert exclusion.what == "femoral component inside the insert"
    rest = truth.kinematics
    depth = 5.0 - min(rest.medial_gap_mm[3], rest.lateral_gap_mm[3])
    assert depth > INSIDE_MM and f"condyle {depth:.1f} mm beyond its rest" in exclusion.detail
    kept = np.r_[0:3, 5:FRAMES]
    np.testing.assert_array_equal(kin.flexion_deg[kept], truth.kinematics.flexion_deg[kept])
    assert "femoral component inside the insert in frames 3–4" in measured_text(kin)


def test_too_few_frames_measured_give_no_flag_and_cbct_assess_exits_1(gait, tmp_path):
    """Seven of twelve frames failed: no clinical flag at all, only "tracking insufficient";
    ``cbct assess`` writes the report, marked, and exits 1 saying so; metrics.csv gives each
    frame's status and no number for a frame not measured."""
    knee, motion, parts, truth = gait
    failed = tuple(range(5, FRAMES))
    femur = _tilted(motion, truth.tibia, failed, 4.0)
    poses = _poses(femur, motion.poses["tibia_r"], failed)
    kin = assess_components(*parts, poses).kinematics
    assert not kin.sufficient and not kin.flagged.any()
    (sentence,) = describe_flags(kin)
    assert sentence.startswith("Tracking insufficient: tibial tray not tracked in frames 5–11")
    assert sentence.endswith("repeat or correct the registration.")
    meshes = {}
    for part in ("femoral_component", "tibial_tray", "tibial_insert"):
        meshes[part] = tmp_path / f"{part}.stl"
        knee.meshes[part].export(meshes[part])
    centroids = {name: np.zeros(3) for name in ("femur", "tibia_fibula")}
    path = write_poses(tmp_path / "poses.csv", poses, centroids)
    assert [p.failed for p in read_poses(path)] == [p.failed for p in poses]
    args = ["assess", "--poses", str(path), "--implant", f"femur={meshes['femoral_component']}"]
    args += [
        "--implant",
        f"tibia={meshes['tibial_tray']}",
        "--insert",
        str(meshes["tibial_insert"]),
    ]
    result = CliRunner().invoke(app, [*args, "--out", str(tmp_path / "out")])
    assert result.exit_code == 1 and "Tracking insufficient" in result.output
    page = (tmp_path / "out" / "report.html").read_text(encoding="utf-8")
    assert '<div class="banner">Tracking insufficient' in page
    assert (
        '<div class="flags insufficient">' in page and "Medial–lateral difference above" not in page
    )
    with (tmp_path / "out" / "metrics.csv").open(newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    assert rows[4]["status"] == "measured" and rows[4]["mld_mm"] != ""
    assert rows[5]["status"] == "tibial tray not tracked (NCC 0.200 below 0.5)"
    assert {v for k, v in rows[5].items() if k not in ("frame", "status")} == {""}


def test_a_joint_that_jumps_and_comes_back_is_not_measured():
    """The tibia shifted 15 mm against the femur in one frame and back: that frame is left out
    as a jump; a smooth shift of 15 mm over the motion is not."""
    n = 9
    frames = np.arange(n)
    ramp = np.column_stack((np.zeros(n), np.linspace(0.0, -15.0, n), np.zeros(n)))
    zeros = np.zeros(n)
    kin = KneeKinematics(
        "right", frames, zeros, zeros, zeros, ramp, zeros + 3, zeros + 3, ramp[:, :2], ramp[:, :2]
    )
    assert screen(kin, [], {"femur": "femur", "tibia": "tibia"}, "the plateau").measured.all()
    jumped = ramp.copy()
    jumped[4, 1] -= 1.5 * JUMP_MM
    kin = KneeKinematics(
        "right", frames, zeros, zeros, zeros, jumped, zeros + 3, zeros + 3, ramp[:, :2], ramp[:, :2]
    )
    screened = screen(kin, [], {"femur": "femur", "tibia": "tibia"}, "the plateau")
    assert np.flatnonzero(~screened.measured).tolist() == [4]
    assert screened.excluded[4].what == "tibia jumped against the femur"
