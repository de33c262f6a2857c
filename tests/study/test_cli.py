"""The console ``cbct``: simulate-scan, recon and demo end to end, and their refusals."""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from configs import CONFIGS
from recon.config import load_protocol
from recon.fdk import fdk_reconstruct
from recon.geometry import DetectorSpec
from recon.io import read_projections, read_volume, write_projections
from recon.motion import read_motion_csv
from recon.rtk_xml import PanelHeader, read_rtk_geometry, write_rtk_geometry
from sim.phantoms.knee import KneePhantomSpec, rasterize_knee
from study.cli import app

runner = CliRunner()
ROOT = Path(__file__).resolve().parents[2]


def tiny_protocol(tmp_path: Path, **orbit) -> Path:
    """The demo protocol read out 8x8 binned with 60 views: a scan in seconds."""
    data = yaml.safe_load((CONFIGS / "protocols" / "demo_knee.yaml").read_text(encoding="utf-8"))
    data["detector"] = {"rows": 64, "cols": 64, "pixel_pitch_mm": 9.6}
    data["orbit"].update({"views": 60} | orbit)
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def recon_args(projections: Path, geometry: Path, out: Path, *more: str) -> list[str]:
    """``cbct recon``'s arguments for a stack, its geometry, an output and ``more``."""
    return [
        "recon",
        "--projections",
        str(projections),
        "--geometry",
        str(geometry),
        "--out",
        str(out),
        *more,
    ]


