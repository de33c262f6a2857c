"""``cbct demo --size smoke`` end to end: every stage runs in one study folder (the
module's ``demo`` fixture) and every file is checked; the folder refuses a second demo and
resumes; a batch redoes a killed worker's task. The quick and full demos' figures against
the truth: test_demo_scored.py (slow; the quick one is its own step of .ci/run)."""

from __future__ import annotations

import csv
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
from typer.testing import CliRunner

from assessment.handoff import pose_of_itk
from assessment.slicer_scene import referenced_files
from recon.io import read_volume
from registration.poses import read_poses
from scanner.study_folder import Study
from study import batch
from study.cli import app
from study.demo import FULL, QUICK, SMOKE, STAGES, _protocols

runner = CliRunner()
CONFIGS = Path(__file__).resolve().parents[2] / "configs"


@pytest.fixture(scope="module")
def demo(tmp_path_factory, seed) -> Path:
    """The smoke demo, made once: the tests below check it, and the batch test takes a
    hard-linked copy of it (study files are replaced by rename, never rewritten in place, so
    the copy's changes leave it as it was)."""
    out = tmp_path_factory.mktemp("demo") / "study"
    args = ["demo", "--out", str(out), "--size", "smoke", "--seed", str(seed)]
    result = runner.invoke(app, args)
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
    assert frames == SMOKE["frames"] and strip.count("data:image/png;base64,") == frames
    assert html.count("data:image/png;base64,") >= frames + 4  # and the plots
    assert report.stat().st_size <= 15e6  # the bound for the full demo's report
    assert (demo / "assessment" / "frames_beside_4d.png").is_file()


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


def test_the_report_flags_no_frame_it_left_out(demo: Path):
    """The smoke demo's coarse fluoroscopy fails most registrations: no frame the assessment
    did not measure is flagged, and the report's count of measured frames is the table's."""
    assessment = Study.open(demo).stage("assessment")
    with (demo / "assessment" / "metrics.csv").open(encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == SMOKE["frames"]
    assert all(r["status"] == "measured" for r in rows if r["flagged"] == "1")
    assert sum(r["status"] == "measured" for r in rows) == assessment["measured_frames"]


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
    """cbct batch on a copy of the smoke demo's study whose segmentation is to be made again
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


def test_an_existing_folder_is_refused_and_resume_redoes_only_what_is_missing(demo, tmp_path):
    again = runner.invoke(app, ["demo", "--out", str(demo), "--size", "smoke"])
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
    result = runner.invoke(app, ["demo", "--out", str(copy), "--size", "smoke", "--resume"])
    assert result.exit_code == 0, result.output
    for stage in STAGES[:-2]:
        assert f"{stage}: complete, skipped" in result.output
    done = Study.open(copy)
    assert done.stage("assessment")["status"] == "complete" and done.verify() == []
