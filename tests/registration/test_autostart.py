"""registration.autostart: candidate starts of implant components found on a frame alone, and
the tracker's best start among them."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from registration.autostart import binning, candidate_poses
from registration.implants import implant_model
from registration.jointtrack import camera_view
from registration.meshes import MATERIALS
from registration.settings import Settings
from registration.tracker import Tracker
from tests.registration.test_register_implants import component


@pytest.fixture(scope="module")
def two_components(seed):
    """A frame of two components (a C and a T; 256 x 256 pixels of 0.746 mm, 8-bit, noisy,
    the exposed field a band with dark shutters beside it): the view, the models, the true
    poses, the frame, its field and the C's candidates."""
    rng = np.random.default_rng(seed)
    view = camera_view(1198.0, 0.0, 0.0, 0.746, 256, 256)
    models = {b: implant_model(b, component(b), MATERIALS["CoCr"]) for b in ("femur", "tibia")}
    truth = {}
    for name, base in (("femur", (30.0, 15.0, -1080.0)), ("tibia", (-35.0, -20.0, -1085.0))):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("xyz", rng.uniform(-30, 30, 3), degrees=True).as_matrix()
        T[:3, 3] = base
        truth[name] = T
    shadow = sum(models[b].render(view, truth[b]) for b in models)
    intensity = 200.0 * (1.0 - np.clip(shadow, 0.0, 1.0)) + 40.0
    field = np.zeros((256, 256), dtype=bool)
    field[:, 32:224] = True
    counts = np.where(field, rng.poisson(intensity), 0).clip(0, 255)
    frame = 1.0 - counts / 255.0  # the attenuation stand-in: metal and shutters bright
    return view, models, truth, frame, field, candidate_poses(models["femur"], view, frame, field)


def test_each_component_is_found_where_it_lies(two_components, measured):
    """On a frame of two components (a C and a T; 256 x 256 pixels of 0.746 mm, 8-bit, noisy,
    the exposed field a band with dark shutters beside it) the candidates of each include one
    whose silhouette overlaps the true one by a Dice of 0.7 or more: well inside the box the
    tracker's search then covers (measured over seeds 0-5: best 0.90-0.95 for the C, 0.78-0.87
    for the T, whose mirror images cast near-equal shadows; the same with 1 and 2 threads).
    The second component, searched with the first placed, is not put on the first's shadow.
    Orientations are not compared: both shapes have turns that cast the same silhouette."""
    view, models, truth, frame, field, femur = two_components

    def centre(name: str, T: np.ndarray) -> np.ndarray:
        return view.project(T[:3, :3] @ models[name].centroid_mm + T[:3, 3])[0]

    near = (truth["femur"][:3, 3], 120.0)
    tibia = candidate_poses(
        models["tibia"], view, frame, field, near, [(models["femur"], truth["femur"])]
    )
    for name, found in (("femur", femur), ("tibia", tibia)):
        true_shadow = models[name].render(view, truth[name]) > 0
        overlaps = []
        for T in found:
            ours = models[name].render(view, T) > 0
            overlaps.append(2 * (ours & true_shadow).sum() / (ours.sum() + true_shadow.sum()))
        measured(f"{name}_best_dice", float(max(overlaps)), above=0.7)
    femur_centre = centre("femur", truth["femur"])
    assert all(np.hypot(*(centre("tibia", T) - femur_centre)) > 2 * binning(view) for T in tibia)


def test_the_best_start_is_the_best_scoring_candidate_searched(two_components):
    """The tracker's best start of a component (its candidates' searches run at once) is the
    candidate that scores best once searched, each searched and scored alone: to the bit."""
    view, models, _, frame, field, found = two_components
    femur = {"femur": models["femur"]}
    settings = Settings(de_popsize=2, de_maxiter=2)
    tracker = Tracker(view, frame[None].astype(np.float32), femur, settings, None, field)
    candidates = found[:3]
    assert len(candidates) == 3
    best = tracker.best_start(0, "femur", candidates, {})
    scene, scores = tracker.scene, []
    for T in candidates:
        pose, _ = scene.global_search(0, "femur", {"femur": T}, 2.0, True)
        objective = scene.objective(0, scene.levels[0], "femur", {"femur": pose}, True)
        scores.append((objective.scores(pose)[0], pose))
    assert np.array_equal(best, max(scores, key=lambda pair: pair[0])[1])
