"""Reconstruction during acquisition: the volume a scan builds while it acquires equals the
offline recon stage of its stored views (float rounding), after a fault and a resume too, and
the scan's device events are those of a scan without it (the exposure loop never waits)."""

from __future__ import annotations

import csv
import os
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from configs import CONFIGS
from recon.config import load_protocol
from recon.fdk import fdk_reconstruct
from recon.io import read_projections, read_volume
from recon.rtk_xml import read_rtk_geometry
from scanner.inputs import read_inputs
from scanner.scan import ScanFault
from scanner.session import run_session
from scanner.study_folder import Study
from sim.backend import SimBackendSpec
from study.live_recon import BATCH_VIEWS, WORKER_NICENESS, LiveRecon
from study.stages import recon_geometry, recon_grid, recon_stage, scan_protocol

VOXEL_MM = 2.5
FAULT_VIEW = 37  # inside a batch: the resumed scan completes a batch begun before the fault


def small_protocol():
    """The demo knee protocol with 90 views of 96^2."""
    protocol = load_protocol(CONFIGS / "protocols" / "demo_knee.yaml")
    d = protocol.detector
    panel = d.model_copy(update={"rows": 96, "cols": 96, "pixel_pitch_mm": d.width_mm / 96})
    orbit = protocol.orbit.model_copy(update={"views": 90})
    return protocol.model_copy(update={"detector": panel, "orbit": orbit, "name": "small"})


def inputs(tmp: Path, **faults):
    backend = tmp / f"sim-{'-'.join(faults) or 'plain'}.yaml"
    backend.write_text(yaml.safe_dump({"seed": 5, "faults": faults}))
    return read_inputs(
        small_protocol(),
        CONFIGS / "scanner.yaml",
        "sim",
        backend,
        CONFIGS / "phantoms" / "knee.yaml",
        phantom_voxel_mm=2.0,
    )


def offline(study_path: Path) -> np.ndarray:
    """The recon stage's reconstruction of the stored stack, from the files alone."""
    study = Study.open(study_path)
    stack = read_projections(study_path / "scan" / "projections.mha")
    planned = read_rtk_geometry(study_path / "scan" / "planned_geometry.xml", stack.header)
    recorded = read_rtk_geometry(study_path / "scan" / "geometry.xml", stack.header)
    orbit, per_view = recon_geometry(study, scan_protocol(study), planned)
    assert per_view  # no calibration: the rays come from the recorded views
    grid = recon_grid(scan_protocol(study), VOXEL_MM)
    return fdk_reconstruct(stack.data, recorded, grid, orbit_geometry=orbit).volume.data


def events(study: Path, session: int) -> list[tuple[str, str, str]]:
    with open(study / "scan" / f"device_events-{session}.csv", encoding="utf-8") as fh:
        return [(r["time_s"], r["device"], r["event"]) for r in csv.DictReader(fh)]


@pytest.fixture(scope="module")
def live_scan(tmp_path_factory) -> tuple[Path, Path]:
    """The same scan twice: reconstructed while acquiring (recon stage written from it), and
    plain."""
    tmp = tmp_path_factory.mktemp("live")
    live = LiveRecon(VOXEL_MM)
    study = run_session(tmp / "live", inputs(tmp), sink=live)
    recon_stage(
        study, VOXEL_MM, result=live.finish(), written=live.volume_path, say=lambda _m: None
    )
    run_session(tmp / "plain", inputs(tmp))
    return tmp / "live", tmp / "plain"


def test_volume_during_the_scan_equals_the_offline_recon(live_scan):
    live_path, _ = live_scan
    written = read_volume(live_path / "recon" / "volume.mha", unit="1/mm").data
    reference = offline(live_path)
    assert np.abs(reference).max() > 0.01  # a knee, not an empty box
    assert np.abs(written - reference).max() <= 1e-5 * np.abs(reference).max()
    assert Study.open(live_path).stage("recon")["during_scan"] is True


def test_the_scan_runs_as_without_it(live_scan):
    """Same device events at the same (virtual) times: the recon never held the exposure loop,
    and the stored projections are bit for bit the plain scan's."""
    live_path, plain_path = live_scan
    assert events(live_path, 1) == events(plain_path, 1)
    a = read_projections(live_path / "scan" / "projections.mha").data
    b = read_projections(plain_path / "scan" / "projections.mha").data
    np.testing.assert_array_equal(a, b)


def test_a_resumed_scan_rebuilds_the_volume_from_its_stored_views(tmp_path):
    study_path = tmp_path / "study"
    first = LiveRecon(VOXEL_MM)
    with pytest.raises(ScanFault):
        run_session(study_path, inputs(tmp_path, protective_stop_at_view=FAULT_VIEW), sink=first)
    if sys.platform == "linux":  # the worker yields the cores to the exposure loop
        assert os.getpriority(os.PRIO_PROCESS, first._thread.native_id) == WORKER_NICENESS
    first.close()
    assert first.done == FAULT_VIEW - FAULT_VIEW % BATCH_VIEWS  # whole batches only
    assert first.backlog == FAULT_VIEW % BATCH_VIEWS
    second = LiveRecon(VOXEL_MM)
    study = run_session(
        study_path, None, resume=True, backend_override=SimBackendSpec(seed=5), sink=second
    )
    assert second.received == 90
    volume = second.finish().volume.data  # the views still queued are reconstructed first
    assert second.done == 90
    reference = offline(study_path)
    assert np.abs(volume - reference).max() <= 1e-5 * np.abs(reference).max()
    assert study.stage("scan")["status"] == "complete"
