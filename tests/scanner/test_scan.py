"""The scan state machine on the simulated backend: a small knee scan end to end, every injected
fault ending in SAFE with nothing lost, resume reproducing the uninterrupted scan, refusals."""

from __future__ import annotations

import csv
import json
import os
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
import rerun as rr
import yaml

from configs import CONFIGS
from recon.config import load_config, load_protocol
from recon.fdk import fdk_reconstruct
from recon.io import read_projections, read_stack_header
from recon.rtk_xml import read_rtk_geometry
from recon.volume import VolumeGrid
from scanner.inputs import read_inputs
from scanner.scan import OperatorDeclined, ScanFault, ScanSettings
from scanner.session import run_session
from scanner.study_folder import Study, StudyError
from sim.backend import SimBackendSpec
from sim.panel import SimPanelSpec
from sim.phantoms.knee import KneePhantomSpec, rasterize_knee
from sim.scan import photons_per_pixel, simulate_knee_scan

VIEWS = 60
FAULT_VIEW = 20
PHANTOM_VOXEL_MM = 2.0


def small_protocol():
    """The demo knee protocol with :data:`VIEWS` views of 128^2 (the panel binned 2x more)."""
    protocol = load_protocol(CONFIGS / "protocols" / "demo_knee.yaml")
    d = protocol.detector
    panel = d.model_copy(update={"rows": 128, "cols": 128, "pixel_pitch_mm": 2 * d.pixel_pitch_mm})
    orbit = protocol.orbit.model_copy(update={"views": VIEWS})
    return protocol.model_copy(update={"detector": panel, "orbit": orbit, "name": "small"})


def backend_file(tmp: Path, **faults) -> Path:
    path = tmp / f"sim-{'-'.join(faults) or 'plain'}.yaml"
    path.write_text(yaml.safe_dump({"seed": 3, "faults": faults}))
    return path


def inputs(tmp: Path, **faults):
    return read_inputs(
        small_protocol(),
        CONFIGS / "scanner.yaml",
        "sim",
        backend_file(tmp, **faults),
        CONFIGS / "phantoms" / "knee.yaml",
        phantom_voxel_mm=PHANTOM_VOXEL_MM,
    )


