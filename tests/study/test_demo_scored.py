"""The demos scored against the simulation's truth (slow): ``cbct demo --quick`` (about
3 minutes on 2 cores; .ci/run runs it as its own step, `-k "not full_demo"`) and the full
demo. The plumbing of every stage, on the smallest demo, runs by default (test_demo.py)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import binary_erosion
from typer.testing import CliRunner

from recon.io import read_volume
from recon.motion import read_motion_csv
from registration.labels import LABELS
from scanner.study_folder import Study
from sim.phantoms.knee import KneePhantomSpec, attenuation_per_mm, rasterize_knee
from study.cli import app

runner = CliRunner()
pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def demo(tmp_path_factory, seed) -> Path:
    """The quick demo, made once: the tests below score it against the simulation's truth."""
    out = tmp_path_factory.mktemp("demo") / "study"
    result = runner.invoke(app, ["demo", "--out", str(out), "--quick", "--seed", str(seed)])
    assert result.exit_code == 0, result.output
    assert "demo finished" in result.output and f"rerun {out}/recording.rrd" in result.output
    return out


def _plays_in_3d_offline(study: Path, browse) -> None:
    """Chromium opens the study's report at the first frame and at the deepest flexion: no
    request leaves the file, the 3D view draws both, and they differ (the knee flexed)."""
    report = study / "assessment" / "report.html"
    with (study / "assessment" / "metrics.csv").open(encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    deepest = max(rows, key=lambda r: float(r["flexion_deg"]))["frame"]
    canvases = []
    for frame in (rows[0]["frame"], deepest):
        shown = browse(report, f"frame={frame}&probe")
        assert shown.requests == []
        canvases.append(shown.canvas())
        assert canvases[-1].std() > 0.05
    assert (np.abs(canvases[0] - canvases[1]).max(axis=2) > 0.1).mean() > 0.02


def test_the_demo_report_plays_the_knee_in_3d_offline(demo: Path, browse):
    _plays_in_3d_offline(demo, browse)


def test_the_full_demo_report_plays_every_frame_in_3d_offline(full_demo: Path, browse):
    """The full demo's report: an overlay for each of its 30 frames, within 15 MB, played in
    3D offline."""
    report = full_demo / "assessment" / "report.html"
    text = report.read_text(encoding="utf-8")
    start = text.index('<div class="filmstrip">')
    assert text[start : text.index("</div>", start)].count("data:image/png;base64,") == 30
    assert report.stat().st_size <= 15e6
    _plays_in_3d_offline(full_demo, browse)


def test_the_calibration_recovers_the_vibration(demo: Path, measured):
    """The arms vibrate 0.3 mm in a way no encoder sees: the calibrated geometry reconstructs
    as well as the true one (RMSE within 1 %)."""
    recon = Study.open(demo).stage("recon")
    ratio = recon["rmse_calibrated_per_mm"] / recon["rmse_true_per_mm"]
    measured("rmse_calibrated_excess", ratio - 1.0, below=0.01)


def test_the_volume_has_the_phantom_attenuation(demo: Path, measured):
    """Soft tissue away from edges (eroded by 3 voxels) within 3 % of muscle: quantum noise at
    ~1e6 photons per 2.4 mm pixel and the cone-beam error stay below that."""
    volume = read_volume(demo / "recon" / "volume.nii.gz")
    spec = KneePhantomSpec()
    labels, _ = rasterize_knee(spec, volume.grid, supersample=1)
    soft = binary_erosion(labels == LABELS["soft_tissue"], iterations=3) & (volume.data > 0)
    mu = attenuation_per_mm(spec.effective_energy_kev)
    error = abs(np.median(volume.data[soft]) / mu["muscle"] - 1.0)
    measured("soft_tissue_mu_rel_error", error, below=0.03)
    assert len(list((demo / "recon" / "dicom").glob("*.dcm"))) == volume.grid.shape[0]


def test_the_recon_stage_compensates_the_patients_sway(demo: Path, measured):
    """The quick demo's patient sways by 1.5 mm at the knee: the recon stage finds the motion
    (kept, as the projections agree better with it), reconstructs through it no worse than
    the volume made during the scan, writes the motion and its QA figure, and the report says
    so. (bench/motion.py measures the recovery against the sway's size.)"""
    study = Study.open(demo)
    recon = study.stage("recon")
    motion = recon["motion"]
    assert motion["reprojection_rms"]["moving"] < motion["reprojection_rms"]["still"]
    assert 0.5 < max(motion["peak_mm"].values()) < 8.0
    measured("motion_error_median_mm", motion["error_mm"]["median"], below=1.5)
    assert recon["rmse_calibrated_per_mm"] <= recon["rmse_uncompensated_per_mm"]
    bodies, poses = read_motion_csv(demo / "recon" / "motion.csv")
    assert bodies == tuple(motion["bodies"]) and len(poses) == study.stage("scan")["views"]
    assert (demo / "recon" / "motion.png").stat().st_size > 10_000
    assert (demo / "recon" / "live_volume.mha").is_file()
    assert (demo / "scan" / "true_motion.csv").is_file()
    report = (demo / "assessment" / "report.html").read_text(encoding="utf-8")
    assert "Static scan" in report and motion["verdict"] in report


def test_registration_tracks_every_bone_within_the_single_plane_physics(demo: Path, measured):
    """The quick demo (8 frames to 40 deg, a static scan of 1 mm voxels): median TRE below a
    voxel, every frame's in-plane error below half a voxel, and at most one registration in ten
    beyond the RSR threshold (1.5 mm). Depth, along the ray, is what single-plane registration
    resolves worst: over seeds 0-2, threads 1-2 and two CPUs' code paths the worst frame's
    TRE, depth nearly all of it, ranged 1.19 to 1.52 mm here; the full demo, at finer voxels,
    holds every frame below the threshold (the slow test below). The fluoroscopy is rendered
    from the 0.5 mm phantom: over seeds 0-2 the worst frame's TRE was 1.48, 1.44 and 1.80 mm
    here (RSR 100, 100 and 95.8 %); from the 1 mm phantom the femur's first frame stood 1.8 mm
    deep and two bodies failed. Those spreads predate the patient's sway: with the 1.5 mm sway
    compensated, seed 2 fails this test (one thread, Zen 3: TRE median 1.10 mm, RSR 66.7 %;
    standing still 0.62 mm, 100 %), the femur's and the patella's depth 1.4-2.2 mm (the
    standing patient issue's tracking target)."""
    metrics = json.loads((demo / "registration" / "metrics.json").read_text(encoding="utf-8"))
    measured("tre_median_mm", metrics["tre_mm_median"], below=1.0)
    measured("in_plane_worst_mm", max(r["in_plane_mm"] for r in metrics["per_frame"]), below=0.5)
    measured("rsr_shortfall_pct", 100.0 - metrics["rsr_pct"], below=10.0)


def test_the_report_flags_nothing_the_true_poses_do_not_and_no_frame_it_left_out(demo: Path):
    """Every frame the demo's report flags, the assessment of the true poses flags too (the
    varus built into frames 3-4 opens the lateral compartment 2.4 mm); no flagged frame is
    one the assessment did not measure."""
    assessment = Study.open(demo).stage("assessment")
    assert set(assessment["flagged_frames"]) <= set(assessment["truth_flagged_frames"])
    assert assessment["truth_flagged_frames"] == [3, 4]
    with (demo / "assessment" / "metrics.csv").open(encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    assert all(r["status"] == "measured" for r in rows if r["flagged"] == "1")
    assert sum(r["status"] == "measured" for r in rows) == assessment["measured_frames"]


@pytest.fixture(scope="module")
def full_demo(tmp_path_factory, seed) -> Path:
    out = tmp_path_factory.mktemp("full-demo") / "study"
    result = runner.invoke(app, ["demo", "--out", str(out), "--seed", str(seed)])
    assert result.exit_code == 0, result.output
    return out


def test_the_full_demo_tracks_every_frame_within_the_rsr_threshold(full_demo: Path, measured):
    """30 frames to 90 deg, a static scan of 0.8 mm voxels: every registration's TRE below the
    RSR threshold (1.5 mm), the paper's success criterion."""
    metrics = json.loads((full_demo / "registration" / "metrics.json").read_text("utf-8"))
    measured("worst_tre_mm", max(row["tre_mm"] for row in metrics["per_frame"]), below=1.5)