@pytest.fixture(scope="module")
def scan_folder(tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("scan")
    out = tmp / "scan"
    result = runner.invoke(
        app,
        [
            "simulate-scan",
            "--protocol",
            str(tiny_protocol(tmp)),
            "--out",
            str(out),
            "--voxel-mm",
            "2.0",
        ],
    )
    assert result.exit_code == 0, result.output
    return out


def test_simulate_scan_writes_a_checksummed_rtk_readable_scan(scan_folder):
    manifest = json.loads((scan_folder / "scan.json").read_text(encoding="utf-8"))
    for name, digest in manifest["files"].items():
        assert hashlib.sha256((scan_folder / name).read_bytes()).hexdigest() == digest
    stack = read_projections(scan_folder / "projections.mha")
    geometry = read_rtk_geometry(scan_folder / "geometry.xml", stack.header)
    assert stack.data.shape == (60, 64, 64) and len(geometry) == 60
    counts = read_projections(scan_folder / "counts.mha").data
    photons = manifest["photons_per_pixel"]
    # the stored line integrals are -ln(counts / I0) of the stored counts
    np.testing.assert_allclose(stack.data, -np.log(counts / photons), atol=2e-5)
    assert read_volume(scan_folder / "labels.nii.gz").unit == "label"


def test_simulate_scan_refuses_a_folder_with_data(scan_folder, tmp_path):
    before = sorted(p.name for p in scan_folder.iterdir())
    result = runner.invoke(
        app,
        ["simulate-scan", "--protocol", str(tiny_protocol(tmp_path)), "--out", str(scan_folder)],
    )
    assert result.exit_code == 2
    assert "exists and is not empty" in result.output
    assert sorted(p.name for p in scan_folder.iterdir()) == before


def test_a_bad_protocol_field_is_named_with_its_value_and_limit(tmp_path):
    path = tiny_protocol(tmp_path, sid_mm=-600)
    result = runner.invoke(
        app, ["simulate-scan", "--protocol", str(path), "--out", str(tmp_path / "x")]
    )
    assert result.exit_code == 2
    assert str(path) in result.output and "orbit.sid_mm" in result.output
    assert "-600" in result.output and "greater than 0" in result.output
    assert not (tmp_path / "x").exists()


def test_recon_reconstructs_the_scan_and_refuses_to_overwrite(scan_folder, tmp_path):
    out = tmp_path / "volume.nii.gz"
    args = recon_args(
        scan_folder / "projections.mha",
        scan_folder / "geometry.xml",
        out,
        "--spacing-mm",
        "2.0",
        "--size",
        "64",
        "64",
        "64",
        "--preview",
        str(tmp_path / "slices.png"),
    )
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    volume = read_volume(out)
    assert volume.grid.size_xyz == (64, 64, 64) and volume.unit == "1/mm"
    protocol = load_protocol(tiny_protocol(tmp_path))
    np.testing.assert_allclose(volume.grid.center_mm, protocol.orbit.isocenter_mm, atol=1e-6)
    assert (tmp_path / "slices.png").stat().st_size > 10_000
    again = runner.invoke(app, args)
    assert again.exit_code == 2 and "exists" in again.output


def test_recon_refuses_mismatched_and_broken_inputs(scan_folder, tmp_path):
    stack = read_projections(scan_folder / "projections.mha")
    geometry = read_rtk_geometry(scan_folder / "geometry.xml", stack.header)
    fewer = write_rtk_geometry(tmp_path / "fewer.xml", geometry[:50])
    result = runner.invoke(
        app, recon_args(scan_folder / "projections.mha", fewer, tmp_path / "v.mha")
    )
    assert result.exit_code == 2
    assert "holds 60 projections" in result.output and "describes 50 views" in result.output
    truncated = tmp_path / "truncated.mha"
    truncated.write_bytes((scan_folder / "projections.mha").read_bytes()[:5000])
    result = runner.invoke(
        app, recon_args(truncated, scan_folder / "geometry.xml", tmp_path / "w.mha")
    )
    assert result.exit_code == 2 and str(truncated) in result.output
    nan = stack.data.copy()
    nan[3, 10, 10] = np.nan
    with pytest.raises(ValueError, match="NaN"):  # refused before anything is written
        write_projections(tmp_path / "nan.mha", nan, 9.6)
    assert not list(tmp_path.glob("*.nii.gz")) and not (tmp_path / "v.mha").exists()


def _rtk_turned_scan(folder: Path, views: int, panel: int, pitch: float) -> tuple[Path, Path]:
    """A scan made by RTK alone (data made elsewhere): a circular orbit about world z whose
    panel is turned a quarter (rows along the axis) and read out bottom-up (Direction
    diag(1, -1)), its pixel (0, 0) at RTK's default Origin (0, 0); RTK's XML writer and its
    analytic Shepp-Logan projections, written by ITK."""
    import itk
    from itk import RTK as rtk

    geometry = rtk.ThreeDCircularProjectionGeometry.New()
    for beta in np.radians(np.arange(views) * 360.0 / views):
        toward = np.array([np.sin(beta), -np.cos(beta), 0.0])
        row, col = np.array([0.0, 0.0, 1.0]), np.array([np.cos(beta), np.sin(beta), 0.0])
        center = -400.0 * toward
        corner = center - 0.5 * (panel - 1) * pitch * (row - col)  # pixel (0, 0), v reversed
        geometry.AddProjection(
            itk.Point[itk.D, 3]((600.0 * toward).tolist()),
            itk.Point[itk.D, 3](corner.tolist()),
            itk.Vector[itk.D, 3](row.tolist()),
            itk.Vector[itk.D, 3](col.tolist()),
        )
    writer = rtk.ThreeDCircularProjectionGeometryXMLFileWriter.New()
    writer.SetFilename(str(folder / "rtk.xml"))
    writer.SetObject(geometry)
    writer.WriteFile()
    image_type = itk.Image[itk.F, 3]
    stack = itk.image_from_array(np.zeros((views, panel, panel), np.float32))
    stack.SetSpacing([pitch, pitch, 1.0])
    stack.SetDirection(itk.matrix_from_array(np.diag([1.0, -1.0, 1.0])))
    phantom = rtk.SheppLoganPhantomFilter[image_type, image_type].New()
    phantom.SetInput(stack)
    phantom.SetGeometry(geometry)
    phantom.SetPhantomScale(28.0)
    phantom.Update()
    itk.imwrite(phantom.GetOutput(), str(folder / "rtk.mha"))
    return folder / "rtk.mha", folder / "rtk.xml"


def test_recon_reads_an_rtk_scan_of_a_turned_panel_by_its_own_header(tmp_path, measured):
    """RTK's scan of a turned, bottom-up panel at Origin (0, 0) reconstructs as well as the
    same orbit with an upright, centred panel (its header read, its negative SID honoured, its
    rows filtered along the motion); the same file with its Origin rewritten (centred) no
    longer belongs to its geometry and is refused with the Origin named."""
    from recon.geometry import circular_orbit
    from recon.rtk_peer import rtk_shepp_logan

    projections, geometry = _rtk_turned_scan(tmp_path, 90, 96, 1.6)
    out = tmp_path / "turned.mha"
    args = ["recon", "--projections", str(projections), "--geometry", str(geometry)]
    grid_args = ["--spacing-mm", "1", "--size", "64", "64", "64", "--filter", "ram-lak"]
    result = runner.invoke(app, [*args, "--out", str(out), *grid_args])
    assert result.exit_code == 0, result.output
    turned = read_volume(out)
    grid = turned.grid
    np.testing.assert_allclose(grid.center_mm, (0.0, 0.0, 0.0), atol=1e-9)  # the orbit's
    upright = circular_orbit(90, 600, 1000, DetectorSpec(rows=96, cols=96, pixel_pitch_mm=1.6))
    data, truth = rtk_shepp_logan(upright, grid, 28.0)
    reference = fdk_reconstruct(data, upright, grid, window="ram-lak").volume.data
    x, y, z = grid.axes_mm()
    inside = (np.abs(z) < 24)[:, None, None] & (np.hypot(*np.meshgrid(x, y)) < 24)[None]

    def rmse(volume):
        return float(np.sqrt(np.mean((volume - truth)[inside] ** 2)))

    measured("rmse_turned_rel_diff", abs(rmse(turned.data) / rmse(reference) - 1.0), below=0.02)

    import SimpleITK as sitk

    image = sitk.ReadImage(str(projections))
    image.SetOrigin((-76.0, 76.0, 0.0))  # centred, as for a geometry of a centred panel
    moved = tmp_path / "centred.mha"
    sitk.WriteImage(image, str(moved))
    result = runner.invoke(
        app,
        [
            "recon",
            "--projections",
            str(moved),
            "--geometry",
            str(geometry),
            "--out",
            str(tmp_path / "bad.mha"),
            *grid_args,
        ],
    )
    assert result.exit_code == 2
    assert "rotation axis projects at pixel" in result.output and "Origin" in result.output
    assert not (tmp_path / "bad.mha").exists()


def test_plan_writes_the_study_plan_and_a_recording(tmp_path):
    protocol = tiny_protocol(tmp_path, views=24)
    study = tmp_path / "study"
    result = runner.invoke(app, ["plan", "--protocol", str(protocol), "--out", str(study)])
    assert result.exit_code == 0, result.output
    names = sorted(p.name for p in (study / "plan").iterdir())
    assert names == [
        "collision_report.json",
        "geometry.xml",
        "recording.rrd",
        "summary.json",
        "trajectory.npz",
        "views.csv",
    ]
    summary = json.loads((study / "plan" / "summary.json").read_text(encoding="utf-8"))
    assert summary["views"] == 24 and summary["min_clearance_mm"] >= 20.0
    assert "min clearance" in result.output and "max joint speed" in result.output
    panel = load_protocol(protocol).detector
    centred = PanelHeader.centered(panel.rows, panel.cols, panel.pixel_pitch_mm)
    geometry = read_rtk_geometry(study / "plan" / "geometry.xml", centred)
    assert len(geometry) == 24


def test_plan_refuses_an_unsafe_protocol_and_writes_nothing(tmp_path):
    scanner = yaml.safe_load((CONFIGS / "scanner.yaml").read_text(encoding="utf-8"))
    scanner["obstacles"]["patient"] = [
        {"center_xy_mm": [0, 0], "radius_mm": 390, "z_min_mm": 0, "z_max_mm": 1800}
    ]
    scanner_path = tmp_path / "scanner.yaml"
    scanner_path.write_text(yaml.safe_dump(scanner))
    study = tmp_path / "study"
    result = runner.invoke(
        app,
        [
            "plan",
            "--protocol",
            str(tiny_protocol(tmp_path, views=12)),
            "--out",
            str(study),
            "--scanner",
            str(scanner_path),
        ],
    )
    assert result.exit_code == 2
    assert "view 0: detector_tool and patient0 are 10.0 mm apart" in result.output
    assert not study.exists()


def test_assess_writes_the_report_and_the_4d_series(tmp_path):
    from recon.io import write_volume
    from recon.volume import Volume, VolumeGrid
    from registration.poses import BodyPose, write_poses
    from sim.motion import flexion_extension

    spec = KneePhantomSpec()
    grid = VolumeGrid.centered((96, 96, 220), 1.5, (0.0, -4.0, 490.0))
    labels = Volume(rasterize_knee(spec, grid, supersample=1)[0], grid, "label")
    write_volume(tmp_path / "labels.nii.gz", labels)
    motion = flexion_extension(
        spec, frames=6, max_flexion_deg=60.0, varus_deg=4.0, varus_frames=(2, 3)
    )
    poses = [
        BodyPose(int(f), b, motion.poses[b][i])
        for i, f in enumerate(motion.frames)
        for b in ("femur", "tibia", "patella")
    ]
    write_poses(
        tmp_path / "poses.csv", poses, {b: np.zeros(3) for b in ("femur", "tibia", "patella")}
    )
    out = tmp_path / "assessment"
    args = [
        "assess",
        "--poses",
        str(tmp_path / "poses.csv"),
        "--labels",
        str(tmp_path / "labels.nii.gz"),
        "--out",
        str(out),
    ]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "6 frames" in result.output and "2 frame(s) flagged" in result.output
    page = (out / "report.html").read_text(encoding="utf-8")
    assert "frames 2–3" in page and page.count("data:image/png;base64,") == 5
    assert len((out / "metrics.csv").read_text(encoding="utf-8").splitlines()) == 7
    assert sorted(p.name for p in (out / "series" / "frame_0003").iterdir()) == [
        "femur.stl",
        "patella.stl",
        "tibia.stl",
    ]
    assert (out / "series.rrd").stat().st_size > 0
    again = runner.invoke(app, args)
    assert again.exit_code == 2 and "exists" in again.output


def test_calibrate_then_reconstruct_a_scan_of_the_same_protocol(tmp_path):
    """A BB scan and a knee scan on the same vibrating arms (same pattern): calibrate from the
    first, reconstruct the second with it; a scan of another protocol is refused."""
    data = yaml.safe_load((CONFIGS / "protocols" / "calibration_spiral.yaml").read_text())
    data["orbit"]["views"] = 24
    protocol = tmp_path / "cal.yaml"
    protocol.write_text(yaml.safe_dump(data))
    shake = ["--vibration-mm", "0.5", "--vibration-deg", "0.2"]
    for phantom, folder in (("bb", "bb"), ("knee", "knee")):
        result = runner.invoke(
            app,
            [
                "simulate-scan",
                "--protocol",
                str(protocol),
                "--out",
                str(tmp_path / folder),
                "--phantom",
                phantom,
                "--voxel-mm",
                "1.0",
                "--no-noise",
                *shake,
            ],
        )
        assert result.exit_code == 0, result.output
        assert (tmp_path / folder / "true_geometry.xml").exists()
    bb = tmp_path / "bb"
    result = runner.invoke(
        app,
        [
            "calibrate",
            "--projections",
            str(bb / "projections.mha"),
            "--geometry",
            str(bb / "geometry.xml"),
            "--protocol",
            str(protocol),
            "--study",
            str(tmp_path / "study"),
        ],
    )
    assert result.exit_code == 0, result.output
    assert "24 of 24 views calibrated" in result.output
    knee = tmp_path / "knee"
    args = [
        "recon",
        "--projections",
        str(knee / "projections.mha"),
        "--geometry",
        str(knee / "geometry.xml"),
        "--size",
        "32",
        "32",
        "32",
        "--spacing-mm",
        "3",
    ]
    result = runner.invoke(
        app,
        [
            *args,
            "--out",
            str(tmp_path / "v.mha"),
            "--calibration",
            str(tmp_path / "study" / "calibration"),
            "--protocol",
            str(protocol),
        ],
    )
    assert result.exit_code == 0, result.output
    other = tmp_path / "other.yaml"
    other.write_text(yaml.safe_dump(data | {"name": "other"}))
    result = runner.invoke(
        app,
        [
            *args,
            "--out",
            str(tmp_path / "w.mha"),
            "--calibration",
            str(tmp_path / "study" / "calibration"),
            "--protocol",
            str(other),
        ],
    )
    assert result.exit_code == 2
    assert "cannot correct a scan of protocol 'other'" in result.output


def test_the_console_loads_only_what_the_command_runs():
    """``cbct --help`` and a scan's start import none of the science they do not use (the
    console answers in a fraction of a second and a scan's process starts sooner)."""
    probe = (
        "import sys; from study.cli import app; "
        "print(' '.join(m for m in {MODULES} if m in sys.modules))"
    )
    heavy = ("distributed", "matplotlib", "registration.tracking", "SimpleITK", "pinocchio")
    scan = ("distributed", "registration.tracking")  # (toppra, which plans it, loads matplotlib)
    scanning = "from scanner import session; from study import live_recon, stages; "
    for command, absent in (("", heavy), (scanning, scan)):
        code = command + probe.format(MODULES=repr(heavy))
        out = subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT
        )
        loaded = out.stdout.split()
        assert not set(loaded) & set(absent), (command or "--help", loaded)


