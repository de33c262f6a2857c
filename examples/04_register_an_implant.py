"""A DRR of an implant component and one registered frame: a tray-like mesh rendered at a known
pose (the "frame"), found again from 4 mm and 4 degrees off; prints the TRE before and after."""

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from registration import MATERIALS, Settings, Tracker, implant_model
from registration.jointtrack import camera_view

plate = trimesh.creation.box(extents=(70.0, 4.0, 50.0))
keel = trimesh.creation.cylinder(radius=6.0, height=40.0)
keel.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (1, 0, 0)))
keel.apply_translation((8.0, -22.0, 0.0))
tray = implant_model("tibial_tray", trimesh.util.concatenate([plate, keel]), MATERIALS["CoCr"])

# JointTrack's camera: the source at the origin, a 256 x 256 panel of 0.6 mm 1198 mm away
view = camera_view(1198.0, 0.0, 0.0, 0.6, 256, 256)
truth = np.eye(4)
truth[:3, :3] = Rotation.from_euler("xyz", (10, -5, 20), degrees=True).as_matrix()
truth[:3, 3] = (0.0, 0.0, -1080.0)  # 118 mm in front of the panel
frame = tray.render(view, truth)[None]  # the DRR stands for a frame of line integrals
start = truth.copy()
start[:3, :3] = Rotation.from_euler("z", 4, degrees=True).as_matrix() @ truth[:3, :3]
start[:3, 3] += (4.0, 0.0, 0.0)

settings = Settings(pyramid_mm=[1.2, 0.6], global_init=False)  # refine from the start only
tracker = Tracker(view, frame, {"tibial_tray": tray}, settings)  # it plays the tibia
result = tracker.register(0, {"tibial_tray": start}, [])


def tre(T: np.ndarray) -> float:
    """Mean distance (mm) of the tray's points at ``T`` from where the true pose puts them."""
    d = T - truth
    return float(np.linalg.norm(tray.points_mm @ d[:3, :3].T + d[:3, 3], axis=1).mean())


found = result.bodies["tibial_tray"].T_world_body
print(f"TRE {tre(start):.2f} mm at the start, {tre(found):.3f} mm registered")
