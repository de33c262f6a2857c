"""The simulated scanner as a backend: sim/'s mock devices with scanner/'s drivers, registered.

The ``sim`` backend, the ``sim`` panel and the phantoms, registered in :mod:`scanner.registry`
when this module is imported (the ``dualarm_cbct.backends`` entry point names it). It lives on
the floor that sees both: sim/ knows no scanner, and the scanner knows no simulator.

The ``sim`` backend drives the mock generator through the scanner's real serial driver over a
pty, and reads its panel directly or, with ``panel_gige_interface``, served as a GigE Vision
camera through the GigE Vision driver. The ``sim`` panel stands in for the UR backend's: it
renders the subject through the view the arms' measured joints realise, and senses the pulses
the generator delivers. The phantoms (``knee``, ``bb``, ``tka``) are what a simulated panel
images.
"""

from __future__ import annotations

import itertools
import shutil
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calibration.phantom import BBPhantomSpec
from recon.geometry import DetectorSpec, Geometry, View
from recon.volume import Volume
from scanner.backends import generator_driver
from scanner.corrections import PanelMaps
from scanner.detector_calibration import calibrate_detector
from scanner.generator import SerialGenerator
from scanner.hardware import Backend, Clock, Detector, Technique, close_quietly
from scanner.inputs import SessionInputs
from scanner.registry import (
    BackendKind,
    Opened,
    PanelKind,
    PhantomKind,
    Rig,
    Subject,
    nothing_in_the_beam,
    register_backend,
    register_panel,
    register_phantom,
)
from scanner.spellman import SpellmanGenerator
from sim.backend import (
    SimBackendSpec,
    SimFaults,
    SimulatedScanner,
    simulated_scanner,
    vibrated_view,
    volume_subject,
)
from sim.detector import FrameTimeout, SimDetector
from sim.phantoms.bb import project_bb
from sim.phantoms.knee import KneePhantomSpec, knee_grid, rasterize_knee
from sim.phantoms.tka import TkaPhantomSpec
from sim.sway import Sway, SwayingKnee, SwayingSubject, SwayPivots, SwaySpec

SIM_GIGE_WINDOW_MS = 100.0
"""The simulated panel's integration window over GigE Vision, ms: the pulse comes well within
it (the mock generator fires as soon as EXP arrives)."""
SIM_GIGE_FRAME_TIMEOUT_S = 0.3
"""Longest wait for a frame of the simulated panel over GigE Vision, s (a dead panel's bound)."""
SIM_GIGE_WARMUP_FRAMES = 1
"""Frames the driver reads and discards when it connects to the simulated panel: the first
frame after the stream starts comes late, which the frame timeout would take for a dead panel
(a CI run lost a scan's view 0 so). They are blank and leave the sensor's noise untouched."""
SIM_CALIBRATION_FRAMES = 8
"""Darks and floods of the simulated panel's calibration at the start of a session."""
LEG_HEIGHT_MM = 480.0
"""Length of leg the simulated panel images, mm, centred on the joint line: more than the cone
covers at the knee (a leg cut off inside the cone would end in the reconstruction, and in the
registration's soft tissue, where a patient's does not)."""


@dataclass(frozen=True)
class SimTruth:
    """What the simulated scanner knows of the last view its panel read
    (:class:`scanner.registry.Truth`); ``simulated`` holds every simulated device."""

    simulated: SimulatedScanner
    subject: Subject

    def view_matrix(self) -> np.ndarray:
        return self.simulated.detector.true_views[-1].matrix

    def body_poses(self) -> dict[str, np.ndarray] | None:
        if not isinstance(self.subject, SwayingSubject):
            return None
        return self.subject.poses_at(self.simulated.detector.true_times_s[-1])

    def events(self) -> list[tuple[int, float, str, str]]:
        return self.simulated.world.events


def open_sim(spec: SimBackendSpec, rig: Rig) -> Opened:
    """The simulated scanner's devices for ``rig`` (the generator driven through its serial
    driver over the pty; the panel read directly or over GigE Vision), and its truth."""
    simulated = simulated_scanner(rig.model, rig.start_q, rig.panel, rig.sdd_mm, rig.subject, spec)
    closing: list[Callable[[], None]] = [simulated.close]
    detector: Detector = simulated.detector
    if spec.panel_gige_interface is not None:
        try:
            detector, stop_panel = _panel_over_gige(spec, simulated, rig.panel)
        except BaseException:
            simulated.close()
            raise
        closing.insert(0, stop_panel)
    driver = generator_driver(spec, simulated.generator.port, rig.on_generator_sent)
    backend = Backend(
        name="sim",
        clock=simulated.clock,
        stage=simulated.stage,
        source_arm=simulated.source_arm,
        detector_arm=simulated.detector_arm,
        generator=_ClosingGenerator(driver, closing),
        detector=detector,
    )
    return backend, SimTruth(simulated, rig.subject)


def calibrate_sim_panel(spec: SimBackendSpec, rig: Rig, technique: Technique) -> PanelMaps:
    """The simulated panel's maps, made now: :func:`calibrate_detector` on a fault-free twin of
    the session's devices, nothing in the beam, its panel read directly (the session's own
    already serves it over GigE Vision when asked to)."""
    quiet = {"faults": SimFaults(), "event_log": None, "start_pose": None}
    twin = spec.model_copy(update=quiet | {"panel_gige_interface": None})
    clear = Rig(rig.model, rig.start_q, rig.panel, rig.sdd_mm, nothing_in_the_beam(rig.panel))
    devices, _ = open_sim(twin, clear)
    try:
        return calibrate_detector(devices, technique, SIM_CALIBRATION_FRAMES)
    finally:
        close_quietly(devices)


