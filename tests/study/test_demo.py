"""``cbct demo --quick`` end to end: every stage in one study folder (the module's ``demo``
fixture), checked."""

from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import threading
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
import rerun as rr
import SimpleITK as sitk
from distributed import Client
from scipy.ndimage import binary_erosion
from typer.testing import CliRunner

from assessment.handoff import pose_of_itk
from assessment.slicer_scene import referenced_files
from recon.io import read_volume
from recon.motion import read_motion_csv
from registration.labels import LABELS
from registration.poses import read_poses
from scanner.study_folder import Study
from sim.phantoms.knee import KneePhantomSpec, attenuation_per_mm, rasterize_knee
from study import batch
from study.cli import app
from study.demo import FULL, QUICK, STAGES, _protocols

runner = CliRunner()
CONFIGS = Path(__file__).resolve().parents[2] / "configs"


@pytest.fixture(scope="module")
def demo(tmp_path_factory, seed) -> Path:
    """The quick demo, made once: the tests below check it, and the batch test takes a
    hard-linked copy of it (study files are replaced by rename, never rewritten in place, so
    the copy's changes leave it as it was)."""
    out = tmp_path_factory.mktemp("demo") / "study"
    result = runner.invoke(app, ["demo", "--out", str(out), "--quick", "--seed", str(seed)])
    assert result.exit_code == 0, result.output
    assert "demo finished" in result.output and f"rerun {out}/recording.rrd" in result.output
    return out


def test_every_stage_is_complete_and_every_file_checked(demo: Path):
    study = Study.open(demo)
    for stage in ("plan", *STAGES):
        assert study.stage(stage)["status"] == "complete", stage
    assert study.verify() == []
    files = study.manifest["files"]
    for name in (
        "calibration/geometry.xml",
        "scan/projections.mha",
        "scan/geometry.xml",
        "recon/volume.nii.gz",
        "segmentation/labels.nii.gz",
        "segmentation/femur.stl",
        "fluoro/frames.mha",
        "fluoro/dewarp_grid.mha",
        "registration/distortion.json",
        "registration/poses.csv",
        "registration/metrics.json",
        "assessment/report.html",
        "recording.rrd",
    ):
        assert name in files, name


def test_the_assessment_hands_the_motion_to_slicer_itk_and_autoscoper(demo: Path):
    export = demo / "assessment" / "export"
    named = referenced_files(export / "scene.mrml")
    assert export / "static.nii.gz" in named and all(p.is_file() for p in named)
    poses = read_poses(demo / "registration" / "poses.csv")
    last = max(p.frame for p in poses)
    for pose in (p for p in poses if p.frame == last):
        tfm = sitk.ReadTransform(str(export / "itk" / pose.body / f"frame_{last:04d}.tfm"))
        np.testing.assert_allclose(pose_of_itk(tfm), pose.T_world_body, atol=1e-9)


def test_report_has_its_plots_and_plays_every_registered_frame(demo: Path):
    report = demo / "assessment" / "report.html"
    html = report.read_text(encoding="utf-8")
    assert len(list((demo / "assessment").glob("*.png"))) >= 4
    frames = len(list((demo / "registration" / "overlays").glob("frame_*.png")))
    start = html.index('<div class="filmstrip">')
    strip = html[start : html.index("</div>", start)]
    assert frames == 8 and strip.count("data:image/png;base64,") == frames
    assert html.count("data:image/png;base64,") >= frames + 4  # and the plots
    assert report.stat().st_size <= 15e6  # the bound for the full demo's report
    assert (demo / "assessment" / "frames_beside_4d.png").is_file()


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


@pytest.mark.parametrize(
    ("protocol", "views"),
    [
        ("knee_reverse_spiral_360_sparse90.yaml", {"full": 44, "quick": 44}),
        ("knee_reverse_spiral_360_quarter_dose.yaml", {"full": 180, "quick": 90}),
    ],
)
def test_a_protocol_given_to_the_demo_scans_its_share_of_the_full_demos_views(
    protocol: str, views: dict[str, int]
):
    """A 90-view protocol: a quarter of the full demo's 180 views in whole passes of the
    spiral (45 is one pass and a half, refused by the orbit); a 360-view one: each size's
    own. The plan and the calibration read-out agree on them."""
    for name, size in (("full", FULL), ("quick", QUICK)):
        knee, calibration = _protocols(
            CONFIGS, size | {"protocol": CONFIGS / "protocols" / protocol}
        )
        assert knee.orbit.views == calibration.orbit.views == views[name]
        assert knee.orbit.views % knee.orbit.passes == 0
        assert knee.reconstruction.method == "tv"


def test_the_demo_report_plays_the_knee_in_3d_offline(demo: Path, browse):
    _plays_in_3d_offline(demo, browse)


@pytest.mark.slow
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


