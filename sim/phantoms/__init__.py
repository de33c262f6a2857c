"""Digital phantoms: additive ellipsoids (Shepp–Logan) and a standing knee.

Both give ground truth in world mm (docs/conventions.md frame): ellipsoid phantoms have exact
analytic projections; the knee phantom has labels, attenuation, bone poses and landmarks.
"""

from __future__ import annotations

from sim.phantoms.ellipsoids import (
    Ellipsoid,
    ellipsoid_line_integrals,
    project_ellipsoids,
    rasterize_ellipsoids,
    shepp_logan_3d,
)
from sim.phantoms.knee import (
    KneePhantomSpec,
    attenuation_per_mm,
    knee_bone_poses,
    knee_grid,
    knee_landmarks,
    knee_sdf,
    label_points,
    rasterize_knee,
)

__all__ = [
    "Ellipsoid",
    "KneePhantomSpec",
    "attenuation_per_mm",
    "ellipsoid_line_integrals",
    "knee_bone_poses",
    "knee_grid",
    "knee_landmarks",
    "knee_sdf",
    "label_points",
    "project_ellipsoids",
    "rasterize_ellipsoids",
    "rasterize_knee",
    "shepp_logan_3d",
]
