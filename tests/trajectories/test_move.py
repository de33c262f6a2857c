"""trajectories.move: moves from wherever the scanner stands to the plan's start or park keep
every limit and the clearance margin along the whole motion, end exactly on the goal, or are
refused naming the joint or link pair, the value and the limit."""

from __future__ import annotations

import numpy as np
import pytest

from tests.trajectories.conftest import random_rest_pose
from trajectories.collision import RESOLUTION_M, motion_clearance
from trajectories.errors import CollisionError, JointLimitError, PlanningError
from trajectories.model import ScannerModel
from trajectories.move import JointMove, park_pose, plan_move
from trajectories.plan import SAMPLE_DT_S
from trajectories.timing import point_to_point, sample


def assert_move_is_safe(move: JointMove, model: ScannerModel) -> None:
    """Starts and ends at rest on its two poses, every sample within the position and velocity
    limits (the planner aims at 99 % of each; 1e-6 of a unit for rounding), clearance at every
    sample >= margin - resolution (the check between samples is the planner's)."""
    np.testing.assert_allclose(move.q[0], move.start_q, atol=1e-9)
    np.testing.assert_allclose(move.q[-1], move.goal_q, atol=1e-9)
    np.testing.assert_allclose(move.qd[[0, -1]], 0.0, atol=1e-9)
    lower, upper = model.to_units(model.limits.lower), model.to_units(model.limits.upper)
    vmax = model.to_units(model.limits.velocity)
    assert np.all(move.q >= lower - 1e-6) and np.all(move.q <= upper + 1e-6)
    assert np.all(np.abs(move.qd) <= vmax + 1e-6)
    assert np.all(np.diff(move.t_s) > 0) and move.t_s[-1] == pytest.approx(move.duration_s)
    assert move.min_clearance_mm >= move.clearance_margin_mm
    margin_m = move.clearance_margin_mm / 1000.0
    sampled = [model.clearance(model.from_units(q))[0] for q in move.q[::5]]
    assert min(sampled) >= margin_m - RESOLUTION_M


@pytest.mark.parametrize("seed", range(4))
def test_random_rest_pose_moves_to_the_start_and_back(scanner, seed):
    rng = np.random.default_rng(seed)
    pose = random_rest_pose(scanner, rng)
    there = plan_move(scanner, pose, park_pose(scanner), "park")
    assert_move_is_safe(there, scanner)
    back = plan_move(scanner, park_pose(scanner), pose, "the pose")
    assert_move_is_safe(back, scanner)
    # jerk-limited rest-to-rest at the planner's limits: no faster than the slowest joint's
    # rest-to-rest triangle/trapezoid under its velocity and acceleration limits
    change = np.abs(pose - park_pose(scanner))
    vmax = scanner.to_units(scanner.limits.velocity)
    amax = scanner.to_units(scanner.limits.acceleration)
    bound = np.where(
        change >= vmax**2 / amax, change / vmax + vmax / amax, 2 * np.sqrt(change / amax)
    ).max()
    assert there.duration_s >= bound - 1e-9


def test_a_start_beyond_a_joint_limit_is_refused(scanner):
    pose = park_pose(scanner)
    pose[0] = 380.0
    with pytest.raises(
        JointLimitError,
        match=r"stands with joint rotary at 380\.00 deg, outside its range "
        r"\[-370\.00, 370\.00\] deg",
    ):
        plan_move(scanner, pose, park_pose(scanner), "park")


def test_a_start_inside_the_margin_is_refused_naming_the_pair(scanner):
    """The detector arm's wrist bent toward the source arm's tool until the two come within
    the margin: refused, naming the pair, the clearance and the margin."""
    pose = park_pose(scanner)
    margin_m = scanner.config.obstacles.clearance_margin_mm / 1000.0
    for step in np.arange(0.0, 120.0, 0.5):
        trial = pose.copy()
        trial[8] += step  # detector shoulder pan, toward the source side
        distance, *_ = scanner.clearance(scanner.from_units(trial))
        if 0.0 < distance < margin_m:
            break
    else:
        pytest.fail("no pose within the margin on the way")
    with pytest.raises(CollisionError, match=r"mm apart, less than the clearance margin of 20 mm"):
        plan_move(scanner, trial, park_pose(scanner), "park")


def test_bad_joint_vector_is_refused(scanner):
    with pytest.raises(PlanningError, match="start_q: need 14 finite joint values"):
        plan_move(scanner, np.zeros(13), park_pose(scanner), "park")


# rest poses found by random_rest_pose (seed 8; seed 1002 with arm_deg=45), rounded
PANEL_NEAR_PLATFORM = [
    112.98, 169.19, -35.76, -95.36, 134.17, -25.13, 80.45, 166.01,
    -28.14, -101.62, 105.67, -44.74, 62.79, -4.27,
]  # fmt: skip
PANEL_BESIDE_THE_OTHER_LEG = [
    -78.09, 12.83, -70.75, -70.46, 97.97, -62.1, 41.7, 203.16,
    -38.06, -136.03, 86.75, -23.5, 24.14, -23.76,
]  # fmt: skip


def straight_clearance_mm(model: ScannerModel, a: np.ndarray, b: np.ndarray) -> float:
    """Clearance along the straight jerk-limited move a -> b (plan units), mm."""
    qa, qb = model.from_units(np.asarray(a)), model.from_units(np.asarray(b))
    segment = point_to_point(qa, qb, model.limits.velocity, model.limits.acceleration, "straight")
    path = sample(segment, SAMPLE_DT_S)
    return motion_clearance(model, path, lambda t: segment.evaluate(t)[0]).distance_m * 1000


def test_a_straight_move_inside_the_margin_goes_round_with_the_arms_folded(scanner):
    """The straight move would sweep the panel within 18 mm of the platform: the arms fold
    where the stage stands, the stage turns and lowers, and the move keeps the margin."""
    pose = np.array(PANEL_NEAR_PLATFORM)
    margin = scanner.config.obstacles.clearance_margin_mm
    assert straight_clearance_mm(scanner, pose, park_pose(scanner)) < margin
    move = plan_move(scanner, pose, park_pose(scanner), "park")
    assert move.route == "retract" and [leg for leg, _, _ in move.legs] == ["fold arms", "stage"]
    assert_move_is_safe(move, scanner)
    fold_end = move.legs[0][2]
    k = int(np.argmin(np.abs(move.t_s - fold_end)))
    np.testing.assert_allclose(move.q[k, 2:], park_pose(scanner)[2:], atol=1e-6)  # folded
    np.testing.assert_allclose(move.q[k, :2], pose[:2], atol=1e-6)  # the stage not yet moved


def test_a_move_no_route_keeps_clear_of_is_refused_naming_both(scanner):
    with pytest.raises(CollisionError) as caught:
        plan_move(scanner, np.array(PANEL_BESIDE_THE_OTHER_LEG), park_pose(scanner), "park")
    message = str(caught.value)
    assert message.startswith("move to park refused: the straight move brings detector_tool")
    assert "the retract route's fold arms leg brings detector_tool and patient1 to" in message
    assert message.endswith("the clearance margin is 20 mm")
