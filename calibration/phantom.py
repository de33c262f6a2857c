"""The steel-ball (BB) calibration phantom: a radiolucent PMMA body with steel balls on a helix.

Ball i sits at angle ``i * angle_step_deg`` and height ``(i - (N-1)/2) * z_step_mm`` on a helix
about the phantom's z axis. Consecutive balls differ little in depth, so in any cone-beam view
their projections keep the helix's order along the detector rows; a missing ball leaves a
double gap. Ball sizes follow a binary code (``code``: 1 = large) in which every window of
:data:`CODE_WINDOW` consecutive balls is unique, which pins the index of the first ball seen.
Together: every ball is identified from its own view alone (calibration.identify). The
phantom is specified here, by the package that measures it; sim.phantoms.bb renders it.
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator
from scipy.spatial.transform import Rotation

CODE_WINDOW = 5
"""Length of the code windows that are unique along the helix."""


class BBPhantomSpec(BaseModel):
    """The BB phantom (``configs/phantoms/bb_helix.yaml``) and where it stands."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    body_radius_mm: float = Field(70.0, gt=0.0, le=300.0, description="PMMA body radius")
    body_half_height_mm: float = Field(110.0, gt=0.0, le=500.0)
    body_mu_per_mm: float = Field(0.0214, ge=0.0, le=0.1, description="PMMA at 70 keV")
    ball_mu_per_mm: float = Field(0.47, gt=0.0, le=5.0, description="steel at 70 keV")
    helix_radius_mm: float = Field(45.0, gt=0.0, le=300.0)
    angle_step_deg: float = Field(15.0, gt=0.0, le=90.0)
    z_step_mm: float = Field(7.0, gt=0.0, le=50.0)
    small_diameter_mm: float = Field(2.0, gt=0.0, le=10.0)
    large_diameter_mm: float = Field(3.0, gt=0.0, le=10.0)
    code: str = Field(description="ball sizes along the helix: 1 large, 0 small")
    center_mm: tuple[float, float, float] = (0.0, 0.0, 480.0)
    rotation_deg: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0), description="extrinsic xyz rotation of the phantom in the world"
    )

    @model_validator(mode="after")
    def _check(self) -> BBPhantomSpec:
        if set(self.code) - {"0", "1"} or len(self.code) < CODE_WINDOW:
            raise ValueError(f"code must be >= {CODE_WINDOW} characters of 0/1, got {self.code!r}")
        windows = [self.code[i : i + CODE_WINDOW] for i in range(len(self.code) - CODE_WINDOW + 1)]
        if len(set(windows)) != len(windows):
            raise ValueError(f"code {self.code!r}: a window of {CODE_WINDOW} balls repeats")
        if self.large_diameter_mm < 1.3 * self.small_diameter_mm:
            raise ValueError("large_diameter_mm must be >= 1.3 x small_diameter_mm to tell sizes")
        if self.helix_radius_mm + self.large_diameter_mm >= self.body_radius_mm:
            raise ValueError("the helix must lie inside the body: helix_radius_mm too large")
        return self

    @property
    def balls(self) -> int:
        return len(self.code)

    def ball_positions_local_mm(self) -> np.ndarray:
        """Ball centres in the phantom's own frame, (N, 3) mm."""
        i = np.arange(self.balls)
        theta = np.radians(self.angle_step_deg) * i
        z = (i - 0.5 * (self.balls - 1)) * self.z_step_mm
        r = self.helix_radius_mm
        return np.column_stack((r * np.cos(theta), r * np.sin(theta), z))

    def ball_diameters_mm(self) -> np.ndarray:
        return np.where(
            np.array(list(self.code)) == "1", self.large_diameter_mm, self.small_diameter_mm
        )

    @property
    def T_world_phantom(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("xyz", self.rotation_deg, degrees=True).as_matrix()
        T[:3, 3] = self.center_mm
        return T

    def ball_positions_mm(self) -> np.ndarray:
        """Ball centres in the world, (N, 3) mm."""
        T = self.T_world_phantom
        return self.ball_positions_local_mm() @ T[:3, :3].T + T[:3, 3]