def exp_commands(study: Path, session: int) -> list[float]:
    """When each EXP of a session was sent (its generator command log), monotonic s."""
    with open(study / "scan" / f"generator_commands-{session}.csv", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    return [float(row["monotonic_s"]) for row in rows if row["command"] == "EXP"]


def device_events(study: Path, session: int) -> list[tuple[int, str, str]]:
    with open(study / "scan" / f"device_events-{session}.csv", encoding="utf-8") as fh:
        return [(int(r["sequence"]), r["device"], r["event"]) for r in csv.DictReader(fh)]


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Path:
    """An uninterrupted scan."""
    tmp = tmp_path_factory.mktemp("reference")
    run_session(tmp / "study", inputs(tmp))
    return tmp / "study"


def test_scan_completes_with_every_file_checked(reference: Path):
    study = Study.open(reference)
    assert study.stage("plan")["status"] == "complete"
    scan = study.stage("scan")
    assert scan["status"] == "complete" and scan["views"] == VIEWS
    assert scan["dose_mas"] == pytest.approx(VIEWS * small_protocol().exposure.mas)
    assert study.verify() == []
    stack = read_projections(reference / "scan" / "projections.mha")
    assert stack.data.shape == (VIEWS, 128, 128)
    with open(reference / "scan" / "exposure_log.csv", encoding="utf-8") as fh:
        log = list(csv.DictReader(fh))
    assert [int(r["view"]) for r in log] == list(range(VIEWS))
    assert [int(r["sequence"]) for r in log] == list(range(1, VIEWS + 1))  # one pulse per view


def test_recorded_geometry_is_the_measured_one(reference: Path):
    """Recorded views come from the measured joints: off the plan by the tracking lag (within
    the acquisition tolerance), off the truth by the structure's vibration, which no encoder
    sees (RMS over a turn = the configured amplitude)."""
    scan = reference / "scan"
    panel = read_stack_header(scan / "projections.mha")
    recorded, true, planned = (
        read_rtk_geometry(scan / f"{name}.xml", panel)
        for name in ("geometry", "true_geometry", "planned_geometry")
    )
    vib = SimBackendSpec().vibration
    src_vs_true = np.linalg.norm(recorded.sources_mm - true.sources_mm, axis=1)
    rms = np.sqrt(np.mean(src_vs_true**2))
    assert 0.6 * vib.source_mm < rms < 1.4 * vib.source_mm
    src_vs_plan = np.linalg.norm(recorded.sources_mm - planned.sources_mm, axis=1)
    assert src_vs_plan.max() < ScanSettings().pose_tolerance_mm


def test_reconstructs_as_well_as_the_direct_simulation(reference: Path):
    """FDK of the scan with its RECORDED geometry is as accurate as FDK of the same protocol
    simulated directly (no arms, no generator, no storage) with its exact geometry: the chain
    adds no error beyond the vibration the encoders cannot see."""
    protocol = small_protocol()
    phantom = load_config(CONFIGS / "phantoms" / "knee.yaml", KneePhantomSpec)
    grid = VolumeGrid.centered((80, 80, 64), 1.5, (0.0, 0.0, 480.0))
    labels, mu = rasterize_knee(phantom, grid)
    inside = labels > 0
    stack = read_projections(reference / "scan" / "projections.mha")
    recorded = read_rtk_geometry(reference / "scan" / "geometry.xml", stack.header)
    ours = fdk_reconstruct(stack.data, recorded, grid).volume.data
    direct = simulate_knee_scan(protocol, phantom, voxel_mm=PHANTOM_VOXEL_MM, seed=3)
    theirs = fdk_reconstruct(direct.projections, direct.geometry, grid).volume.data

    def rmse(v):
        return float(np.sqrt(np.mean((v - mu)[inside] ** 2)))

    assert rmse(ours) < 1.1 * rmse(theirs)


def test_recording_has_every_view(reference: Path):
    chunks = defaultdict(list)
    for chunk in rr.chunk.RrdReader(reference / "scan" / "recording.rrd").stream():
        chunks[chunk.entity_path.lstrip("/")].append(chunk)
    for entity in ("scan/projection", "scan/joints/rotary", "world/scan/frustum"):
        rows = sum(c.to_record_batch().num_rows for c in chunks[entity] if not c.is_static)
        assert rows == VIEWS, entity


FAULTS = {
    "protective_stop_at_view": "protective stop",
    "generator_timeout_at_view": "no reply to 'exp'",
    "dropped_frame_at_view": "frame of exposure",
    "interlock_open_at_view": "interlock",
}


@pytest.mark.parametrize("fault", sorted(FAULTS))
def test_fault_ends_in_safe_and_resume_completes_the_same_scan(fault, reference, tmp_path):
    study_path = tmp_path / "study"
    with pytest.raises(ScanFault) as caught:
        run_session(
            study_path,
            inputs(tmp_path, **{fault: FAULT_VIEW}),
            settings=ScanSettings(device_timeout_s=1.0),
        )
    assert FAULTS[fault] in caught.value.reason.lower()
    study = Study.open(study_path)
    scan = study.stage("scan")
    assert scan["status"] == "incomplete" and scan["views_stored"] == FAULT_VIEW
    assert study.verify() == []
    assert not list((study_path / "scan" / "views").glob(".*"))  # reserved files released

    # SAFE: X-ray off first, then every joint group stops; no pulse after the fault
    events = device_events(study_path, 1)
    abort = min(seq for seq, who, what in events if who == "generator" and what == "abort")
    stops = [seq for seq, who, what in events if what == "stop"]
    assert {who for _, who, what in events if what == "stop"} >= {
        "stage",
        "source_arm",
        "detector_arm",
    }
    assert abort < min(stops)
    pulses = [seq for seq, who, what in events if who == "generator" and what == "xray_on"]
    assert len(pulses) == FAULT_VIEW + (fault == "dropped_frame_at_view")

    # the stored views are the reference's, bit for bit
    ref = Study.open(reference)
    for k in range(FAULT_VIEW):
        name = f"scan/views/view_{k:04d}.mha"
        assert study.manifest["files"][name] == ref.manifest["files"][name]

    # resume without the fault: completes, and the scan equals the uninterrupted one
    run_session(study_path, None, resume=True, backend_override=SimBackendSpec(seed=3))
    study = Study.open(study_path)
    assert study.stage("scan")["status"] == "complete" and study.verify() == []
    ours = read_projections(study_path / "scan" / "projections.mha").data
    theirs = read_projections(reference / "scan" / "projections.mha").data
    np.testing.assert_array_equal(ours[:FAULT_VIEW], theirs[:FAULT_VIEW])
    # the resumed panel starts without the charge the view before left (lag), which the
    # reference's correction removed with that view's estimate: the first resumed view differs
    # by lag / (1 - lag) of that estimate's noise (and by a count of rounding), the next ones
    # by powers of lag of it
    panel, protocol = SimPanelSpec(), small_protocol()
    counts = read_projections(reference / "scan" / "counts.mha").data[FAULT_VIEW:]
    signal_adu = np.maximum(counts - panel.offset_adu, 1.0)
    photons = photons_per_pixel(protocol.exposure, protocol.detector, protocol.orbit.sdd_mm)
    sigma = np.sqrt(
        np.exp(theirs[FAULT_VIEW:]) / photons + (panel.read_noise_adu**2 + 1 / 12) / signal_adu**2
    )
    bound = 6 * panel.lag / (1 - panel.lag) * sigma + 1.0 / signal_adu
    assert np.all(np.abs(ours[FAULT_VIEW:] - theirs[FAULT_VIEW:]) <= bound)


def test_off_pose_arms_never_expose(tmp_path):
    """With a pose tolerance below the arms' tracking lag every view is off pose: the scan
    stops at the first view and the generator never fires."""
    with pytest.raises(ScanFault) as caught:
        run_session(tmp_path / "s", inputs(tmp_path), settings=ScanSettings(pose_tolerance_mm=1e-3))
    assert "off pose" in caught.value.reason and caught.value.views_stored == 0
    events = device_events(tmp_path / "s", 1)
    assert not [e for e in events if e[2] == "xray_on"]


def test_operator_declining_moves_nothing(tmp_path):
    with pytest.raises(OperatorDeclined):
        run_session(tmp_path / "s", inputs(tmp_path), confirm=lambda _q: False)
    events = device_events(tmp_path / "s", 1)
    assert not [e for e in events if e[2] in ("xray_on", "prep")]
    assert not (tmp_path / "s" / "scan" / "views").exists()


def test_bad_input_is_refused_before_anything_is_written(tmp_path):
    with pytest.raises(ValueError, match=r"exceeds dose_limit_mas 10\.0 mAs"):
        read_inputs(
            small_protocol().model_copy(update={"dose_limit_mas": 10.0}),
            CONFIGS / "scanner.yaml",
            "sim",
            backend_file(tmp_path),
            CONFIGS / "phantoms" / "knee.yaml",
        )
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump({"lag_s": 5.0}))
    with pytest.raises(ValueError, match="lag_s"):
        read_inputs(
            small_protocol(),
            CONFIGS / "scanner.yaml",
            "sim",
            bad,
            CONFIGS / "phantoms" / "knee.yaml",
        )
    existing = tmp_path / "existing"
    existing.mkdir()
    (existing / "keep.txt").write_text("acquired")
    with pytest.raises(StudyError, match="never overwritten"):
        run_session(existing, inputs(tmp_path))
    assert [p.name for p in existing.iterdir()] == ["keep.txt"]