def test_the_recording_holds_every_stage_on_its_timeline(demo: Path):
    timelines = defaultdict(set)
    for chunk in rr.chunk.RrdReader(demo / "recording.rrd").stream():
        if not chunk.is_static:
            timelines[chunk.entity_path.lstrip("/")].update(chunk.timeline_names)
    assert "plan_time" in timelines["joints/rotary"]  # arms through the plan
    assert "view" in timelines["world/views/frustum"]  # source/detector frustums
    assert "view" in timelines["scan/projection"]
    assert "view" in timelines["calibration_scan/projection"]
    assert "slice" in timelines["recon/axial"]  # the volume's slices
    for bone in ("femur", "tibia_fibula", "patella"):
        assert "frame" in timelines[f"world/bones/{bone}"]


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


def test_cbct_segment_labels_a_scan_as_the_demo_does(demo: Path, tmp_path):
    """A user's own static scan through cbct segment: the demo's reconstruction gives the
    demo's labels (the side found from the fibula, not told), and a mesh per bone."""
    out, meshes = tmp_path / "labels.nii.gz", tmp_path / "meshes"
    args = ["segment", "--volume", str(demo / "recon" / "volume.nii.gz"), "--out", str(out)]
    result = runner.invoke(app, [*args, "--meshes", str(meshes)])
    assert result.exit_code == 0, result.output
    assert "femur" in result.output and "patella" in result.output
    ours = read_volume(out, unit="label")
    demos = read_volume(demo / "segmentation" / "labels.nii.gz", unit="label")
    assert ours.grid == demos.grid and np.array_equal(ours.data, demos.data)
    assert sorted(p.name for p in meshes.iterdir()) == sorted(
        p.name for p in (demo / "segmentation").glob("*.stl")
    )


def test_a_worker_killed_mid_task_loses_nothing(demo, tmp_path):
    """cbct batch on a copy of the quick demo's study whose segmentation is to be made again
    (the recon task's second stage): a worker SIGKILLed while it segments, its folder half
    written; the task runs again elsewhere. (Here, beside the demo's other tests: the suite's
    parallel workers take whole files, and the demo is made once per worker.)"""
    studies = [tmp_path / "studies" / "knee"]
    shutil.copytree(demo, studies[0], copy_function=os.link)
    copy = Study.open(studies[0])
    copy.mark("segmentation", "incomplete", reason="made again by the test")
    killed: dict[str, object] = {}

    def kill_a_worker_in_segmentation(client: Client) -> None:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and "pid" not in killed:
            if any((p / "segmentation.partial").is_dir() for p in studies):
                for address, stacks in client.call_stack().items():
                    keys = [k for k in stacks if str(k).startswith("recon-")]
                    if keys:
                        pid = client.run(os.getpid, workers=[address])[address]
                        os.kill(pid, signal.SIGKILL)
                        killed.update(address=address, pid=pid, key=str(keys[0]))
                        return
            time.sleep(0.05)

    options = batch.TaskOptions()
    cluster = batch.local_cluster(2)
    try:
        with Client(cluster) as client:
            killer = threading.Thread(target=kill_a_worker_in_segmentation, args=(client,))
            killer.start()
            report = batch.run(client, studies, "recon", options)
            killer.join()
    finally:
        cluster.close()

    assert "pid" in killed, "no recon task was seen segmenting"
    index = int(str(killed["key"]).rsplit("-", 1)[1])
    assert [o.status for o in report.outcomes] == ["ran"], report.outcomes
    rerun = next(o for o in report.outcomes if o.study == str(studies[index]))
    assert rerun.pid != killed["pid"]  # the killed task ran again, in another process
    for path in studies:
        study = Study.open(path)
        assert all(study.stage(s)["status"] == "complete" for s in ("recon", "segmentation"))
        assert study.verify() == [] and not list(path.glob("*.partial"))
        assert (path / "segmentation" / "labels.nii.gz").is_file()


@pytest.mark.slow
def test_the_full_demo_tracks_every_frame_within_the_rsr_threshold(full_demo: Path, measured):
    """30 frames to 90 deg, a static scan of 0.8 mm voxels: every registration's TRE below the
    RSR threshold (1.5 mm), the paper's success criterion."""
    metrics = json.loads((full_demo / "registration" / "metrics.json").read_text("utf-8"))
    measured("worst_tre_mm", max(row["tre_mm"] for row in metrics["per_frame"]), below=1.5)


def test_an_existing_folder_is_refused_and_resume_redoes_only_what_is_missing(demo, tmp_path):
    again = runner.invoke(app, ["demo", "--out", str(demo), "--quick"])
    assert again.exit_code == 2 and "not empty" in again.output
    copy = tmp_path / "copy"
    shutil.copytree(demo, copy)
    shutil.rmtree(copy / "assessment")
    (copy / "recording.rrd").unlink()
    study = Study.open(copy)
    study.mark("assessment", "incomplete", reason="interrupted (test)")
    study.mark("recording", "incomplete", reason="interrupted (test)")
    for name in [n for n in study.manifest["files"] if n.startswith("assessment/")]:
        del study.manifest["files"][name]
    del study.manifest["files"]["recording.rrd"]
    study.save()
    result = runner.invoke(app, ["demo", "--out", str(copy), "--quick", "--resume"])
    assert result.exit_code == 0, result.output
    for stage in STAGES[:-2]:
        assert f"{stage}: complete, skipped" in result.output
    done = Study.open(copy)
    assert done.stage("assessment")["status"] == "complete" and done.verify() == []
