"""The scanner's hardware description (``configs/scanner.yaml``): axes, arms, tools, obstacles.

Frames: the world (docs/conventions.md) -> rotary axis about world z through the platform centre ->
carriage lifted along z by the lift -> arm bases mounted on the carriage. Every placement is
``xyz_mm`` plus extrinsic ``rpy_deg`` (scipy "xyz"). Units are in the field names.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from recon.geometry import DetectorSpec
from trajectories.arms import ARMS


class _Frozen(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


class Placement(_Frozen):
    """A rigid placement: translation (mm) and extrinsic x-y-z rotation (degrees)."""

    xyz_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)


class RotaryAxis(_Frozen):
    """Bearing that turns the carriage about world z."""

    range_deg: tuple[float, float] = (-370.0, 370.0)
    max_speed_deg_s: float = Field(30.0, gt=0.0, le=360.0)
    max_accel_deg_s2: float = Field(30.0, gt=0.0, le=720.0)

    @model_validator(mode="after")
    def _ordered(self) -> RotaryAxis:
        if not self.range_deg[0] < self.range_deg[1]:
            raise ValueError(f"range_deg = {self.range_deg}: lower limit must be below upper")
        return self


class LiftAxis(_Frozen):
    """Vertical lift of the carriage above the platform."""

    range_mm: tuple[float, float] = (0.0, 1800.0)
    max_speed_mm_s: float = Field(100.0, gt=0.0, le=1000.0)
    max_accel_mm_s2: float = Field(200.0, gt=0.0, le=5000.0)

    @model_validator(mode="after")
    def _ordered(self) -> LiftAxis:
        lo, hi = self.range_mm
        if not 0.0 <= lo < hi <= 1800.0:
            raise ValueError(f"range_mm = {self.range_mm}: need 0 <= lower < upper <= 1800")
        return self


class ArmConfig(_Frozen):
    """One arm: its type, where its base sits on the carriage, its tool and home posture."""

    model: Literal["ur3e", "ur5e", "ur10e"] = "ur5e"
    mount: Placement
    tool: Placement = Field(description="tool frame on the flange")
    home_deg: tuple[float, float, float, float, float, float]
    speed_scale: float = Field(1.0, gt=0.0, le=1.0, description="share of the maker's speeds")
    accel_scale: float = Field(1.0, gt=0.0, le=1.0, description="share of the default accel")

    @model_validator(mode="after")
    def _home_in_range(self) -> ArmConfig:
        limit = ARMS[self.model].range_deg
        for i, q in enumerate(self.home_deg):
            if abs(q) > limit:
                raise ValueError(f"home_deg[{i}] = {q} is outside +-{limit} deg of a {self.model}")
        return self


class Box(_Frozen):
    """An axis-aligned box in its parent frame: centre and full size, mm."""

    center_mm: tuple[float, float, float]
    size_mm: tuple[float, float, float] = Field(description="full extents x, y, z")

    @model_validator(mode="after")
    def _positive(self) -> Box:
        if min(self.size_mm) <= 0:
            raise ValueError(f"size_mm = {self.size_mm}: every extent must be > 0")
        return self


class Cylinder(_Frozen):
    """An upright cylinder in the world: axis at ``center_xy_mm``, from ``z_min_mm`` up."""

    center_xy_mm: tuple[float, float] = (0.0, 0.0)
    radius_mm: float = Field(gt=0.0, le=2000.0)
    z_min_mm: float = 0.0
    z_max_mm: float

    @model_validator(mode="after")
    def _ordered(self) -> Cylinder:
        if self.z_max_mm <= self.z_min_mm:
            raise ValueError(f"z_max_mm = {self.z_max_mm} must exceed z_min_mm = {self.z_min_mm}")
        return self


class Tube(_Frozen):
    """X-ray tube housing on the source tool frame (focal spot at the origin, beam along +z)."""

    housing: Box


class Panel(_Frozen):
    """Flat-panel detector on the detector tool frame (panel centre at the origin, x = e_u,
    y = e_v, z toward the source): pixels and housing."""

    pixels: DetectorSpec
    housing_thickness_mm: float = Field(40.0, gt=0.0, le=200.0)
    housing_border_mm: float = Field(15.0, ge=0.0, le=200.0)


class Obstacles(_Frozen):
    """Fixed and carried obstacles, and the clearance every planned motion keeps from them."""

    clearance_margin_mm: float = Field(20.0, ge=0.0, le=200.0)
    platform: Cylinder = Field(description="weight-bearing platform (world)")
    column: Box = Field(description="lift column, carriage frame")
    patient: tuple[Cylinder, ...] = Field(min_length=1, description="standing-patient envelope")


class ScannerConfig(_Frozen):
    """The whole scanner."""

    name: str = Field(min_length=1, max_length=80)
    rotary: RotaryAxis
    lift: LiftAxis
    source_arm: ArmConfig
    detector_arm: ArmConfig
    tube: Tube
    panel: Panel
    obstacles: Obstacles
