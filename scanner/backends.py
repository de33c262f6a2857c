"""The UR backend (UR arms over ur-rtde, the lift/rotary stage and the X-ray generator over
serial, a GigE Vision panel), registered as ``ur``; and a session's way to any backend by name.

Every backend runs the same state machine, storage and checks; only the devices differ. The UR
backend reads a GigE Vision panel (``detector: gige``, :class:`scanner.gige.GigEPanel`) or a
registered panel kind by its name (``detector: sim``: the simulator's panel rendering the
subject through the view the arms' MEASURED joints realise, which lets the same scan run against
the fake UR controllers without a panel; its config is ``simulated_panel``).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator, model_validator

from scanner.generator import SerialGenerator
from scanner.hardware import Backend
from scanner.registry import BackendKind, Opened, Rig, panel_kind, register_backend
from scanner.serial_link import DEFAULT_BAUDRATE
from scanner.spellman import SpellmanGenerator
from scanner.stage import SerialStage
from trajectories.arms import ARM_JOINTS


class URBackendSpec(BaseModel):
    """The UR backend's connections (configs/backends/ur.yaml)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    source_host: str = Field(description="IP of the source arm's UR controller")
    detector_host: str = Field(description="IP of the detector arm's UR controller")
    stage_port: str = Field(description="serial port of the lift/rotary controller")
    generator_port: str = Field(description="serial port of the X-ray generator")
    generator_protocol: Literal["line", "spellman"] = Field(
        "line", description="the generator's serial protocol: ours, or Spellman's"
    )
    generator_kv_full_scale: float = Field(
        150.0, gt=0.0, description="Spellman: kV at set-point count 4095 (the model's), kVp"
    )
    generator_ma_full_scale: float = Field(
        100.0, gt=0.0, description="Spellman: mA at set-point count 4095 (the model's), mA"
    )
    baudrate: int = Field(115200, gt=0)
    servo_lookahead_s: float = Field(0.1, ge=0.03, le=0.2)
    servo_gain: float = Field(300.0, ge=100.0, le=2000.0)
    detector: str = Field(
        "sim", description="gige: the GigE Vision panel; another name: that registered panel kind"
    )
    gige_device: str | None = Field(None, description="the panel's Aravis device id or IPv4")
    gige_trigger: Literal["software", "line0"] = Field(
        "software", description="software: the driver triggers each window; line0: the generator"
    )
    gige_window_ms: float = Field(100.0, gt=0.0, le=5000.0, description="integration window")
    gige_frame_timeout_s: float = Field(
        0.5, gt=0.0, le=10.0, description="longest wait for a frame (a dead panel's bound)"
    )
    simulated_panel: dict[str, Any] = Field(
        default_factory=dict,
        validate_default=True,
        description="the config of the panel kind ``detector`` names",
    )
    detector_maps: str | None = Field(
        None, description="folder of the panel's maps (cbct detector-calibrate)"
    )
    max_map_age_days: float = Field(7.0, gt=0.0, description="oldest detector maps a scan uses")

    @field_validator("simulated_panel")
    @classmethod
    def _panel_config(cls, config: dict[str, Any], info: ValidationInfo) -> dict[str, Any]:
        """The config of the panel kind ``detector`` names, checked and complete."""
        name = info.data.get("detector", "gige")
        if name == "gige":
            return config
        return panel_kind(name).config.model_validate(config).model_dump(mode="json")

    @model_validator(mode="after")
    def _gige_needs_a_device(self) -> URBackendSpec:
        if self.detector == "gige" and not self.gige_device:
            raise ValueError("detector: gige needs gige_device (the panel's device id or IP)")
        if self.gige_frame_timeout_s * 1e3 <= self.gige_window_ms:
            raise ValueError(
                f"gige_frame_timeout_s {self.gige_frame_timeout_s} s must exceed the window, "
                f"gige_window_ms {self.gige_window_ms} ms"
            )
        return self


def open_ur(spec: URBackendSpec, rig: Rig) -> Opened:
    """The UR backend's devices: its arms, stage and generator, and its panel (GigE Vision, or
    the panel kind ``spec.detector`` names, seeing the subject through the measured joints)."""
    from scanner.ur import URArm  # ur-rtde's native libraries load only for the UR backend

    stage = SerialStage(spec.stage_port, baudrate=spec.baudrate)
    arms = [
        URArm(
            name,
            host,
            ARM_JOINTS,
            servo_lookahead_s=spec.servo_lookahead_s,
            servo_gain=spec.servo_gain,
        )
        for name, host in (("source_arm", spec.source_host), ("detector_arm", spec.detector_host))
    ]
    clock = _WallClock()
    if spec.detector == "gige":
        from scanner.gige import GigEPanel

        gige = GigEPanel(
            spec.gige_device,
            rig.panel.rows,
            rig.panel.cols,
            rig.panel.pixel_pitch_mm,
            window_ms=spec.gige_window_ms,
            trigger=spec.gige_trigger,
            frame_timeout_s=spec.gige_frame_timeout_s,
        )
        driver = generator_driver(spec, spec.generator_port, rig.on_generator_sent, spec.baudrate)
        return Backend("ur", clock, stage, arms[0], arms[1], driver, gige), None
    groups = (stage, *arms)

    def measured_q() -> np.ndarray:
        return np.concatenate([group.state(1.0).q for group in groups])

    panel = panel_kind(spec.detector)
    config = panel.config.model_validate(spec.simulated_panel)
    driver = generator_driver(spec, spec.generator_port, rig.on_generator_sent, spec.baudrate)
    detector, generator = panel.open(config, rig, measured_q, clock, driver)
    return Backend("ur", clock, stage, arms[0], arms[1], generator, detector), None


def generator_driver(
    spec: Any,
    port: str,
    on_sent: Callable[[str, float], None] | None,
    baudrate: int = DEFAULT_BAUDRATE,
) -> SerialGenerator | SpellmanGenerator:
    """The generator's driver on ``port`` for the protocol ``spec`` names
    (``generator_protocol``: ``line``, ours; ``spellman``, with its full scales)."""
    if spec.generator_protocol == "spellman":
        return SpellmanGenerator(
            port,
            baudrate,
            kv_full_scale=spec.generator_kv_full_scale,
            ma_full_scale=spec.generator_ma_full_scale,
            on_sent=on_sent,
        )
    return SerialGenerator(port, baudrate, on_sent=on_sent)


class _WallClock:
    """Monotonic wall time."""

    def now(self) -> float:
        return time.monotonic()

    def sleep_until(self, t_s: float) -> None:
        delay = t_s - time.monotonic()
        if delay > 0:
            time.sleep(delay)


register_backend("ur", BackendKind(URBackendSpec, open_ur))
