"""Moving the scanner to the plan's start through the UR backend (ur-rtde against two fake UR
controllers, the stage and the generator over serial), from a random rest pose: the move ends
within the start tolerance and the scan's preflight then accepts."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from configs import CONFIGS
from recon.config import load_config
from scanner.inputs import read_inputs
from scanner.scan import OperatorDeclined, ScanSettings
from scanner.session import run_session
from scanner.study_folder import Study
from sim.generator import MockGenerator
from sim.stage import MockStage
from sim.ur_controller import FakeURController
from tests.scanner.test_move_scanner import tiny_protocol
from tests.trajectories.conftest import random_rest_pose
from trajectories.config import ScannerConfig
from trajectories.model import ScannerModel

pytest.importorskip("rtde_control")
pytestmark = pytest.mark.timeout(120)


def test_ur_backend_moves_from_a_random_pose_to_the_start(tmp_path, panel_maps):
    scanner = load_config(CONFIGS / "scanner.yaml", ScannerConfig)
    model = ScannerModel(scanner)
    # small offsets: this move runs on the wall clock
    pose = random_rest_pose(
        model, np.random.default_rng(5), rotary_deg=20.0, lift_mm=60.0, arm_deg=10.0
    )
    asked = []

    def confirm(question: str) -> bool:  # yes to the move, no at the scan's first question
        asked.append(question)
        return question.startswith("Move the scanner")

    with (
        MockStage.of_scanner(scanner, pose[:2], servo_lag_s=0.004) as stage,
        MockGenerator(time_scale=0.0, warmup_s=0.05) as generator,
        FakeURController("127.0.0.2", pose[2:8]),
        FakeURController("127.0.0.3", pose[8:14]),
    ):
        config = tmp_path / "ur.yaml"
        config.write_text(
            yaml.safe_dump(
                {
                    "source_host": "127.0.0.2",
                    "detector_host": "127.0.0.3",
                    "stage_port": stage.port,
                    "generator_port": generator.port,
                    "detector_maps": str(panel_maps(tiny_protocol())),
                }
            )
        )
        inputs = read_inputs(
            tiny_protocol(),
            CONFIGS / "scanner.yaml",
            "ur",
            config,
            CONFIGS / "phantoms" / "knee.yaml",
            phantom_voxel_mm=2.0,
        )
        with pytest.raises(OperatorDeclined, match="declined motion"):
            run_session(
                tmp_path / "ur",
                inputs,
                move_to_start=True,
                confirm=confirm,
                settings=ScanSettings(device_timeout_s=2.0),
            )
        assert generator.exposures == 0
    # the scan asks "Start motion?" only once every preflight check, the start pose's
    # included, has passed
    assert [q.split("?")[0] for q in asked] == [
        "Move the scanner to the plan's start",
        "Start motion",
    ]
    (move,) = Study.open(tmp_path / "ur").manifest["moves"]
    assert move["status"] == "done" and move["error"] <= ScanSettings().start_tolerance
    assert np.abs(np.subtract(move["to"], move["from"])).max() > 10.0  # deg / mm: a real move
    np.testing.assert_allclose(move["from"], pose, atol=0.01)
