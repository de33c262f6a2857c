"""Backends from config: ``sim`` (the simulated scanner) and ``ur`` (UR arms over ur-rtde, the
lift/rotary stage and the X-ray generator over serial).

Both run the same state machine, storage and checks; only the devices differ. The ``sim``
backend drives the mock generator through the real serial driver over a pty. The ``ur`` backend
has no flat-panel driver yet: its frames come from the simulated panel rendering the subject
through the view the arms' MEASURED joints realise (``detector: sim``), which is what lets the
same scan run against the fake UR controllers in tests.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from recon.config import load_config
from recon.geometry import DetectorSpec, View
from scanner.generator import SerialGenerator
from scanner.hardware import Backend
from scanner.stage import SerialStage
from sim.backend import ARM_JOINTS, SimBackendSpec, simulated_scanner
from sim.detector import SimDetector
from sim.vibration import vibrate_at
from trajectories.model import ScannerModel
from trajectories.plan import view_at


class URBackendSpec(BaseModel):
    """The UR backend's connections (configs/backends/ur.yaml)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    source_host: str = Field(description="IP of the source arm's UR controller")
    detector_host: str = Field(description="IP of the detector arm's UR controller")
    stage_port: str = Field(description="serial port of the lift/rotary controller")
    generator_port: str = Field(description="serial port of the X-ray generator")
    baudrate: int = Field(115200, gt=0)
    servo_lookahead_s: float = Field(0.1, ge=0.03, le=0.2)
    servo_gain: float = Field(300.0, ge=100.0, le=2000.0)
    detector: Literal["sim"] = "sim"
    simulated_panel: SimBackendSpec = SimBackendSpec()
    detector_maps: str | None = Field(
        None, description="folder of the panel's maps (cbct detector-calibrate)"
    )
    max_map_age_days: float = Field(7.0, gt=0.0, description="oldest detector maps a scan uses")


BACKEND_SPECS = {"sim": SimBackendSpec, "ur": URBackendSpec}


def load_backend_spec(kind: str, path: str | Path) -> SimBackendSpec | URBackendSpec:
    """Read a backend config; raises naming the file and field on any problem."""
    if kind not in BACKEND_SPECS:
        raise ValueError(f"backend must be one of {sorted(BACKEND_SPECS)}, got {kind!r}")
    return load_config(path, BACKEND_SPECS[kind])


def open_backend(
    spec: SimBackendSpec | URBackendSpec,
    model: ScannerModel,
    start_q: np.ndarray,
    panel: DetectorSpec,
    sdd_mm: float,
    subject: Callable[[View], np.ndarray],
    on_generator_sent: Callable[[str, float], None] | None = None,
) -> tuple[Backend, object | None]:
    """The devices of ``spec`` (not yet connected), and the simulated scanner when there is
    one (its ``world`` holds the truth and the ordered event log). ``on_generator_sent``
    hears every command sent to the generator with its ``time.monotonic()``."""
    if isinstance(spec, SimBackendSpec):
        simulated = simulated_scanner(model, start_q, panel, sdd_mm, subject, spec)
        backend = Backend(
            name="sim",
            clock=simulated.clock,
            stage=simulated.stage,
            source_arm=simulated.source_arm,
            detector_arm=simulated.detector_arm,
            generator=_ClosingGenerator(
                SerialGenerator(simulated.generator.port, on_sent=on_generator_sent), simulated
            ),
            detector=simulated.detector,
        )
        return backend, simulated
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
    groups = (stage, *arms)
    vibration = spec.simulated_panel.vibration

    def measured_view() -> View:
        q = np.concatenate([group.state(1.0).q for group in groups])
        return vibrate_at(view_at(model, q, panel), vibration, rotary_deg=float(q[0]))

    clock = _WallClock()
    detector = SimDetector(
        panel,
        measured_view,
        subject,
        clock.now,
        sdd_mm=sdd_mm,
        seed=spec.simulated_panel.seed,
        sensor=spec.simulated_panel.panel,
    )
    driver = SerialGenerator(spec.generator_port, baudrate=spec.baudrate, on_sent=on_generator_sent)
    generator = _PanelSensing(driver, detector)
    return Backend("ur", clock, stage, arms[0], arms[1], generator, detector), None


class _WallClock:
    """Monotonic wall time."""

    def now(self) -> float:
        return time.monotonic()

    def sleep_until(self, t_s: float) -> None:
        delay = t_s - time.monotonic()
        if delay > 0:
            time.sleep(delay)


class _PanelSensing:
    """A generator whose delivered pulses the simulated panel senses (its exposure detection)."""

    def __init__(self, driver: SerialGenerator, panel: SimDetector) -> None:
        self._driver, self._panel = driver, panel

    def __getattr__(self, name: str):
        return getattr(self._driver, name)

    def expose(self, timeout_s: float, permit: Callable[[], None] | None = None):
        exposure = self._driver.expose(timeout_s, permit)
        t = exposure.technique
        self._panel.exposed(t.kv, t.ma, t.ms, exposure.sequence)
        return exposure


class _ClosingGenerator:
    """The serial generator driver, also closing the simulated devices behind its pty."""

    def __init__(self, driver: SerialGenerator, simulated) -> None:
        self._driver, self._simulated = driver, simulated

    def __getattr__(self, name: str):
        return getattr(self._driver, name)

    def close(self) -> None:
        try:
            self._driver.close()
        finally:
            self._simulated.close()
