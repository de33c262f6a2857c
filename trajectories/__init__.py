"""Robot kinematics, collision checks and timing of scans: poses in, joint trajectories out.

Inside this package lengths are metres and angles radians (Pinocchio's units); everything it
hands out (plans, reports, files) is in millimetres and degrees. The public names below load
their module on first use.
"""

from recon._exports import lazy  # recon first: its OpenMP wait policy before Pinocchio's libgomp

_EXPORTS = {
    "ScannerModel": "trajectories.model",
    "ScannerConfig": "trajectories.config",
    "Plan": "trajectories.plan",
    "plan_scan": "trajectories.plan",
    "JointMove": "trajectories.move",
    "plan_move": "trajectories.move",
    "park_pose": "trajectories.move",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy(__name__, _EXPORTS)
