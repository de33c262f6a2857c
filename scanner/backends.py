"""Backends from config: ``sim`` (the simulated scanner) and ``ur`` (UR arms over ur-rtde, the
lift/rotary stage and the X-ray generator over serial).

Both run the same state machine, storage and checks; only the devices differ. The ``sim``
backend drives the mock generator through the real serial driver over a pty, and reads its
panel directly or, with ``panel_gige_interface``, served as a GigE Vision camera through the
GigE Vision driver. The ``ur`` backend reads a GigE Vision panel (``detector: gige``,
:class:`scanner.gige.GigEPanel`), or the simulated panel rendering the subject through the
view the arms' MEASURED joints realise (``detector: sim``), which lets the same scan run
against the fake UR controllers without a panel.
"""

from __future__ import annotations

import itertools
import shutil
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from recon.config import load_config
from recon.geometry import DetectorSpec, View
from scanner.generator import SerialGenerator
from scanner.hardware import Backend, Detector
from scanner.serial_link import DEFAULT_BAUDRATE
from scanner.spellman import SpellmanGenerator
from scanner.stage import SerialStage
from sim.backend import ARM_JOINTS, SimBackendSpec, simulated_scanner
from sim.detector import FrameTimeout, SimDetector
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
    detector: Literal["sim", "gige"] = Field(
        "sim", description="gige: the GigE Vision panel; sim: the simulated panel"
    )
    gige_device: str | None = Field(None, description="the panel's Aravis device id or IPv4")
    gige_trigger: Literal["software", "line0"] = Field(
        "software", description="software: the driver triggers each window; line0: the generator"
    )
    gige_window_ms: float = Field(100.0, gt=0.0, le=5000.0, description="integration window")
    gige_frame_timeout_s: float = Field(
        0.5, gt=0.0, le=10.0, description="longest wait for a frame (a dead panel's bound)"
    )
    simulated_panel: SimBackendSpec = SimBackendSpec()
    detector_maps: str | None = Field(
        None, description="folder of the panel's maps (cbct detector-calibrate)"
    )
    max_map_age_days: float = Field(7.0, gt=0.0, description="oldest detector maps a scan uses")

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


