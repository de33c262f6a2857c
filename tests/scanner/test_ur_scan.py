"""The same scan through the UR backend (ur-rtde against two fake UR controllers, the stage and
the generator over serial) as through the simulated backend."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from recon.config import ScanProtocol, load_config
from recon.io import read_projections, read_stack_header
from recon.rtk_xml import read_rtk_geometry
from scanner.cli import CONFIGS
from scanner.detector_calibration import calibrate_session
from scanner.scan import ScanSettings
from scanner.session import read_inputs, run_session
from scanner.study import Study
from sim.generator import MockGenerator
from sim.stage import MockStage
from sim.ur_controller import FakeURController
from trajectories.config import ScannerConfig
from trajectories.model import ScannerModel
from trajectories.plan import plan_scan

CALIBRATION_FRAMES = 4


def tiny_protocol() -> ScanProtocol:
    """The demo protocol read out 8x8 binned, two 40-degree passes of 16 views in all (10 s of
    real-time motion on the UR backend)."""
    data = yaml.safe_load((CONFIGS / "protocols" / "demo_knee.yaml").read_text(encoding="utf-8"))
    data["detector"] = {"rows": 64, "cols": 64, "pixel_pitch_mm": 9.6}
    data["orbit"].update(views=16, arc_deg=40, z_travel_mm=10)
    return ScanProtocol.model_validate(data)


def scan(tmp: Path, kind: str, config: dict) -> Path:
    """Scan on ``kind``'s backend; the UR one's panel first calibrated over its devices."""
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
    run_session(tmp / kind, inputs, settings=ScanSettings(device_timeout_s=2.0))
    return tmp / kind


def test_ur_backend_scans_like_the_simulated_one(tmp_path):
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
    sim = scan(tmp_path, "sim", {})
    for study in (ur, sim):
        done = Study.open(study)
        assert done.stage("scan")["status"] == "complete" and done.verify() == []

    # the same views (within the acquisition tolerance) and the same images (within noise)
    g_ur, g_sim = (
        read_rtk_geometry(s / "geometry.xml", read_stack_header(s / "projections.mha"))
        for s in (ur / "scan", sim / "scan")
    )
    apart = np.linalg.norm(g_ur.sources_mm - g_sim.sources_mm, axis=1)
    assert apart.max() < 2 * ScanSettings().pose_tolerance_mm
    p_ur, p_sim = (read_projections(s / "scan" / "projections.mha").data for s in (ur, sim))
    assert np.corrcoef(p_ur.ravel(), p_sim.ravel())[0, 1] > 0.99
