"""The simulated knee replacement (sim.tka): the grand-challenge subject's components on its
bones, placed by its OpenSim model and moved through its measured gait."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from recon.geometry import DetectorSpec
from registration.implants import ray_lengths
from sim.fluoro import lateral_view
from sim.phantoms.knee import KneePhantomSpec
from sim.tka import (
    LEG_RADIUS_MM,
    OSIM_TO_LPS,
    cylinder_chords,
    leg_chords,
    load_tka,
    read_gait,
    simulate_tka_fluoro,
    tka_motion,
)

DATA = Path(__file__).resolve().parents[3] / "shared" / "data" / "grand-challenge-tka"
pytestmark = pytest.mark.skipif(not DATA.is_dir(), reason=f"no grand-challenge data at {DATA}")
CENTER_MM = np.array([0.0, 0.0, 490.0])


@pytest.fixture(scope="module")
def knee():
    knee = load_tka(DATA)
    gait = read_gait(DATA / "kinematics" / "fluoroscopic_gait.sto")
    return knee, tka_motion(knee, gait, 12, CENTER_MM)


def test_the_femoral_component_rides_on_the_insert_through_the_gait(knee):
    """At every frame the femoral component rides on the insert: its nearest vertex within
    5 mm of the insert's surface, none of it more than 2 mm inside (a wrong axis or sign in
    the model's frames or the joint puts it 30 mm or more off; the unloaded swing lifts it
    a few mm in our reading of the file's translations); the flexion is a gait's, 5 deg at
    heel strike to about 50 in swing; the tray was read closed (two fins removed)."""
    knee, motion = knee
    insert = knee.meshes["tibial_insert"]
    tree, normals = cKDTree(insert.vertices), insert.vertex_normals
    for k in range(len(motion.frames)):
        T = np.linalg.inv(motion.poses["tibia_r"][k]) @ motion.poses["femur_r"][k]
        points = knee.meshes["femoral_component"].vertices @ T[:3, :3].T + T[:3, 3]
        distance, nearest = tree.query(points)
        depth = -np.einsum("ij,ij->i", points - insert.vertices[nearest], normals[nearest])
        assert distance.min() < 5.0
        assert depth[distance < 5.0].max(initial=0.0) < 2.0
    assert motion.flexion_deg[0] < 10.0 and 45.0 < motion.flexion_deg.max() < 60.0
    assert knee.repairs["tibial_tray"] == ("removed 2 piece(s) of no volume",)


def test_a_frame_shows_the_metal_as_the_beam_stopped(knee):
    """Through 5 mm or more of CoCr (mu 0.8/mm at 70 keV) at most e^-4 of the beam passes:
    those pixels read above 0.98 (noise: 2e4 photons); beside the knee, through the leg's
    water alone, the frame reads well below."""
    knee, motion = knee
    detector = DetectorSpec(rows=96, cols=96, pixel_pitch_mm=3.2)
    view, frames = simulate_tka_fluoro(
        knee, motion, detector, CENTER_MM, 2.0e4, seed=1, supersample=1, blur_mm=0.0
    )
    assert frames.shape == (12, 96, 96)
    femoral = knee.meshes["femoral_component"]
    metal = ray_lengths(view, femoral.vertices, femoral.faces, motion.poses["femur_r"][0]) > 5.0
    assert metal.sum() > 20 and frames[0][metal].min() > 0.98
    assert frames[0][:, :3].mean() < 0.5  # the panel's edge: air, or the leg's skin
    front, shown = simulate_tka_fluoro(  # a second camera, turned 90 deg: from the front
        knee, motion, detector, CENTER_MM, 2.0e4, seed=1, supersample=1, blur_mm=0.0, turn_deg=90
    )
    assert abs(np.dot(view.normal, front.normal)) < 1e-9  # the panels at 90 deg
    assert front.source_mm[1] < CENTER_MM[1] - 100.0  # anterior is -y (LPS)
    metal = ray_lengths(front, femoral.vertices, femoral.faces, motion.poses["femur_r"][0]) > 5.0
    assert metal.sum() > 20 and shown[0][metal].min() > 0.98


def test_the_leg_bends_with_the_knee():
    """Straight, the leg is the vertical cylinder about the knee; bent 60 degrees, the ray
    through a point of the shank's axis crosses at least its diameter (less the half pixel it
    misses the point by), and the ray through where the straight shank was crosses no leg."""
    detector = DetectorSpec(rows=64, cols=64, pixel_pitch_mm=4.8)
    view = lateral_view(KneePhantomSpec(side="right"), detector, target_mm=CENTER_MM)
    straight = np.eye(4)
    straight[:3, :3] = OSIM_TO_LPS  # the bodies' y (superior) along the world's z
    vertical = cylinder_chords(view, CENTER_MM)
    assert np.allclose(leg_chords(view, CENTER_MM, straight, straight), vertical, atol=1e-9)
    bent = straight.copy()
    bent[:3, :3] = Rotation.from_euler("x", 60.0, degrees=True).as_matrix() @ OSIM_TO_LPS
    chords = leg_chords(view, CENTER_MM, straight, bent)
    shank = np.rint(view.project((CENTER_MM - 100.0 * bent[:3, 1])[None])[0]).astype(int)
    assert chords[shank[1], shank[0]] > 2.0 * np.sqrt(LEG_RADIUS_MM**2 - 3.0**2)
    was = np.rint(view.project((CENTER_MM - [0.0, 0.0, 100.0])[None])[0]).astype(int)
    assert vertical[was[1], was[0]] > 0.0 and chords[was[1], was[0]] == 0.0