BACKEND_SPECS = {"sim": SimBackendSpec, "ur": URBackendSpec}
SIM_GIGE_WINDOW_MS = 100.0
"""The simulated panel's integration window over GigE Vision, ms: the pulse comes well within
it (the mock generator fires as soon as EXP arrives)."""
SIM_GIGE_FRAME_TIMEOUT_S = 0.3
"""Longest wait for a frame of the simulated panel over GigE Vision, s (a dead panel's bound)."""
SIM_GIGE_WARMUP_FRAMES = 1
"""Frames the driver reads and discards when it connects to the simulated panel: the first
frame after the stream starts comes late, which the frame timeout would take for a dead panel
(a CI run lost a scan's view 0 so). They are blank and leave the sensor's noise untouched."""


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
    subject: Callable[[View, float], np.ndarray],
    on_generator_sent: Callable[[str, float], None] | None = None,
) -> tuple[Backend, object | None]:
    """The devices of ``spec`` (not yet connected), and the simulated scanner when there is
    one (its ``world`` holds the truth and the ordered event log). ``on_generator_sent``
    hears every command sent to the generator with its ``time.monotonic()``."""
    if isinstance(spec, SimBackendSpec):
        simulated = simulated_scanner(model, start_q, panel, sdd_mm, subject, spec)
        closing: list[Callable[[], None]] = [simulated.close]
        detector = simulated.detector
        if spec.panel_gige_interface is not None:
            try:
                detector, stop_panel = _panel_over_gige(spec, simulated, panel)
            except BaseException:
                simulated.close()
                raise
            closing.insert(0, stop_panel)
        backend = Backend(
            name="sim",
            clock=simulated.clock,
            stage=simulated.stage,
            source_arm=simulated.source_arm,
            detector_arm=simulated.detector_arm,
            generator=_ClosingGenerator(
                _generator_driver(spec, simulated.generator.port, on_generator_sent), closing
            ),
            detector=detector,
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
    if spec.detector == "gige":
        from scanner.gige import GigEPanel

        gige = GigEPanel(
            spec.gige_device,
            panel.rows,
            panel.cols,
            panel.pixel_pitch_mm,
            window_ms=spec.gige_window_ms,
            trigger=spec.gige_trigger,
            frame_timeout_s=spec.gige_frame_timeout_s,
        )
        driver = _generator_driver(spec, spec.generator_port, on_generator_sent, spec.baudrate)
        return Backend("ur", clock, stage, arms[0], arms[1], driver, gige), None
    detector = SimDetector(
        panel,
        measured_view,
        subject,
        clock.now,
        sdd_mm=sdd_mm,
        seed=spec.simulated_panel.seed,
        sensor=spec.simulated_panel.panel,
    )
    driver = _generator_driver(spec, spec.generator_port, on_generator_sent, spec.baudrate)
    generator = _PanelSensing(driver, detector)
    return Backend("ur", clock, stage, arms[0], arms[1], generator, detector), None


def _generator_driver(
    spec: SimBackendSpec | URBackendSpec,
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


class _PanelSensing:
    """A generator whose delivered pulses the simulated panel senses (its exposure detection)."""

    def __init__(self, driver: SerialGenerator | SpellmanGenerator, panel: SimDetector) -> None:
        self._driver, self._panel = driver, panel

    def __getattr__(self, name: str):
        return getattr(self._driver, name)

    def expose(self, timeout_s: float, permit: Callable[[], None] | None = None):
        exposure = self._driver.expose(timeout_s, permit)
        t = exposure.technique
        self._panel.exposed(t.kv, t.ma, t.ms, exposure.sequence)
        return exposure


class _ClosingGenerator:
    """The serial generator driver, also closing the simulated devices behind its pty (and the
    simulated panel's GigE Vision camera, when it is served)."""

    def __init__(
        self, driver: SerialGenerator | SpellmanGenerator, closing: list[Callable[[], None]]
    ) -> None:
        self._driver, self._closing = driver, closing

    def __getattr__(self, name: str):
        return getattr(self._driver, name)

    def close(self) -> None:
        try:
            self._driver.close()
        finally:
            for close in self._closing:
                close()


def _panel_over_gige(
    spec: SimBackendSpec, simulated, panel: DetectorSpec
) -> tuple[Detector, Callable[[], None]]:
    """The simulated panel served as a GigE Vision camera at ``spec.panel_gige_interface``
    (:mod:`sim.gige_panel`, its sensor the simulated panel's :meth:`SimDetector.integrate`),
    and the GigE Vision driver that reads it; with what stops the camera. The camera-gone
    fault kills the camera's process when the frame of view ``camera_gone_at_view`` is asked
    for; a dropped frame (``dropped_frame_at_view``) comes after the driver's frame timeout.
    The driver's warm-up frames (:data:`SIM_GIGE_WARMUP_FRAMES`) are blank: the views' frames
    are the sensor's, the same as read directly."""
    from scanner.gige import GigEPanel
    from sim.gige_panel import serve_sensor, start_fake_panel

    sensor = simulated.detector
    sensor.connect(0.0)
    sensor.arm(0.0)
    gone_at = spec.faults.camera_gone_at_view
    camera = None
    frames = itertools.count(-SIM_GIGE_WARMUP_FRAMES)  # this session's: one per view

    def integrate(window_s: float) -> np.ndarray:
        frame = next(frames)
        if frame < 0:
            return np.zeros((panel.rows, panel.cols), dtype=np.uint16)
        if frame == gone_at and camera is not None:
            simulated.world.log("detector", "camera gone")
            camera.kill()
        try:
            return sensor.integrate(window_s)
        except FrameTimeout:  # the dropped-frame fault: the frame comes after the host gave up
            time.sleep(SIM_GIGE_FRAME_TIMEOUT_S + SIM_GIGE_WINDOW_MS * 1e-3)
            raise

    folder = Path(tempfile.mkdtemp(prefix="cbct-panel-"))
    server = serve_sensor(integrate, folder / "sensor.sock")
    try:
        camera = start_fake_panel(
            spec.panel_gige_interface, sensor.serial, panel.rows, panel.cols, server.path
        )
    except BaseException:
        server.close()
        shutil.rmtree(folder, ignore_errors=True)
        raise
    driver = GigEPanel(
        spec.panel_gige_interface,
        panel.rows,
        panel.cols,
        panel.pixel_pitch_mm,
        window_ms=SIM_GIGE_WINDOW_MS,
        frame_timeout_s=SIM_GIGE_FRAME_TIMEOUT_S,
        warmup_frames=SIM_GIGE_WARMUP_FRAMES,
    )

    def stop() -> None:
        try:
            driver.close()
        finally:
            camera.stop()
            server.close()
            shutil.rmtree(folder, ignore_errors=True)

    return driver, stop