def test_resume_refuses_an_altered_view(reference, tmp_path):
    study_path = tmp_path / "study"
    with pytest.raises(ScanFault):
        run_session(study_path, inputs(tmp_path, dropped_frame_at_view=5))
    view = study_path / "scan" / "views" / "view_0002.mha"
    view.write_bytes(view.read_bytes()[:-4] + b"\0\0\0\0")
    with pytest.raises(StudyError, match=r"view 2: .* was altered"):
        run_session(study_path, None, resume=True, backend_override=SimBackendSpec(seed=3))
    assert (
        json.loads((study_path / "study.json").read_text())["stages"]["scan"]["views_stored"] == 5
    )


def test_at_a_pulse_only_the_view_before_may_not_be_on_disk_yet(tmp_path, monkeypatch):
    """A view's files are written while the plan streams on and the next view is exposed, but
    every pulse finds each view acquired before the one before it stored (its images and record
    in place) and its own view's space reserved; SAFE and DONE leave every view stored."""
    import study.simulator
    from scanner.generator import SerialGenerator

    expose, calibrate = SerialGenerator.expose, study.simulator.calibrate_detector
    pulses, not_yet, calibrating = [], 0, False

    def calibrating_panel(*args, **kwargs):  # the session's floods before the scan
        nonlocal calibrating
        calibrating = True
        try:
            return calibrate(*args, **kwargs)
        finally:
            calibrating = False

    def checked_expose(self, timeout_s, permit=None):
        nonlocal not_yet
        if calibrating:
            return expose(self, timeout_s, permit)
        n = len(pulses)
        views = tmp_path / "study" / "scan" / "views"
        on_disk = sorted(p.name for p in views.glob("view_*.json"))
        assert on_disk[: max(n - 1, 0)] == [f"view_{k:04d}.json" for k in range(max(n - 1, 0))]
        assert len(on_disk) in (max(n - 1, 0), n)
        not_yet += len(on_disk) < n
        for k in range(n - 1):
            assert (views / f"view_{k:04d}.mha").is_file()
            assert (views / f"view_{k:04d}_counts.mha").is_file()
        reserved = sorted(p.name for p in views.glob(f".view_{n:04d}*"))
        suffixes = ("_counts.tmp.mha", ".tmp.json", ".tmp.mha")
        assert reserved == sorted(f".view_{n:04d}{suffix}" for suffix in suffixes)
        pulses.append(n)
        return expose(self, timeout_s, permit)

    monkeypatch.setattr(SerialGenerator, "expose", checked_expose)
    monkeypatch.setattr(study.simulator, "calibrate_detector", calibrating_panel)
    run_session(tmp_path / "study", inputs(tmp_path))
    assert len(pulses) == VIEWS
    assert not_yet > 0  # the storage does overlap the next pulse
    study = Study.open(tmp_path / "study")
    assert study.verify() == [] and study.stage("scan")["views"] == VIEWS
    assert list((tmp_path / "study" / "scan" / "views").glob(".*")) == []


