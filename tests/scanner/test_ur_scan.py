"""The same scan through the UR backend (ur-rtde against two fake UR controllers, the stage and
the generator over serial, the panel simulated or over GigE Vision) as through the simulated
backend."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from configs import CONFIGS
from recon.config import ScanProtocol, load_config
from recon.geometry import DetectorSpec
from recon.io import read_projections, read_stack_header
from recon.rtk_xml import read_rtk_geometry
from scanner.detector_calibration import calibrate_session
from scanner.inputs import read_inputs, subject
from scanner.scan import ScanSettings
from scanner.session import run_session
from scanner.study_folder import Study
from sim.detector import SimDetector
from sim.generator import MockGenerator
from sim.gige_panel import FakePanelAddressError, aravis_missing, fake_panel_with_sensor
from sim.stage import MockStage
from sim.ur_controller import FakeURController
from trajectories.config import ScannerConfig
from trajectories.model import ScannerModel
from trajectories.plan import plan_scan

CALIBRATION_FRAMES = 4
GIGE_ADDRESS = "127.0.0.5"
"""The fake GigE Vision panel's address (other modules use others)."""


def tiny_protocol() -> ScanProtocol:
    """The demo protocol read out 8x8 binned, two 40-degree passes of 16 views in all (10 s of
    real-time motion on the UR backend)."""
    data = yaml.safe_load((CONFIGS / "protocols" / "demo_knee.yaml").read_text(encoding="utf-8"))
    data["detector"] = {"rows": 64, "cols": 64, "pixel_pitch_mm": 9.6}
    data["orbit"].update(views=16, arc_deg=40, z_travel_mm=10)
    return ScanProtocol.model_validate(data)


def scan(tmp: Path, kind: str, config: dict, before_scan=lambda: None) -> Path:
    """Scan on ``kind``'s backend; the UR one's panel first calibrated over its devices
    (``before_scan`` runs between the calibration and the scan)."""
    path = tmp / f"{kind}.yaml"
    if kind == "ur":
        config = config | {"detector_maps": str(tmp / "maps")}
    path.write_text(yaml.safe_dump(config))
    inputs = read_inputs(
        tiny_protocol(),
        CONFIGS / "scanner.yaml",
        kind,
        path,
        CONFIGS / "phantoms" / "knee.yaml",
        phantom_voxel_mm=2.0,
    )
    if kind == "ur":
        calibrate_session(inputs, tmp / "maps", CALIBRATION_FRAMES)
    before_scan()
    run_session(tmp / kind, inputs, settings=ScanSettings(device_timeout_s=2.0))
    return tmp / kind


@pytest.fixture(scope="module")
def simulated(tmp_path_factory) -> Path:
    """The tiny protocol scanned on the simulated backend."""
    return scan(tmp_path_factory.mktemp("sim"), "sim", {})


def like_the_simulated_one(ur: Path, sim: Path) -> None:
    """Both scans complete, the same views within the acquisition tolerance, the same images
    within noise."""
    for study in (ur, sim):
        done = Study.open(study)
        assert done.stage("scan")["status"] == "complete" and done.verify() == []
    g_ur, g_sim = (
        read_rtk_geometry(s / "geometry.xml", read_stack_header(s / "projections.mha"))
        for s in (ur / "scan", sim / "scan")
    )
    apart = np.linalg.norm(g_ur.sources_mm - g_sim.sources_mm, axis=1)
    assert apart.max() < 2 * ScanSettings().pose_tolerance_mm
    p_ur, p_sim = (read_projections(s / "scan" / "projections.mha").data for s in (ur, sim))
    assert np.corrcoef(p_ur.ravel(), p_sim.ravel())[0, 1] > 0.99


# one UR scan in the default suite: every device over its own protocol where Aravis is there,
# else this one (the panel simulated); the other is slow
WITHOUT_GIGE_ELSE_SLOW = pytest.mark.slow if aravis_missing() is None else pytest.mark.usefixtures()


@WITHOUT_GIGE_ELSE_SLOW
def test_ur_backend_scans_like_the_simulated_one(tmp_path, simulated):
    scanner = load_config(CONFIGS / "scanner.yaml", ScannerConfig)
    q0 = plan_scan(ScannerModel(scanner), tiny_protocol()).q[0]
    with (
        MockStage.of_scanner(scanner, q0[:2], servo_lag_s=0.004) as stage,
        MockGenerator(time_scale=0.0, warmup_s=0.05) as generator,
        FakeURController("127.0.0.2", q0[2:8]),
        FakeURController("127.0.0.3", q0[8:14]),
    ):
        ur = scan(
            tmp_path,
            "ur",
            {
                "source_host": "127.0.0.2",
                "detector_host": "127.0.0.3",
                "stage_port": stage.port,
                "generator_port": generator.port,
            },
        )
        assert generator.exposures == CALIBRATION_FRAMES + 16  # the floods, then the views
    like_the_simulated_one(ur, simulated)


@pytest.mark.skipif(aravis_missing() is not None, reason=str(aravis_missing()))
def test_every_device_over_its_own_protocol_scans_like_the_simulated_one(tmp_path, simulated):
    """Arms over RTDE to the fake UR controllers, stage and generator over serial, the panel over
    GigE Vision: a fake GigE Vision camera (sim.gige_panel) whose sensor is the simulated
    panel, lit by the mock generator's pulses, each at its view of the plan (floods with
    nothing in the beam)."""
    scanner = load_config(CONFIGS / "scanner.yaml", ScannerConfig)
    protocol = tiny_protocol()
    plan = plan_scan(ScannerModel(scanner), protocol)
    q0, d = plan.q[0], protocol.detector
    panel = DetectorSpec(rows=d.rows, cols=d.cols, pixel_pitch_mm=d.pixel_pitch_mm)
    knee = subject(
        read_inputs(
            protocol,
            CONFIGS / "scanner.yaml",
            "sim",
            CONFIGS / "backends" / "sim.yaml",
            CONFIGS / "phantoms" / "knee.yaml",
            phantom_voxel_mm=2.0,
        ),
        lambda _m: None,
    )
    scanning = threading.Event()
    views = iter(plan.achieved)
    sensor = SimDetector(
        panel,
        lambda: next(views) if scanning.is_set() else plan.achieved[0],
        lambda view, t_s: knee(view, t_s) if scanning.is_set() else np.zeros((d.rows, d.cols)),
        time.monotonic,
        sdd_mm=protocol.orbit.sdd_mm,
    )
    sensor.connect(0.0)
    sensor.arm(0.0)
    try:
        with (
            MockStage.of_scanner(scanner, q0[:2], servo_lag_s=0.004) as stage,
            MockGenerator(time_scale=0.0, warmup_s=0.05, on_exposure=sensor.exposed) as gen,
            FakeURController("127.0.0.2", q0[2:8]),
            FakeURController("127.0.0.3", q0[8:14]),
            fake_panel_with_sensor(GIGE_ADDRESS, sensor.serial, d.rows, d.cols, sensor.integrate),
        ):
            config = {
                "source_host": "127.0.0.2",
                "detector_host": "127.0.0.3",
                "stage_port": stage.port,
                "generator_port": gen.port,
                "detector": "gige",
                "gige_device": GIGE_ADDRESS,
            }
            ur = scan(tmp_path, "ur", config, before_scan=scanning.set)
            assert gen.exposures == CALIBRATION_FRAMES + 16
    except FakePanelAddressError as error:
        pytest.skip(f"{error} (see .ci/run)")
    like_the_simulated_one(ur, simulated)
