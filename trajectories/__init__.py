"""Robot kinematics, collision checks and timing of scans: poses in, joint trajectories out.

Inside this package lengths are metres and angles radians (Pinocchio's units); everything it
hands out (plans, reports, files) is in millimetres and degrees.
"""
