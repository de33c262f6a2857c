"""A small matched knee case for registration tests.

The knee phantom on a 1 mm grid, a lateral view of 160 x 160 pixels of 1.92 mm (307 mm panel,
magnification 1.5), frames rendered as scene DRRs at the true poses of a 12-frame, 30 degree
squat with quantum noise. The squat's motion and the noise follow the ``seed`` option (0: the
case the bounds were set on).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from recon.geometry import DetectorSpec, View
from recon.volume import Volume, VolumeGrid
from registration.drr import BoneModel, SoftTissue, bone_models, scene
from registration.labels import BONE_UNITS
from sim.fluoro import add_fluoro_noise, lateral_view
from sim.motion import squat_motion
from sim.phantoms.knee import KneePhantomSpec, rasterize_knee

BONES = tuple(BONE_UNITS)  # the static scan's bones, the bodies tracked

SPEC = KneePhantomSpec()
GRID = VolumeGrid.centered((90, 90, 220), 1.0, (0.0, -4.0, 490.0))
FRAMES = 12


@dataclass(frozen=True)
class KneeCase:
    volume: Volume
    labels: Volume
    models: dict[str, BoneModel]
    soft: SoftTissue
    view: View
    truth: list[dict[str, np.ndarray]]
    frames: np.ndarray


@pytest.fixture(scope="session")
def knee_case(seed) -> KneeCase:
    labels, mu = rasterize_knee(SPEC, GRID, supersample=1)
    volume, labels = Volume(mu, GRID, "1/mm"), Volume(labels, GRID, "label")
    models = bone_models(volume, labels)
    soft = SoftTissue.of(volume, labels)
    view = lateral_view(SPEC, DetectorSpec(rows=160, cols=160, pixel_pitch_mm=1.92))
    motion = squat_motion(SPEC, frames=FRAMES, max_flexion_deg=30.0, seed=seed)
    truth = [{b: motion.poses[b][k] for b in BONES} for k in range(FRAMES)]
    clean = np.stack([scene(view, models, t, soft) for t in truth])
    frames = add_fluoro_noise(clean, 2.0e5, np.random.default_rng(3 + seed))[1]
    return KneeCase(volume, labels, models, soft, view, truth, frames)
