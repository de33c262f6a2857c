"""The knee replacement on the simulated CBCT (sim.tka_ct) and its spectrum (sim.spectrum):
metal hardens the beam and starves the panel, the truth holds every part where its mesh is."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from recon.geometry import DetectorSpec, circular_orbit
from recon.volume import VolumeGrid
from registration.implants import ray_lengths
from sim.phantoms.tka import TkaPhantomSpec
from sim.spectrum import COMPOSITIONS, tube_spectrum
from sim.tka import cylinder_chords
from sim.tka_ct import BODY_OF_PART, METAL_LABEL, tka_scene, tka_truth

UP = np.array([0.0, 0.0, 1.0])
DATA = Path(__file__).resolve().parents[3] / "shared" / "data" / "grand-challenge-tka"


def test_the_spectrum_hardens_and_metal_starves() -> None:
    """Behind more water the mean energy rises (beam hardening), and the polychromatic line
    integral through CoCr grows slower than its length (the monochromatic one at the entry
    spectrum's mean attenuation is linear)."""
    beam = tube_spectrum(110.0)
    assert beam.hardened("water", 200.0).effective_energy_kev() > beam.effective_energy_kev() + 5
    mu = COMPOSITIONS["CoCr"].mu_per_mm(beam.energies_kev)[None]
    p = [-np.log(beam.transmission(mu, np.array([[t]])))[0] for t in (2.0, 4.0, 8.0)]
    assert p[1] < 2 * p[0] and p[2] < 2 * p[1]
    assert p[2] > 5.0  # 8 mm of CoCr: under 1 % of the signal left
    with pytest.raises(ValueError, match="tube voltage 200"):
        tube_spectrum(200.0)


@pytest.mark.skipif(not DATA.is_dir(), reason=f"no grand-challenge data at {DATA}")
def test_the_scene_projects_its_metal_and_its_truth_holds_the_parts() -> None:
    spec = TkaPhantomSpec(data=str(DATA), supersample=1)
    scene = tka_scene(spec)
    grid = VolumeGrid.centered((70, 70, 150), 2.0, tuple(spec.center_mm))  # the stem's too
    truth = tka_truth(scene, grid, 110.0)
    labels, mu = truth.labels, truth.mu
    metal = labels == METAL_LABEL
    components = [layer for layer in scene.layers if "CoCr" in layer.materials]
    volume = sum(trimesh.Trimesh(c.vertices_mm, c.faces).volume for c in components)
    assert metal.sum() * 8.0 == pytest.approx(volume, rel=0.1)  # 2 mm voxels, thin metal
    assert np.median(mu[metal]) > 30 * np.median(mu[labels == 1])  # CoCr 65 x water
    panel = DetectorSpec(rows=64, cols=64, pixel_pitch_mm=4.0)
    view = circular_orbit(1, 600.0, 1000.0, panel, isocenter_mm=spec.center_mm)[0]
    reference = TkaPhantomSpec(data=str(DATA), supersample=1, metal=False)
    with_metal = scene.line_integrals(view, tube_spectrum(110.0))
    without = tka_scene(reference).line_integrals(view, tube_spectrum(110.0))
    assert with_metal.max() > 8.0 and without.max() < 6.0
    shadow = sum(ray_lengths(view, c.vertices_mm, c.faces, np.eye(4)) for c in components) > 0
    assert np.allclose(with_metal[~shadow], without[~shadow])  # only the metal differs
    assert np.all(with_metal[shadow] > without[shadow])
    scores = truth.near_metal_scores(labels)
    assert scores["bone"] == 1.0 and scores["femur"] == 1.0


@pytest.mark.skipif(not DATA.is_dir(), reason=f"no grand-challenge data at {DATA}")
def test_the_swaying_scene_moves_each_part_with_its_body() -> None:
    """At the reference pose the swaying scene is the still one; moved whole it is the still
    scene seen through the view carried the other way; the thigh moved alone changes only the
    rays through the thigh's parts and the leg's upper half."""
    spec = TkaPhantomSpec(data=str(DATA), supersample=1)
    scene, beam = tka_scene(spec), tube_spectrum(110.0)
    panel = DetectorSpec(rows=64, cols=64, pixel_pitch_mm=4.0)
    view = circular_orbit(1, 600.0, 1000.0, panel, isocenter_mm=spec.center_mm)[0]
    still = scene.line_integrals(view, beam)
    eye = {"thigh": np.eye(4), "shank": np.eye(4)}
    np.testing.assert_allclose(scene.line_integrals(view, beam, eye), still, rtol=0, atol=1e-9)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.radians([0.5, -0.8, 1.5])).as_matrix()
    T[:3, 3] = [2.0, -1.5, 3.0]
    whole = scene.line_integrals(view, beam, {"thigh": T, "shank": T})
    carried = scene.line_integrals(view.transformed(np.linalg.inv(T)), beam)
    np.testing.assert_allclose(whole, carried, rtol=0, atol=1e-6)
    assert np.abs(whole - still).max() > 1.0  # the metal's edges moved by millimetres
    thigh_only = scene.line_integrals(view, beam, {"thigh": T, "shank": np.eye(4)})
    thigh_parts = [layer for layer in scene.layers if BODY_OF_PART[layer.part] == "thigh"]
    touched = np.zeros((64, 64), bool)
    for pose in (np.eye(4), T):
        moved = view.transformed(np.linalg.inv(pose))
        for layer in thigh_parts:
            touched |= ray_lengths(view, layer.vertices_mm, layer.faces, pose) > 0
        touched |= cylinder_chords(moved, spec.center_mm, spec.leg_radius_mm, side=UP) > 0
    assert 0.2 < touched.mean() < 0.8
    np.testing.assert_allclose(thigh_only[~touched], still[~touched], rtol=0, atol=1e-9)
    assert np.abs(thigh_only - still)[touched].max() > 1.0
