"""Bodies play anatomical roles: the tracker orders, starts and carries them by role, and
files written under a body's older name (a component tracked as its bone) still read."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from recon.geometry import DetectorSpec, circular_orbit
from registration.implants import implant_model
from registration.meshes import MATERIALS
from registration.poses import BodyPose, write_poses
from registration.roles import playing, roles_of
from registration.tracker import Tracker
from study.jobs.register import _poses_by_body

VIEW = circular_orbit(1, 600.0, 1000.0, DetectorSpec(rows=32, cols=32, pixel_pitch_mm=2.0))[0]


def _model(name: str) -> object:
    return implant_model(name, trimesh.creation.box(extents=(20.0, 10.0, 15.0)), MATERIALS["CoCr"])


def test_a_researchers_names_with_roles_track_in_the_canonical_order_and_carry():
    """Bodies named freely, their roles given: registered tibia, femur, patella; the tibia and
    the femur searched alone on a first frame; the patella carried by the femur's body."""
    names = {"cap": "patella", "thigh": "femur", "shin": "tibia"}
    tracker = Tracker(VIEW, np.zeros((1, 32, 32)), {n: _model(n) for n in names}, roles=names)
    assert tracker.order == ("shin", "thigh", "cap")
    assert tracker.scene.carriers == {"cap": "thigh"}
    canonical = Tracker(
        VIEW,
        np.zeros((1, 32, 32)),
        {n: _model(n) for n in ("patella", "femoral_component", "tibial_tray")},
    )
    assert canonical.order == ("tibial_tray", "femoral_component", "patella")
    assert canonical.scene.carriers == {"patella": "femoral_component"}


def test_a_body_without_a_role_or_two_in_one_role_is_refused():
    with pytest.raises(ValueError, match="'tray_a' has no known role"):
        roles_of(["tray_a"])
    with pytest.raises(ValueError, match="role 'shin'"):
        roles_of(["tray_a"], {"tray_a": "shin"})
    with pytest.raises(ValueError, match="'tibia_fibula' and 'tibial_tray' both play the tibia"):
        roles_of(["tibia_fibula", "tibial_tray"])
    with pytest.raises(ValueError, match="no body plays the femur"):
        playing(["tibial_tray"], "femur")


def test_poses_written_under_a_bones_name_read_for_the_component_playing_it(tmp_path):
    """A poses.csv of an older run, its components written as femur and tibia_fibula, is the
    truth (or start) of the femoral component and the tray."""
    rng = np.random.default_rng(0)
    stacks = {b: np.tile(np.eye(4), (2, 1, 1)) for b in ("femur", "tibia_fibula")}
    for stack in stacks.values():
        stack[:, :3, 3] = rng.uniform(-20, 20, (2, 3))
    rows = [BodyPose(k, b, stacks[b][k]) for k in range(2) for b in stacks]
    path = write_poses(tmp_path / "poses.csv", rows, {b: np.zeros(3) for b in stacks})
    roles = roles_of(["tibial_tray", "femoral_component"])
    found = _poses_by_body(path, roles, VIEW, "true")
    np.testing.assert_array_equal(found["femoral_component"], stacks["femur"])
    np.testing.assert_array_equal(found["tibial_tray"], stacks["tibia_fibula"])
