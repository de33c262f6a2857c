"""Scans with the simulated panel served as a GigE Vision camera (sim.gige_panel) and read by the
GigE Vision driver: the same frames as read directly, and a camera that dies mid-scan ends SAFE
within the driver's frame timeout. The camera serves on 127.0.0.4 (other modules use others)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from configs import CONFIGS
from recon.io import read_projections
from scanner.inputs import read_inputs
from scanner.scan import ScanFault, ScanSettings
from scanner.session import run_session
from scanner.study_folder import Study
from sim.backend import SimBackendSpec
from sim.gige_panel import FakePanelAddressError, aravis_missing
from study.simulator import SIM_GIGE_FRAME_TIMEOUT_S
from tests.scanner.test_ur_scan import tiny_protocol

ADDRESS = "127.0.0.4"
SIGNALLED_S = 0.1
"""From the error to X-ray off and every arm stopped (bench/soak.py's bound for a fault the
software is told of)."""

pytestmark = pytest.mark.skipif(aravis_missing() is not None, reason=str(aravis_missing()))


def scan(tmp: Path, name: str, **spec) -> Path:
    """A 16-view scan of 64^2 on the simulated backend configured by ``spec``."""
    config = tmp / f"{name}.yaml"
    config.write_text(yaml.safe_dump({"seed": 3, "event_log": str(tmp / f"{name}.csv"), **spec}))
    inputs = read_inputs(
        tiny_protocol(),
        CONFIGS / "scanner.yaml",
        "sim",
        config,
        CONFIGS / "phantoms" / "knee.yaml",
        phantom_voxel_mm=2.0,
    )
    try:
        run_session(tmp / name, inputs, settings=ScanSettings(device_timeout_s=2.0))
    except FakePanelAddressError as error:
        pytest.skip(f"{error} (see .ci/run)")
    return tmp / name


def wall_events(path: Path) -> list[tuple[float, str, str]]:
    """The device log's (wall time, device, event)."""
    rows = (line.split(",", 4) for line in path.read_text(encoding="utf-8").splitlines())
    return [(float(wall), who, what) for _, _, wall, who, what in rows]


def test_the_panel_over_gige_vision_gives_the_frames_read_directly(tmp_path):
    direct = scan(tmp_path, "direct")
    gige = scan(tmp_path, "gige", panel_gige_interface=ADDRESS)
    for study in (direct, gige):
        assert Study.open(study).verify() == []
    ours, theirs = (read_projections(s / "scan" / "counts.mha").data for s in (gige, direct))
    assert ours.shape == (16, 64, 64)
    np.testing.assert_array_equal(ours, theirs)  # the same raw counts, bit for bit


def test_a_camera_gone_mid_scan_ends_safe_within_the_frame_timeout_then_resumes(tmp_path):
    with pytest.raises(ScanFault) as caught:
        scan(tmp_path, "gone", panel_gige_interface=ADDRESS, faults={"camera_gone_at_view": 5})
    assert "GigE panel" in caught.value.reason
    study = Study.open(tmp_path / "gone")
    assert study.stage("scan")["views_stored"] == 5, caught.value.reason
    assert study.verify() == []

    events = wall_events(tmp_path / "gone.csv")
    gone = next(t for t, who, what in events if what == "camera gone")
    abort = next(t for t, who, what in events if who == "generator" and what == "abort")
    stops: dict[str, float] = {}  # each group's first stop after it
    for t, who, what in events:
        if what == "stop" and t > gone:
            stops.setdefault(who, t)
    assert set(stops) >= {"stage", "source_arm", "detector_arm"}
    assert abort <= min(stops.values())  # X-ray off first
    # the frame asked for when the camera died never comes: found at the frame timeout
    assert max(stops.values()) - gone <= SIM_GIGE_FRAME_TIMEOUT_S + SIGNALLED_S
    pulses = [t for t, who, what in events if who == "generator" and what == "xray_on"]
    assert sum(t > gone for t in pulses) <= 1  # the pulse of the frame being lost, no more

    resumed = SimBackendSpec(seed=3, panel_gige_interface=ADDRESS)
    run_session(tmp_path / "gone", None, resume=True, backend_override=resumed)
    done = Study.open(tmp_path / "gone")
    assert done.stage("scan")["status"] == "complete" and done.verify() == []
