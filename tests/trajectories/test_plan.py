"""trajectories.plan: planned scans reach every view, keep every limit and clearance, or fail
with an error that names the view, the joint or link pair and the limit."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.trajectories.conftest import scanner_config, small_protocol
from trajectories.collision import RESOLUTION_M, motion_clearance
from trajectories.errors import (
    CollisionError,
    JointLimitError,
    PlanningError,
    TimingError,
    UnreachableError,
)
from trajectories.model import ScannerModel
from trajectories.plan import plan_scan
from trajectories.timing import TimedPath, rest_to_rest_lower_bound, time_pass

POSE_MM, POSE_DEG = 0.1, 0.05


def assert_plan_is_safe(plan, scanner: ScannerModel) -> None:
    """Every view on its pose, every sample within position, velocity and acceleration limits
    (the planners aim at 99 % of each limit, the check allows 100 % plus 1e-6 of a unit for
    rounding: moves that end on a limit land within 1e-13 of it), clearance >= margin."""
    assert plan.pose_error_mm.max() <= POSE_MM
    assert plan.pose_error_deg.max() <= POSE_DEG
    lower = scanner.to_units(scanner.limits.lower[None])[0]
    upper = scanner.to_units(scanner.limits.upper[None])[0]
    vmax = scanner.to_units(scanner.limits.velocity[None])[0]
    amax = scanner.to_units(scanner.limits.acceleration[None])[0]
    assert np.all(plan.q >= lower - 1e-6) and np.all(plan.q <= upper + 1e-6)
    assert np.all(np.abs(plan.qd) <= vmax + 1e-6)
    assert np.all(np.abs(plan.qdd) <= amax + 1e-6)
    assert plan.min_clearance_mm >= plan.clearance_margin_mm
    assert np.all(np.diff(plan.view_times_s) >= 0)


def test_demo_spiral_plans_within_every_limit(scanner):
    plan = plan_scan(scanner, small_protocol(views=60))
    assert_plan_is_safe(plan, scanner)
    assert len(plan.achieved) == 60
    # IK converges to 1e-7 m: the realised views match the protocol's to 1e-3 mm
    assert all(a.isclose(d, atol_mm=1e-3) for a, d in zip(plan.achieved, plan.desired, strict=True))
    start, end = plan.phases["scan"]
    assert plan.view_times_s[0] == pytest.approx(start) and plan.view_times_s[-1] <= end
    # the view times are where the trajectory passes the views' configurations
    for i in (0, 17, 59):
        k = int(np.argmin(np.abs(plan.t_s - plan.view_times_s[i])))
        step = np.abs(plan.qd[k]) * 0.02
        assert np.all(np.abs(plan.q[k] - plan.view_q[i]) <= step + 1e-6)
    # two passes of 360 degrees (end views included): the rotary carries the orbit out and
    # back, the arms only trim (their home postures differ from the exact tool poses)
    rotary = plan.view_q[:, 0]
    assert rotary[29] - rotary[0] == pytest.approx(360.0, abs=0.1)
    assert rotary[59] == pytest.approx(rotary[0], abs=0.1)
    assert np.ptp(plan.view_q[:, 2:], axis=0).max() < 0.5
    # time-optimal: within 15 % of the slowest axis at its limits (the rotary here)
    assert plan.scan_duration_s <= 1.15 * plan.lower_bound_s


def test_fluoroscopy_pose_is_held_still(scanner):
    protocol = small_protocol(
        kind="static", views=30, start_deg=90.0, passes=1, z_travel_mm=None, arc_deg=None
    )
    plan = plan_scan(scanner, protocol)
    assert_plan_is_safe(plan, scanner)
    assert np.ptp(plan.view_q, axis=0).max() < 1e-9
    np.testing.assert_allclose(plan.achieved[0].source_mm, [600.0, 0.0, 480.0], atol=1e-4)


def test_a_patient_envelope_that_reaches_the_panel_is_refused():
    """The panel's front face turns 400 mm from the axis; a 390 mm envelope leaves 10 mm,
    less than the 20 mm margin."""
    cylinders = [{"center_xy_mm": [0, 0], "radius_mm": 390, "z_min_mm": 0, "z_max_mm": 1800}]
    model = ScannerModel(scanner_config(obstacles={"patient": cylinders}))
    with pytest.raises(CollisionError) as info:
        plan_scan(model, small_protocol(views=12))
    message = str(info.value)
    assert message.startswith("view 0:")
    assert "detector_tool and patient0 are 10.0 mm apart" in message
    assert "clearance margin of 20 mm" in message


def test_a_view_above_the_lift_range_is_refused(scanner):
    protocol = small_protocol(views=12, isocenter_mm=(0.0, 0.0, 2300.0))
    with pytest.raises(
        JointLimitError,
        match=r"view 0: joint lift = 1\d{3}\.\d mm is outside its "
        r"range \[0\.0 mm, 1800\.0 mm\]",
    ):
        plan_scan(scanner, protocol)


def test_a_detector_beyond_the_arms_reach_is_refused(scanner):
    protocol = small_protocol(views=12, sdd_mm=2200.0)
    with pytest.raises(UnreachableError, match="view 0: the detector arm \\(ur5e, reach 1016 mm"):
        plan_scan(scanner, protocol)


def test_sampling_catches_an_obstacle_between_two_clear_samples():
    """The focal spot sweeps 40 degrees past a pole standing at 20 degrees: both ends are clear,
    the middle is not. Refinement to the travel bound finds it."""
    angle = math.radians(20.0)
    pole = {
        "center_xy_mm": [600 * math.sin(angle), -600 * math.cos(angle)],
        "radius_mm": 40,
        "z_min_mm": 0,
        "z_max_mm": 1800,
    }
    legs = scanner_config().obstacles.patient
    model = ScannerModel(
        scanner_config(obstacles={"patient": [*(c.model_dump() for c in legs), pole]})
    )
    q0 = model.neutral()
    q0[model.index["lift"]] = 0.2
    q1 = q0.copy()
    q1[model.index["rotary"]] = math.radians(40.0)
    assert min(model.clearance(q0)[0], model.clearance(q1)[0]) > 0.02  # both ends clear
    path = TimedPath(np.array([0.0, 4.0]), np.array([q0, q1]), np.zeros((2, 14)), np.zeros((2, 14)))
    found = motion_clearance(model, path, lambda t: q0 + np.outer(t / 4.0, q1 - q0))
    assert found.distance_m < 0
    assert "patient3" in found.pair
    assert found.samples > 2


def test_timing_refuses_a_path_that_stands_still_and_bounds_are_exact():
    with pytest.raises(TimingError, match="pass 3: two consecutive views share"):
        time_pass(np.zeros((3, 2)), np.ones(2), np.ones(2), "pass 3")
    # one joint, 10 units at v = 2, a = 1: accelerate 2 s (2 units), cruise 3 s, brake 2 s
    assert rest_to_rest_lower_bound(
        np.array([[0.0], [10.0]]), np.array([2.0]), np.array([1.0])
    ) == pytest.approx(7.0)
    # out and back: two such runs
    assert rest_to_rest_lower_bound(
        np.array([[0.0], [10.0], [0.0]]), np.array([2.0]), np.array([1.0])
    ) == pytest.approx(14.0)
    # too short to cruise: triangle, 2 sqrt(L / a)
    assert rest_to_rest_lower_bound(
        np.array([[0.0], [1.0]]), np.array([2.0]), np.array([1.0])
    ) == pytest.approx(2.0)


@settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    kind=st.sampled_from(["circular", "short_scan", "reverse_spiral"]),
    views=st.sampled_from([12, 24, 36]),
    sid=st.floats(450.0, 750.0),
    gap=st.floats(250.0, 650.0),
    z=st.floats(250.0, 1300.0),
    travel=st.floats(0.0, 300.0),
    start=st.floats(-90.0, 90.0),
)
def test_random_protocols_plan_safely_or_fail_with_a_typed_error(
    scanner, kind, views, sid, gap, z, travel, start
):
    orbit = {
        "kind": kind,
        "views": views,
        "sid_mm": sid,
        "sdd_mm": sid + gap,
        "isocenter_mm": (0.0, 0.0, z),
        "start_deg": start,
        "arc_deg": None,
        "passes": 2 if kind == "reverse_spiral" else 1,
        "z_travel_mm": travel if kind == "reverse_spiral" else None,
    }
    try:
        plan = plan_scan(scanner, small_protocol(**orbit))
    except PlanningError as err:
        message = str(err)
        assert message.startswith(("view ", "approach", "retreat", "pass ", "turn ")), message
        assert any(word in message for word in ("mm", "deg", "limit")), message
        return
    assert_plan_is_safe(plan, scanner)
    assert plan.min_clearance_mm >= plan.clearance_margin_mm
    assert RESOLUTION_M * 1000 < plan.clearance_margin_mm  # sampling cannot hide a contact