def test_every_command_has_clean_help_and_the_console_a_version():
    """Help as a user reads it: no reStructuredText markup, paragraphs reflowed to the terminal."""
    names = [c.name or c.callback.__name__.replace("_", "-") for c in app.registered_commands]
    assert {"plan", "scan", "recon", "register", "assess", "demo", "batch"} <= set(names)
    for name in names:
        result = runner.invoke(app, [name, "--help"], terminal_width=100)
        assert result.exit_code == 0 and "Usage:" in result.output, name
        assert "``" not in result.output, name
    version = runner.invoke(app, ["--version"])
    assert version.exit_code == 0 and version.output.startswith("dualarm-cbct ")


def test_batch_help_states_the_connect_timeout_batch_uses():
    """The console keeps study.batch unloaded for --help, so its help repeats the default."""
    from study import batch

    result = runner.invoke(app, ["batch", "--help"], terminal_width=200)
    assert f"CONNECT_TIMEOUT_S, {batch.CONNECT_TIMEOUT_S:g} s" in " ".join(result.output.split())


@pytest.fixture(scope="module")
def swaying_scan(tmp_path_factory) -> Path:
    """90 views of 128 x 128 pixels of 4.8 mm while the patient sways 3 mm at the knee."""
    tmp = tmp_path_factory.mktemp("sway")
    data = yaml.safe_load((CONFIGS / "protocols" / "demo_knee.yaml").read_text(encoding="utf-8"))
    data["detector"] = {"rows": 128, "cols": 128, "pixel_pitch_mm": 4.8}
    data["orbit"]["views"] = 90
    protocol = tmp / "small.yaml"
    protocol.write_text(yaml.safe_dump(data))
    out = tmp / "scan"
    args = ["simulate-scan", "--protocol", str(protocol), "--out", str(out), "--sway-mm", "3"]
    result = runner.invoke(app, [*args, "--voxel-mm", "1.0"])
    assert result.exit_code == 0, result.output
    return out