def test_a_view_whose_disk_space_cannot_be_reserved_is_not_exposed(tmp_path, monkeypatch):
    """The disk fills (another program) after view 5's room check: allocating its files'
    space fails, SAFE before its pulse, views 0-4 stored, no file of view 5 left behind.
    Before the reservation, the pulse fired and the view then failed to store."""
    fallocate = os.posix_fallocate

    def full_at_view_5(fd: int, offset: int, length: int) -> None:
        if os.readlink(f"/proc/self/fd/{fd}").endswith(".view_0005_counts.tmp.mha"):
            raise OSError(28, "No space left on device")
        fallocate(fd, offset, length)

    monkeypatch.setattr(os, "posix_fallocate", full_at_view_5)
    with pytest.raises(ScanFault, match=r"view 5: cannot reserve .* not exposing") as fault:
        run_session(tmp_path / "study", inputs(tmp_path))
    assert fault.value.views_stored == 5
    assert len(exp_commands(tmp_path / "study", 1)) == 5  # none for view 5
    views = tmp_path / "study" / "scan" / "views"
    assert sorted(p.name for p in views.iterdir() if "0005" in p.name) == []
    assert Study.open(tmp_path / "study").verify() == []


def test_a_view_that_cannot_be_stored_stops_the_scan_by_the_pulse_after_next(tmp_path, monkeypatch):
    """The storage of view 5 fails (its record cannot be written) while view 6 is exposed: SAFE
    before view 7's pulse at the latest (before view 6's when the failure is known by then),
    views 0-4 stored and view 6 if it was exposed, nothing of view 5 left behind."""
    import scanner.study_folder

    write_synced = scanner.study_folder._write_synced

    def failing(path, parts):
        if path.name == ".view_0005.tmp.json":
            raise OSError(28, "No space left on device")
        return write_synced(path, parts)

    monkeypatch.setattr(scanner.study_folder, "_write_synced", failing)
    with pytest.raises(ScanFault, match="No space left") as fault:
        run_session(tmp_path / "study", inputs(tmp_path))
    pulses = exp_commands(tmp_path / "study", 1)
    assert len(pulses) in (6, 7)  # views 0-5, and 6 when 5's failure was not known yet
    assert fault.value.views_stored == len(pulses) - 1
    study = Study.open(tmp_path / "study")
    assert study.stage("scan")["status"] == "incomplete"
    assert "view 5 could not be stored" in study.stage("scan")["reason"]
    views = study.path / "scan" / "views"
    stored = sorted(p.name for p in views.glob("view_*.json"))
    assert stored == [f"view_{k:04d}.json" for k in (0, 1, 2, 3, 4, 6)[: len(pulses) - 1]]
    assert sorted(p.name for p in views.iterdir() if "0005" in p.name) == []
    assert list(views.glob(".*")) == []
    assert study.verify() == []
