"""trajectories.model and ik: the UR chain matches the maker's DH table; IK round trips."""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError
from scipy.spatial.transform import Rotation

from tests.trajectories.conftest import scanner_config
from trajectories.arms import ARMS
from trajectories.ik import solve_ik
from trajectories.model import se3


def dh_chain(d, a, alpha, theta) -> np.ndarray:
    """Standard DH forward kinematics, written out independently of the model code."""
    T = np.eye(4)
    for di, ai, al, th in zip(d, a, alpha, theta, strict=True):
        ct, st_, ca, sa = math.cos(th), math.sin(th), math.cos(al), math.sin(al)
        T = T @ np.array(
            [
                [ct, -st_ * ca, st_ * sa, ai * ct],
                [st_, ct * ca, -ct * sa, ai * st_],
                [0, sa, ca, di],
                [0, 0, 0, 1],
            ]
        )
    return T


@pytest.mark.parametrize("arm_type", ["ur3e", "ur5e", "ur10e"])
def test_flange_pose_matches_the_makers_dh_table(arm_type):
    """The Pinocchio chain of each arm reproduces the DH table's flange pose (to 1e-9 m)."""
    from trajectories.model import ScannerModel

    config = scanner_config(source_arm={"model": arm_type}, detector_arm={"model": arm_type})
    model = ScannerModel(config)
    spec = ARMS[arm_type]
    rng = np.random.default_rng(4)
    mount = se3(config.source_arm.mount).homogeneous
    flange = model.model.getFrameId("source_flange")
    for _ in range(5):
        q = pin.neutral(model.model)
        q[model.index["rotary"]] = rng.uniform(-3, 3)
        q[model.index["lift"]] = rng.uniform(0, 1.5)
        theta = rng.uniform(-math.pi, math.pi, 6)
        for k, name in enumerate(
            ("shoulder_pan", "shoulder_lift", "elbow", "wrist_1", "wrist_2", "wrist_3")
        ):
            q[model.index[f"source_{name}"]] = theta[k]
        pin.framesForwardKinematics(model.model, model.data, q)
        carriage = pin.SE3(
            Rotation.from_euler("z", q[model.index["rotary"]]).as_matrix(),
            np.array([0.0, 0.0, q[model.index["lift"]]]),
        ).homogeneous
        expected = carriage @ mount @ dh_chain(spec.d_m, spec.a_m, spec.alpha_rad, theta)
        np.testing.assert_allclose(model.data.oMf[flange].homogeneous, expected, atol=1e-9)


def test_joints_are_looked_up_by_name_and_units_round_trip(scanner):
    assert scanner.joint_names[:2] == ("rotary", "lift")
    assert sorted(scanner.index.values()) == list(range(14))
    q = scanner.neutral()
    q[scanner.index["lift"]] = 0.4321
    q[scanner.index["detector_elbow"]] = 0.5
    public = scanner.to_units(q)
    assert public[1] == pytest.approx(432.1)
    assert public[scanner.joint_names.index("detector_elbow")] == pytest.approx(math.degrees(0.5))
    np.testing.assert_allclose(scanner.from_units(public), q, atol=1e-12)


@settings(max_examples=25, deadline=None)
@given(
    rotary=st.floats(-3.0, 3.0),
    lift=st.floats(0.1, 1.2),
    perturb=st.lists(st.floats(-0.35, 0.35), min_size=12, max_size=12),
)
def test_ik_recovers_poses_produced_by_forward_kinematics(scanner, rotary, lift, perturb):
    """FK of a configuration near home, then IK from home: both tools land on the same poses
    (1e-4 mm, 1e-5 deg), whatever joint solution IK picks."""
    q_true = scanner.neutral()
    q_true[scanner.index["rotary"]] = rotary
    q_true[scanner.index["lift"]] = lift
    q_true[2:] += np.array(perturb)
    source, detector = scanner.tool_poses(q_true)
    rest = scanner.neutral()
    rest[scanner.index["rotary"]] = rotary
    rest[scanner.index["lift"]] = lift
    result = solve_ik(scanner, rest, source, detector, rest, max_iterations=200)
    assert result.converged
    got = scanner.tool_poses(result.q)
    for g, want in zip(got, (source, detector), strict=True):
        delta = g.actInv(want)
        assert np.linalg.norm(delta.translation) < 1e-7
        assert np.degrees(np.linalg.norm(pin.log3(delta.rotation))) < 1e-5


def test_home_posture_is_clear_of_every_obstacle(scanner):
    distance, a, b = scanner.clearance(scanner.neutral())
    assert distance * 1000 >= scanner.config.obstacles.clearance_margin_mm, (a, b)


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"source_arm": {"model": "ur7x"}}, "source_arm.model"),
        ({"rotary": {"range_deg": [10, -10]}}, "lower limit must be below upper"),
        ({"lift": {"range_mm": [0, 2500]}}, "need 0 <= lower < upper <= 1800"),
        ({"lift": {"max_speed_mm_s": float("nan")}}, "lift.max_speed_mm_s"),
        ({"detector_arm": {"home_deg": [0, -90, 400, 0, 0, 0]}}, "home_deg\\[2\\] = 400"),
        ({"detector_arm": {"speed_scale": 1.5}}, "detector_arm.speed_scale"),
    ],
)
def test_bad_scanner_configs_name_the_field(changes, message):
    with pytest.raises(ValidationError, match=message):
        scanner_config(**changes)
