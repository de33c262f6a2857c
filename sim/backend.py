"""The simulated scanner, assembled: world, mock arms and stage, mock generator, rendering panel.

:func:`simulated_scanner` builds every simulated device of one scan session from a
:class:`SimBackendSpec` (``configs/backends/sim.yaml``): the arms start at the plan's first
configuration (or at the spec's ``start_pose``), the generator is served over a pty (the
scanner drives it with its real serial driver; ``generator_protocol: spellman`` serves a mock
Spellman supply instead), and the panel renders the subject through the view the arms truly
realise at each pulse, vibration included. Faults are injected from the spec: a protective
stop, a generator that stops answering, a dropped frame, an interlock that opens, each at a
given view (the number of views acquired before it happens, counted in this
session). ``event_log`` streams the device events to a file as they happen, with wall-clock
times (bench/soak.py times the way to SAFE from it).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from recon.geometry import DetectorSpec, Geometry, View
from recon.project import JosephProjector
from recon.volume import Volume
from sim.arms import GROUPS, MockArm, SimWorld, VirtualClock
from sim.detector import SimDetector, Subject
from sim.generator import MockGenerator
from sim.panel import SimPanelSpec
from sim.spellman import MockSpellman
from sim.sway import SwaySpec
from sim.vibration import VibrationSpec, vibrate_at
from trajectories.arms import ARM_JOINTS
from trajectories.model import ScannerModel
from trajectories.plan import view_at


class SimFaults(BaseModel):
    """Faults to inject, each at a view index (views acquired in this session before it)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    protective_stop_at_view: int | None = Field(None, ge=0)
    generator_timeout_at_view: int | None = Field(None, ge=0)
    dropped_frame_at_view: int | None = Field(None, ge=0)
    interlock_open_at_view: int | None = Field(None, ge=0)
    camera_gone_at_view: int | None = Field(
        None, ge=0, description="the GigE Vision panel's process killed (panel_gige_interface)"
    )


class SimStartPose(BaseModel):
    """Where the simulated scanner stands when a session opens (e.g. where a protective stop or
    the teach pendant left it)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    rotary_deg: float
    lift_mm: float
    source_arm_deg: tuple[float, float, float, float, float, float]
    detector_arm_deg: tuple[float, float, float, float, float, float]

    def q(self) -> np.ndarray:
        """The plan's 14-joint vector (rotary deg, lift mm, source and detector arm deg)."""
        return np.array(
            [self.rotary_deg, self.lift_mm, *self.source_arm_deg, *self.detector_arm_deg]
        )


