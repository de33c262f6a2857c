"""The knee replacement on the simulated CBCT (sim.tka_ct) and its spectrum (sim.spectrum):
metal hardens the beam and starves the panel, the truth holds every part where its mesh is."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from recon.geometry import DetectorSpec, circular_orbit
from recon.volume import VolumeGrid
from registration.implants import ray_lengths
from sim.phantoms.tka import TkaPhantomSpec
from sim.spectrum import COMPOSITIONS, tube_spectrum
from sim.tka_ct import METAL_LABEL, tka_scene, tka_truth

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