def resumed_sim(spec: SimBackendSpec) -> tuple[SimBackendSpec, str | None]:
    """A resumed session's config: the study's, its injected faults not injected again."""
    if spec.faults == SimFaults():
        return spec, None
    injected = ", ".join(f"{k}={v}" for k, v in spec.faults.model_dump(exclude_none=True).items())
    note = (
        f"the simulated faults of the study's backend config ({injected}) are not injected "
        "again; give --backend-config to inject faults in this session"
    )
    return spec.model_copy(update={"faults": SimFaults()}), note


def open_sim_panel(
    spec: SimBackendSpec,
    rig: Rig,
    measured_q: Callable[[], np.ndarray],
    clock: Clock,
    driver: SerialGenerator | SpellmanGenerator,
) -> tuple[Detector, _PanelSensing]:
    """The simulated panel in place of a hardware one: it renders the rig's subject through the
    view the measured joints realise (with ``spec.vibration``), and senses the pulses
    ``driver`` delivers."""

    def measured_view() -> View:
        return vibrated_view(rig.model, measured_q(), rig.panel, spec.vibration)

    detector = SimDetector(
        rig.panel,
        measured_view,
        rig.subject,
        clock.now,
        sdd_mm=rig.sdd_mm,
        seed=spec.seed,
        sensor=spec.panel,
    )
    return detector, _PanelSensing(driver, detector)


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
    spec: SimBackendSpec, simulated: SimulatedScanner, panel: DetectorSpec
) -> tuple[Detector, Callable[[], None]]:
    """The simulated panel served as a GigE Vision camera at ``spec.panel_gige_interface``
    (:mod:`sim.gige_panel`, its sensor the simulated panel's :meth:`SimDetector.integrate`),
    and the GigE Vision driver that reads it; with what stops the camera. The camera-gone
    fault kills the camera's process when the frame of view ``camera_gone_at_view`` is asked
    for; a dropped frame (``dropped_frame_at_view``) comes after the driver's frame timeout.
    The driver's warm-up frames (:data:`SIM_GIGE_WARMUP_FRAMES`) are blank: the views' frames
    are the sensor's, the same as read directly."""
    from scanner.gige import GigEPanel  # Aravis loads only for a panel served over GigE Vision
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


def knee_subject(inputs: SessionInputs, say: Callable[[str], None], scan_s: float) -> Subject:
    """The knee phantom rasterised and projected; its patient swaying as the ``sim`` backend's
    ``sway`` says over a scan of ``scan_s`` seconds (still on any other backend)."""
    phantom = inputs.phantom
    grid = knee_grid(
        phantom,
        spacing_mm=inputs.phantom_voxel_mm,
        height_mm=LEG_HEIGHT_MM,
        below_mm=0.5 * LEG_HEIGHT_MM,
    )
    say(f"rasterising the knee phantom ({grid.size_xyz} voxels of {inputs.phantom_voxel_mm} mm)")
    labels, mu = rasterize_knee(phantom, grid)
    sway = _sway(inputs)
    if sway is None:
        return volume_subject(Volume(mu, grid, "1/mm"))
    say(f"the patient sways by up to {sway.peak_mm:g} mm at the knee during the scan")
    return SwayingKnee(
        Volume(mu, grid, "1/mm"),
        Volume(labels, grid, "label"),
        phantom,
        Sway(sway, SwayPivots.of_knee(phantom), scan_s),
    )


def bb_subject(inputs: SessionInputs, say: Callable[[str], None], scan_s: float) -> Subject:
    """The steel balls, projected exactly."""
    return lambda view, _t_s=0.0: project_bb(inputs.phantom, Geometry([view]))[0]


def tka_subject(inputs: SessionInputs, say: Callable[[str], None], scan_s: float) -> Subject:
    """The knee replacement's meshes, projected polychromatically at the protocol's tube
    voltage; its patient swaying as the ``sim`` backend's ``sway`` says over a scan of
    ``scan_s`` seconds (still on any other backend)."""
    from sim import tka_ct  # its meshes and spectrum: only here

    say(f"loading the knee replacement from {inputs.phantom.data}")
    scene = tka_ct.tka_scene(inputs.phantom)
    spec, sway = _sway(inputs), None
    if spec is not None:
        say(f"the patient sways by up to {spec.peak_mm:g} mm at the knee during the scan")
        sway = Sway(spec, tka_ct.tka_pivots(scene), scan_s)
    return tka_ct.tka_subject(scene, inputs.protocol.exposure.tube_kv, sway)


def _sway(inputs: SessionInputs) -> SwaySpec | None:
    """The ``sim`` backend's sway of the patient, None when still or on another backend."""
    sway = inputs.backend.sway if isinstance(inputs.backend, SimBackendSpec) else None
    return sway if sway is not None and sway.peak_mm > 0 else None


register_backend(
    "sim",
    BackendKind(SimBackendSpec, open_sim, calibrate_panel=calibrate_sim_panel, resumed=resumed_sim),
)
register_panel("sim", PanelKind(SimBackendSpec, open_sim_panel))
register_phantom("knee", PhantomKind(KneePhantomSpec, knee_subject))
register_phantom("bb", PhantomKind(BBPhantomSpec, bb_subject))
register_phantom("tka", PhantomKind(TkaPhantomSpec, tka_subject))