class SimBackendSpec(BaseModel):
    """The simulated backend's behaviour (configs/backends/sim.yaml)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    lag_s: float = Field(0.004, ge=0.0, le=0.1, description="set-point tracking lag, s")
    tracking_noise_deg: float = Field(
        0.002, ge=0.0, le=0.5, description="true joint scatter about the lagged set-point, deg"
    )
    vibration: VibrationSpec = VibrationSpec(source_mm=0.3, detector_mm=0.3, detector_deg=0.05)
    warmup_s: float = Field(0.05, ge=0.0, le=60.0, description="generator warm-up, s")
    generator_protocol: Literal["line", "spellman"] = Field(
        "line", description="the generator's serial protocol: ours, or Spellman's (MockSpellman)"
    )
    generator_kv_full_scale: float = Field(
        150.0, gt=0.0, description="Spellman: kV at set-point count 4095, kVp"
    )
    generator_ma_full_scale: float = Field(
        100.0, gt=0.0, description="Spellman: mA at set-point count 4095, mA"
    )
    seed: int = 0
    faults: SimFaults = SimFaults()
    start_pose: SimStartPose | None = Field(
        None, description="where the scanner stands at the session's start (None: the plan's start)"
    )
    event_log: str | None = Field(
        None,
        description="file the device events are appended to as they happen (sim.arms.SimWorld)",
    )
    panel: SimPanelSpec = SimPanelSpec()
    panel_gige_interface: str | None = Field(
        None,
        description="serve the simulated panel as a GigE Vision camera on this address (an "
        "interface's own, e.g. 127.0.0.4) and read it with the GigE Vision driver; None: read "
        "it directly",
    )
    detector_maps: str | None = Field(
        None,
        description="folder of the panel's maps (cbct detector-calibrate); None: the simulated "
        "panel is calibrated at the start of each session",
    )
    max_map_age_days: float = Field(7.0, gt=0.0, description="oldest detector maps a scan uses")
    sway: SwaySpec = Field(
        SwaySpec(), description="the knee phantom's patient sways during its scans (sim.sway)"
    )

    @model_validator(mode="after")
    def _camera_gone_needs_the_camera(self) -> SimBackendSpec:
        if self.faults.camera_gone_at_view is not None and self.panel_gige_interface is None:
            raise ValueError(
                "faults.camera_gone_at_view needs panel_gige_interface (the panel served over "
                "GigE Vision)"
            )
        return self


def vibrated_view(
    model: ScannerModel, q: np.ndarray, panel: DetectorSpec, vibration: VibrationSpec
) -> View:
    """The view the joints ``q`` (the plan's units) realise on arms that vibrate as
    ``vibration`` says, at their rotary angle ``q[0]`` (deg)."""
    return vibrate_at(view_at(model, q, panel), vibration, rotary_deg=float(q[0]))


def volume_subject(volume: Volume) -> Subject:
    """Line integrals of a still attenuation volume (1/mm) through one view (recon
    projector), at any time."""

    projector = JosephProjector(volume.data, volume.grid)  # padded once for every view

    def render(view: View, t_s: float = 0.0) -> np.ndarray:
        return projector.project(Geometry([view]))[0]

    return render


@dataclass
class SimulatedScanner:
    """Every simulated device of one session; ``world`` holds the truth and the event log."""

    world: SimWorld
    clock: VirtualClock
    stage: MockArm
    source_arm: MockArm
    detector_arm: MockArm
    generator: MockGenerator | MockSpellman
    detector: SimDetector

    def close(self) -> None:
        self.generator.close()


def simulated_scanner(
    model: ScannerModel,
    start_q: np.ndarray,
    panel: DetectorSpec,
    sdd_mm: float,
    subject: Subject,
    spec: SimBackendSpec,
) -> SimulatedScanner:
    """Build the simulated devices, standing at ``start_q`` unless ``spec.start_pose`` says
    otherwise; the generator's pty is served from now until close()."""
    if spec.start_pose is not None:
        start_q = spec.start_pose.q()
    world = SimWorld(
        model,
        start_q,
        lag_s=spec.lag_s,
        tracking_noise=spec.tracking_noise_deg,
        seed=spec.seed,
        event_log=None if spec.event_log is None else Path(spec.event_log),
    )
    faults = spec.faults
    arms = {
        group: MockArm(
            world,
            group,
            ("rotary", "lift") if group == "stage" else ARM_JOINTS,
            protective_stop_after=faults.protective_stop_at_view if group == "source_arm" else None,
        )
        for group in GROUPS
    }

    def true_view() -> View:
        with world.lock:
            q = world.q_true.copy()
        return vibrated_view(model, q, panel, spec.vibration)

    detector = SimDetector(
        panel,
        true_view,
        subject,
        lambda: world.t,
        sdd_mm=sdd_mm,
        seed=spec.seed,
        sensor=spec.panel,
        drop_frame_at=faults.dropped_frame_at_view,
        log=world.log,
    )

    def exposed(kv: float, ma: float, ms: float, seq: int) -> None:
        with world.lock:
            world.exposures += 1
        detector.exposed(kv, ma, ms, seq)

    def one_based(view: int | None) -> int | None:
        return None if view is None else view + 1

    generator_faults = {
        "timeout_at_exposure": one_based(faults.generator_timeout_at_view),
        "interlock_open_at_exposure": one_based(faults.interlock_open_at_view),
        "on_event": lambda name, info: world.log("generator", name),
        "on_exposure": exposed,
    }
    if spec.generator_protocol == "spellman":  # no warm-up; the host times the pulses
        generator: MockGenerator | MockSpellman = MockSpellman(
            kv_full_scale=spec.generator_kv_full_scale,
            ma_full_scale=spec.generator_ma_full_scale,
            **generator_faults,
        )
    else:
        generator = MockGenerator(warmup_s=spec.warmup_s, time_scale=0.0, **generator_faults)
    generator.start()
    return SimulatedScanner(
        world,
        VirtualClock(world),
        arms["stage"],
        arms["source_arm"],
        arms["detector_arm"],
        generator,
        detector,
    )
