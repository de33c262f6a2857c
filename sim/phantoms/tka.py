"""The knee replacement the simulated scanner images: what it is made from and where it
stands (the scene itself, and its projection: sim.tka_ct)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

DEFAULT_DATA = Path(__file__).resolve().parents[3] / "shared" / "data" / "grand-challenge-tka"
"""Where the grand-challenge knee replacement is: ``../shared/data`` beside the repository."""


class TkaPhantomSpec(BaseModel):
    """The knee replacement as the simulated scanner images it (configs/phantoms/tka.yaml)."""

    model_config = ConfigDict(extra="forbid")

    data: str = Field(
        str(DEFAULT_DATA),
        description="the grand-challenge-tka folder (meshes/, DM.osim, kinematics/)",
    )
    joint_height_mm: float = Field(
        480.0, ge=200.0, le=1000.0, description="the knee joint centre's height, mm"
    )
    gait_sample: int = Field(
        0, ge=0, le=100, description="the gait file's sample the subject stands in (0: heel strike)"
    )
    leg_radius_mm: float = Field(
        68.0, ge=45.0, le=120.0, description="the leg's soft tissue: a water cylinder, mm"
    )
    metal: bool = Field(
        True,
        description="the components are metal; false: cancellous bone in their place (a reference)",
    )
    supersample: int = Field(2, ge=1, le=4, description="rays per pixel along each axis")

    @property
    def center_mm(self) -> np.ndarray:
        """The knee's axis point at the joint's height (its cross-section's centre), mm."""
        return np.array([0.0, 0.0, self.joint_height_mm])
