"""Tracking a knee replacement through real fluoroscopy: the femoral component and the tibial
tray of the JointTrack data set (its first three frames), started where JointTrack's own poses
put them in the first frame and followed from there; prints each component's NCC per frame.
(Without ``start``, track finds each component in the first frame itself: minutes.)"""

from pathlib import Path

import registration

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "tka-fluoro-jtml"
files = sorted(DATA.glob("*.tif"))[:3]
frames = registration.read_frames(files, pixel_pitch_mm=0.373)  # the calibration's pixel
view = registration.read_view(frames, calibration_path=DATA / "calibration.txt")
femoral = registration.implant_body("femoral_component", DATA / "KR_left_8_fem.stl", "CoCr")
tray = registration.implant_body("tibial_tray", DATA / "KR_left_8_tib.stl", "CoCr")
jts = {"femoral_component": "fem.jts", "tibial_tray": "tib.jts"}  # JointTrack's poses of each
start = {b: registration.read_jointtrack_poses(DATA / f, view)[0] for b, f in jts.items()}
bodies = {"femoral_component": femoral, "tibial_tray": tray}  # each plays the bone it replaces
results = registration.track(frames, view, bodies, start=start)
for result in results:
    print(f"frame {result.frame}:", {b: round(r.ncc, 3) for b, r in result.bodies.items()})
