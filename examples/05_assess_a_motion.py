"""Knee kinematics of a motion: the knee phantom's labels (the static scan) and its bones' poses
through a 20-frame squat to 60 degrees (as a registration writes them), assessed as the
report does: flexion, varus, the medial and lateral TP-condyle distances and their difference.
"""

from assessment import assess_knee
from recon import Volume
from registration import BodyPose
from sim.motion import squat_motion
from sim.phantoms import KneePhantomSpec, knee_grid, rasterize_knee

spec = KneePhantomSpec()
grid = knee_grid(spec, spacing_mm=1.0)
labels = Volume(rasterize_knee(spec, grid, supersample=1)[0], grid, "label")
motion = squat_motion(spec, frames=20, max_flexion_deg=60.0)
poses = [
    BodyPose(frame, bone, motion.poses[bone][frame])
    for frame in range(20)
    for bone in ("femur", "tibia_fibula")
]
kin = assess_knee(labels, poses, spec.side).kinematics
peak = int(kin.flexion_deg.argmax())
medial, lateral = kin.medial_distance_mm[peak], kin.lateral_distance_mm[peak]
print(
    f"flexion {kin.flexion_deg.min():.0f}..{kin.flexion_deg.max():.0f} deg; at the peak "
    f"medial {medial:.1f} mm, lateral {lateral:.1f} mm, max |MLD| {abs(kin.mld_mm).max():.2f} "
    f"mm, {int(kin.flagged.sum())} frames flagged"
)