def test_recon_compensates_a_swaying_scan_and_writes_its_motion(swaying_scan, tmp_path):
    """The motion beside the volume (one row per view and body) with its QA figure; the
    truth of the simulation beside the projections."""
    out = tmp_path / "knee.nii.gz"
    grid = ["--size", "70", "70", "80", "--spacing-mm", "2", "--origin-mm", "-69", "-73", "411"]
    result = runner.invoke(
        app,
        [
            "recon",
            "--projections",
            str(swaying_scan / "projections.mha"),
            "--geometry",
            str(swaying_scan / "geometry.xml"),
            "--out",
            str(out),
            *grid,
            "--compensate-motion",
            "--times",
            str(swaying_scan / "view_times.csv"),
        ],
    )
    assert result.exit_code == 0, result.output
    assert "moved up to" in result.output
    bodies, poses = read_motion_csv(tmp_path / "knee_motion.csv")
    assert len(poses) == 90 and len(bodies) in (1, 2)
    assert (tmp_path / "knee_motion.png").stat().st_size > 10_000
    true_bodies, _ = read_motion_csv(swaying_scan / "true_motion.csv")
    assert true_bodies == ("shank", "thigh")


def test_recon_refuses_a_scan_too_short_for_motion_and_writes_nothing(scan_folder, tmp_path):
    """The tiny scan's 40 views: refused (exit 2) naming the views and the limit; --times
    alone is refused too."""
    stack = read_projections(scan_folder / "projections.mha")
    geometry = read_rtk_geometry(scan_folder / "geometry.xml", stack.header)
    write_projections(tmp_path / "p.mha", stack.data[:40], geometry[0].pitch_u_mm)
    write_rtk_geometry(tmp_path / "g.xml", geometry[:40])
    out = tmp_path / "v.nii.gz"
    base = [
        "recon",
        "--projections",
        str(tmp_path / "p.mha"),
        "--geometry",
        str(tmp_path / "g.xml"),
    ]
    result = runner.invoke(app, [*base, "--out", str(out), "--compensate-motion"])
    assert result.exit_code == 2, result.output
    assert "40 views" in result.output and "at least 60" in result.output
    assert not out.exists() and not (tmp_path / "v_motion.csv").exists()
    result = runner.invoke(app, [*base, "--out", str(out), "--times", str(tmp_path / "t.csv")])
    assert result.exit_code == 2 and "--times is for --compensate-motion" in result.output


def test_recon_by_tv_from_every_second_view(scan_folder, tmp_path):
    """--method tv --views-every 2 reconstructs 30 of the 60 views by OS-SART + TV, says how
    the iterations went, and titles its preview by the method."""
    out = tmp_path / "tv.mha"
    result = runner.invoke(
        app,
        recon_args(
            scan_folder / "projections.mha",
            scan_folder / "geometry.xml",
            out,
            "--spacing-mm",
            "4.0",
            "--method",
            "tv",
            "--iterations",
            "2",
            "--views-every",
            "2",
        ),
    )
    assert result.exit_code == 0, result.output
    assert "TV: 2 iteration(s), TV weight" in result.output
    assert read_volume(out).data.max() > 0.01  # a knee, not an empty box
