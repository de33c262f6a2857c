"""``cbct register`` end to end on the small matched knee case, and its input checks. The
initial poses (and the case's motion and noise) follow the ``seed`` option."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
import yaml
from typer.testing import CliRunner

from calibration.dewarp_grid import DewarpGridSpec
from recon.attenuation import mu_water_per_mm
from recon.config import ConfigError, load_config
from recon.geometry import DetectorSpec, Geometry, View
from recon.io import write_projections, write_volume
from recon.rtk_xml import PanelHeader, write_rtk_geometry
from recon.volume import Volume, VolumeGrid
from registration.drr import scene
from registration.frames import read_frames
from registration.jointtrack import (
    camera_frame,
    camera_view,
    read_calibration,
    read_jointtrack_poses,
    write_calibration,
)
from registration.labels import BONE_UNITS
from registration.poses import BodyPose, read_poses, write_poses
from registration.se3 import compose
from registration.settings import Settings
from registration.tracking import fluoroscopy_view
from sim.fluoro import (
    DISTORTION_MAX_MM,
    add_fluoro_noise,
    biplane_views,
    distort,
    lateral_view,
    simulate_dewarp_grid,
)
from sim.phantoms.knee import KneePhantomSpec
from study.cli import app

BONES = tuple(BONE_UNITS)  # the static scan's bones, the bodies tracked

runner = CliRunner()
FRAMES = 3
SPEC = KneePhantomSpec()


@pytest.fixture(scope="module")
def inputs(knee_case, seed, tmp_path_factory):
    c = knee_case
    folder = tmp_path_factory.mktemp("register")
    paths = {
        "volume": write_volume(folder / "volume.nii.gz", c.volume),
        "labels": write_volume(folder / "labels.nii.gz", c.labels),
        "frames": write_projections(folder / "frames.mha", c.frames[:FRAMES], c.view.pitch_u_mm),
        "geometry": write_rtk_geometry(folder / "view.xml", Geometry([c.view] * FRAMES)),
    }
    centroids = {b: m.centroid_mm for b, m in c.models.items()}
    truth = [BodyPose(k, b, c.truth[k][b]) for k in range(FRAMES) for b in BONES]
    paths["truth"] = write_poses(folder / "truth.csv", truth, centroids)
    rng = np.random.default_rng(5 + seed)
    start = [  # frames 0 and 1 (a range may start at 1), each 2 mm and 2 deg off at most
        BodyPose(k, b, compose(rng.uniform(-2, 2, 6), c.truth[k][b], centroids[b]))
        for k in (0, 1)
        for b in BONES
    ]
    paths["initial"] = write_poses(folder / "initial.csv", start, centroids)
    # the tests of what cbct register reads start within 2 mm and 2 deg: no global search
    paths["near_start"] = folder / "near_start.yaml"
    paths["near_start"].write_text("global_init: false\n", encoding="utf-8")
    return folder, paths


def _args(paths, out, **override) -> list[str]:
    given = {k: paths[k] for k in ("volume", "labels", "frames", "geometry")} | override
    args = ["register", "--out", str(out)]
    for key, value in given.items():
        args += [f"--{key}", str(value)]
    return args


def test_register_writes_poses_and_metrics(inputs, measured) -> None:
    folder, paths = inputs
    out = folder / "run"
    args = _args(paths, out, truth=paths["truth"], initial=paths["initial"])
    result = runner.invoke(app, [*args, "--settings", str(paths["near_start"])])
    assert result.exit_code == 0, result.output
    poses = read_poses(out / "poses.csv")
    assert {(p.frame, p.body) for p in poses} == {(k, b) for k in range(FRAMES) for b in BONES}
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["registrations"] == FRAMES * len(BONES)
    measured("tre_mm_median", metrics["tre_mm_median"], below=1.0)  # sub-voxel, matched case
    report = json.loads((out / "registration.json").read_text())
    assert len(report["frames"]) == FRAMES * len(BONES)
    assert sorted(r["body"] for r in report["frames"]) == sorted(BONES * FRAMES)
    assert set(metrics["rsr_pct_by_body"]) == set(BONES)
    assert "TRE mean" in result.output
    again = runner.invoke(app, _args(paths, out))
    assert again.exit_code == 2 and "exists" in again.output


def test_register_takes_an_image_intensifier_fluoroscopy_as_dicom(
    inputs, knee_case, measured
) -> None:
    """The frames as a fluoroscopy unit stores them: one multi-frame XA file of 12-bit
    intensities (LIN, sign +1: bone dark), MONOCHROME2, imager pixel spacing, a circular
    image-intensifier field with black outside. They register as the line integrals do; here
    frame 1 alone (--frames-range, started from the initial poses' row for frame 1), whose
    pose keeps the sequence's frame number."""
    folder, paths = inputs
    line_integrals = knee_case.frames[:FRAMES].astype(np.float64)
    stored = 4000.0 * np.exp(-(line_integrals - line_integrals.min()))
    n = stored.shape[-1]
    v, u = np.mgrid[:n, :n] - (n - 1) / 2.0
    stored[:, np.hypot(u, v) > 0.5 * n] = 0.0  # the intensifier's round field
    image = sitk.GetImageFromArray(np.round(stored).astype(np.uint16))
    image.SetSpacing((knee_case.view.pitch_u_mm, knee_case.view.pitch_v_mm, 1.0))
    tags = {"0008|0060": "XA", "0028|0004": "MONOCHROME2", "0028|1040": "LIN", "0028|1041": "1"}
    for key, value in tags.items():
        image.SetMetaData(key, value)
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    writer.SetFileName(str(folder / "fluoro_xa.dcm"))
    writer.Execute(image)
    out = folder / "from-xa"
    given = {"frames": folder / "fluoro_xa.dcm", "truth": paths["truth"]}
    args = [*_args(paths, out, initial=paths["initial"], **given), "--frames-range", "1:1"]
    args += ["--settings", str(paths["near_start"])]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    assert {p.frame for p in read_poses(out / "poses.csv")} == {1}
    assert sorted(p.name for p in (out / "overlays").iterdir()) == ["frame_0001.png"]
    tre = json.loads((out / "metrics.json").read_text())["tre_mm_median"]
    measured("tre_mm_median", tre, below=1.0)
    report = json.loads((out / "registration.json").read_text())
    assert report["fluoroscopy"]["values"] == "-ln(value) (LIN, sign +1)"


def test_register_refuses_bad_inputs_before_work(inputs, knee_case) -> None:
    folder, paths = inputs
    out = folder / "bad"
    labels = knee_case.labels
    shorter = VolumeGrid(
        (labels.grid.shape[0] - 1, *labels.grid.shape[1:]), (1.0, 1.0, 1.0), labels.grid.origin_mm
    )
    cropped = write_volume(folder / "cropped.nii.gz", Volume(labels.data[:-1], shorter, "label"))
    two_views = write_rtk_geometry(folder / "two.xml", Geometry([knee_case.view] * 2))
    cases = {
        "labels": (cropped, "does not match"),
        "geometry": (folder / "missing.xml", "missing.xml"),
        "frames": (folder / "nothing.mha", "nothing.mha"),
    }
    for key, (value, words) in cases.items():
        result = runner.invoke(app, _args(paths, out, **{key: value}))
        assert result.exit_code == 2, (key, result.output)
        assert words in result.output, (key, result.output)
        assert not out.exists()
    result = runner.invoke(app, _args(paths, out, geometry=two_views))
    assert result.exit_code == 2 and "2 views for 3 frames" in result.output
    assert not out.exists()


def _stack_with_header(path: Path, frames: np.ndarray, pitch: float, origin, direction) -> Path:
    """Frames written by SimpleITK with the given header, as another toolkit would."""
    image = sitk.GetImageFromArray(frames.astype(np.float32))
    image.SetSpacing((pitch, pitch, 1.0))
    image.SetOrigin((*origin, 0.0))
    image.SetDirection(np.diag([*direction, 1.0]).ravel().tolist())
    sitk.WriteImage(image, str(path))
    return path


def test_the_frames_header_places_the_panel(inputs, knee_case) -> None:
    """Frames stored bottom-up (Direction diag(1, -1)) at RTK's default Origin (0, 0), with a
    geometry written for that header, give the same view of the same pixels; under the
    geometry of a centred panel the same frames are refused before any work, the header
    named."""
    folder, paths = inputs
    view, frames = knee_case.view, knee_case.frames[:FRAMES]
    pitch, rows = view.pitch_u_mm, view.rows
    flipped = _stack_with_header(
        folder / "flipped.mha", frames[:, ::-1], pitch, (0.0, 0.0), (1.0, -1.0)
    )
    header = PanelHeader(rows, view.cols, (pitch, pitch), (0.0, 0.0), ((1.0, 0.0), (0.0, -1.0)))
    bottom_up = View(
        view.source_mm,
        view.pixel_to_world(0.0, rows - 1.0),
        view.e_u,
        -view.e_v,
        pitch,
        pitch,
        rows,
        view.cols,
    )
    geometry = write_rtk_geometry(folder / "flipped.xml", Geometry([bottom_up] * FRAMES), header)
    read = read_frames(flipped)
    np.testing.assert_array_equal(read.data, frames[:, ::-1])
    seen = fluoroscopy_view(geometry, read)
    points = knee_case.models["femur"].points_mm[::500]
    expected = view.project(points) * [1, -1] + [0, rows - 1]
    np.testing.assert_allclose(seen.project(points), expected, atol=1e-9)

    out = folder / "cornered"
    result = runner.invoke(app, _args(paths, out, frames=flipped))  # the centred view.xml
    assert result.exit_code == 2
    assert "the knee of the static scan projects at pixel" in result.output
    assert "flipped.mha" in result.output and "Origin" in result.output
    assert not out.exists()


def test_register_takes_a_ct_in_hu_written_elsewhere(inputs, knee_case, measured) -> None:
    """The static scan as another scanner's NIfTI: CT numbers, no unit note. ``--unit 1/mm``
    is refused before any work; without ``--unit`` the values tell HU, the volume is converted
    at 70 keV (where the phantom's attenuation was made) and registers as the 1/mm one does;
    registration.json says so."""
    folder, paths = inputs
    volume = knee_case.volume
    water = mu_water_per_mm(70.0)
    hu = sitk.GetImageFromArray((1000.0 * (volume.data - water) / water).astype(np.float32))
    hu.SetSpacing(volume.grid.spacing_mm)
    hu.SetOrigin(volume.grid.origin_mm)
    sitk.WriteImage(hu, str(folder / "ct_hu.nii.gz"))
    wrong = folder / "wrong-unit"
    given = {"volume": folder / "ct_hu.nii.gz"}
    result = runner.invoke(app, [*_args(paths, wrong, **given), "--unit", "1/mm"])
    assert result.exit_code == 2 and "CT numbers (HU), not attenuation in 1/mm" in result.output
    assert "--unit hu" in result.output and not wrong.exists()
    out = folder / "from-hu"
    given |= {"truth": paths["truth"], "initial": paths["initial"]}
    result = runner.invoke(
        app, [*_args(paths, out, **given), "--settings", str(paths["near_start"])]
    )
    assert result.exit_code == 0, result.output
    tre = json.loads((out / "metrics.json").read_text())["tre_mm_median"]
    measured("tre_mm_median", tre, below=1.0)
    static = json.loads((out / "registration.json").read_text())["static_volume"]
    assert (static["unit"], static["unit_from"], static["effective_energy_kev"]) == (
        "HU",
        "values",
        70.0,
    )


def test_the_settings_file_holds_the_defaults_and_bad_fields_are_named(tmp_path) -> None:
    configs = Path(__file__).resolve().parents[2] / "configs"
    assert load_config(configs / "registration.yaml", Settings) == Settings()
    bad = tmp_path / "bad.yaml"
    bad.write_text("powell_maxfev: -3\n", encoding="utf-8")
    with pytest.raises(ConfigError, match="powell_maxfev"):
        load_config(bad, Settings)
    unknown = tmp_path / "unknown.yaml"
    unknown.write_text("kpm_strength: 2\n", encoding="utf-8")
    with pytest.raises(ConfigError, match="kpm_strength"):
        load_config(unknown, Settings)


def test_the_panel_distortion_is_fitted_and_removed(inputs, knee_case, seed, measured) -> None:
    """``cbct calibrate-fluoro`` fits the simulated panel's pincushion (0.6 mm at the corners)
    from one exposure of the grid at a finer read-out of the same panel (480 pixels of
    0.64 mm); ``cbct register --distortion`` dewarps distorted frames of the 160-pixel
    read-out and registers them to sub-voxel; a warp of another panel is refused first. The
    grid exposure's noise follows the ``seed`` option."""
    folder, paths = inputs
    view = knee_case.view
    grid = DewarpGridSpec()
    config = folder / "grid.yaml"
    config.write_text(yaml.safe_dump(grid.model_dump()), encoding="utf-8")
    fine = DetectorSpec(rows=480, cols=480, pixel_pitch_mm=view.pitch_u_mm * view.cols / 480)
    image = simulate_dewarp_grid(grid, lateral_view(SPEC, fine), seed=4 + seed)[None]
    grid_path = write_projections(folder / "grid.mha", image, fine.pixel_pitch_mm)
    warp = folder / "distortion.json"
    args = ["calibrate-fluoro", "--grid", str(grid_path), "--geometry", str(paths["geometry"])]
    args += ["--grid-config", str(config), "--out", str(warp)]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    fit = json.loads(warp.read_text())
    measured("dewarp_fit_rms_mm", fit["rms_mm"], below=0.05)
    displacement_error = abs(fit["max_displacement_mm"] - DISTORTION_MAX_MM)
    measured("dewarp_max_displacement_error_mm", displacement_error, below=0.1)
    again = runner.invoke(app, args)
    assert again.exit_code == 2 and "exists" in again.output

    distorted = distort(knee_case.frames[:FRAMES], DISTORTION_MAX_MM / view.pitch_u_mm)
    frames = write_projections(folder / "distorted.mha", distorted, view.pitch_u_mm)
    out = folder / "dewarped"
    given = {"frames": frames, "truth": paths["truth"], "initial": paths["initial"]}
    args = [*_args(paths, out, **given), "--distortion", str(warp)]
    result = runner.invoke(app, [*args, "--settings", str(paths["near_start"])])
    assert result.exit_code == 0, result.output
    tre = json.loads((out / "metrics.json").read_text())["tre_mm_median"]
    measured("tre_mm_median_dewarped", tre, below=1.0)
    report = json.loads((out / "registration.json").read_text())
    assert report["dewarp"]["balls"] == fit["balls"] and (out / "distortion.json").exists()

    other = {**fit, "width_mm": 2 * fit["width_mm"]}
    (folder / "other.json").write_text(json.dumps(other), encoding="utf-8")
    bad = folder / "bad-warp"
    result = runner.invoke(app, [*_args(paths, bad), "--distortion", str(folder / "other.json")])
    assert result.exit_code == 2 and "do not match the distortion's panel" in result.output
    assert not bad.exists()


@pytest.fixture(scope="module")
def second_camera(inputs, knee_case, seed):
    """The anterior-posterior camera beside the lateral one (sim.fluoro.biplane_views, 90
    degrees about the plateau's vertical), its frames of the same motion: (frames, geometry)."""
    c = knee_case
    folder, _ = inputs
    ap = biplane_views(SPEC, DetectorSpec(rows=160, cols=160, pixel_pitch_mm=1.92))[1]
    clean = np.stack([scene(ap, c.models, c.truth[k], c.soft) for k in range(FRAMES)])
    frames = add_fluoro_noise(clean, 2.0e5, np.random.default_rng(4 + seed))[1]
    return (
        write_projections(folder / "ap.mha", frames, ap.pitch_u_mm),
        write_rtk_geometry(folder / "ap.xml", Geometry([ap] * FRAMES)),
    )


def test_two_cameras_register_every_body_on_both_and_write_each_cameras_files(
    inputs, second_camera, measured
) -> None:
    """--frames and --geometry once per camera: every body's pose scored on both views, its
    depth along the first (lateral) camera's rays within the two-camera issue's 0.2 mm median
    (a voxel is 1 mm); per camera its JointTrack poses in its own camera frame and its
    overlays; an Autoscoper .tra per body in the world."""
    folder, paths = inputs
    out = folder / "biplane"
    args = _args(paths, out, truth=paths["truth"], initial=paths["initial"])
    args += ["--settings", str(paths["near_start"]), "--frames-range", "0:1"]
    args += ["--frames", str(second_camera[0]), "--geometry", str(second_camera[1])]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "view<K>" in result.output
    metrics = json.loads((out / "metrics.json").read_text())
    measured("biplane_depth_mm_median", metrics["out_of_plane_mm_median"], below=0.2)
    assert metrics["rsr_pct"] == 100.0
    poses = {(p.frame, p.body): p.T_world_body for p in read_poses(out / "poses.csv")}
    ap = fluoroscopy_view(second_camera[1], read_frames(second_camera[0]))
    for k, view in ((1, None), (2, ap)):
        assert sorted(p.name for p in (out / f"view{k}" / "overlays").iterdir()) == [
            "frame_0000.png",
            "frame_0001.png",
        ]
        if view is not None:
            in_world = read_jointtrack_poses(out / f"view{k}" / "femur.jts", view)
            for frame in (0, 1):
                np.testing.assert_allclose(in_world[frame], poses[frame, "femur"], atol=1e-4)
    assert sorted(p.name for p in out.glob("*.tra")) == [f"{b}.tra" for b in sorted(BONES)]
    both = sitk.GetArrayFromImage(sitk.ReadImage(str(out / "overlays" / "frame_0001.png")))
    assert both.shape == (160, 2 * 160 + 4, 3)  # the two cameras' side by side, for the report
    report = json.loads((out / "registration.json").read_text())
    assert [c["source"] for c in report["cameras"]][1].endswith("ap.mha")


def _as_jointtrack(view: View, frames: Path, folder: Path, name: str) -> tuple[Path, ...]:
    """``view`` and its ``frames`` as a JointTrack camera (mirrored left to right where the
    view's panel faces the other way: JointTrack's images look down -z): its frames, its
    calibration in its camera frame and that frame's pose in the world (``T_world_camera``,
    a text file)."""
    images = read_frames(frames)
    T = camera_frame(view)
    if (view.transformed(np.linalg.inv(T)).detector_origin_mm[2]) > 0:
        far_column = view.detector_origin_mm + (view.cols - 1) * view.pitch_u_mm * view.e_u
        view = replace(view, detector_origin_mm=far_column, e_u=-view.e_u)
        images = replace(images, data=images.data[:, :, ::-1])
        T = camera_frame(view)
    pitch = view.pitch_u_mm
    stack = write_projections(folder / f"{name}.mha", np.ascontiguousarray(images.data), pitch)
    calibration = write_calibration(folder / f"{name}.txt", view.transformed(np.linalg.inv(T)))
    np.savetxt(folder / f"{name}_pose.txt", T)
    return stack, calibration, folder / f"{name}_pose.txt"


def test_jointtrack_cameras_placed_by_their_poses_track_in_one_world(
    inputs, second_camera, knee_case, tmp_path, measured
) -> None:
    """Two JointTrack calibrations, each with its camera's pose (--camera-pose), are the two
    views in one world: the first frame's depth along the lateral camera's rays within the
    two-camera issue's 0.2 mm median, and each camera's .jts in its own camera frame."""
    _, paths = inputs
    ap = fluoroscopy_view(second_camera[1], read_frames(second_camera[0]))
    lateral = _as_jointtrack(knee_case.view, paths["frames"], tmp_path, "lateral")
    front = _as_jointtrack(ap, second_camera[0], tmp_path, "ap")
    out = tmp_path / "jointtrack"
    args = ["register", "--out", str(out), "--volume", str(paths["volume"])]
    # near the start and the frames' blur given, one short pass: a misplaced camera costs mm
    settings = tmp_path / "settings.yaml"
    fields = ["global_init: false", "frame_blur_mm: [0.4, 0.4]", "nelder_mead_maxfev: 30"]
    settings.write_text("\n".join([*fields, "powell_xtol: 0.2"]) + "\n", encoding="utf-8")
    args += ["--labels", str(paths["labels"]), "--settings", str(settings)]
    args += ["--truth", str(paths["truth"]), "--initial", str(paths["initial"])]
    args += ["--frames-range", "0:0"]
    for frames, calibration, pose in (lateral, front):
        args += ["--frames", str(frames), "--calibration", str(calibration)]
        args += ["--camera-pose", str(pose)]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    metrics = json.loads((out / "metrics.json").read_text())
    measured("jointtrack_biplane_depth_mm_median", metrics["out_of_plane_mm_median"], below=0.2)
    assert metrics["rsr_pct"] == 100.0
    poses = {p.body: p.T_world_body for p in read_poses(out / "poses.csv")}
    _, calibration, pose = front
    placed = read_calibration(calibration, ap.rows, ap.cols).transformed(np.loadtxt(pose))
    in_world = read_jointtrack_poses(out / "view2" / "femur.jts", placed)
    np.testing.assert_allclose(in_world[0], poses["femur"], atol=1e-4)


def test_cameras_that_do_not_pair_or_share_no_world_are_refused_before_work(
    inputs, second_camera, knee_case, tmp_path
) -> None:
    _, paths = inputs
    frames, geometry = second_camera
    two = write_projections(tmp_path / "two.mha", read_frames(frames).data[:2], 1.92)
    calibration = write_calibration(tmp_path / "jt.txt", camera_view(1000.0, 0, 0, 1.92, 160, 160))
    far = knee_case.view.transformed(
        np.array([[1, 0, 0, 0], [0, 1, 0, 5000.0], [0, 0, 1, 0], [0, 0, 0, 1]])
    )
    away = write_rtk_geometry(tmp_path / "away.xml", Geometry([far] * FRAMES))
    base = ["register", "--volume", str(paths["volume"]), "--labels", str(paths["labels"])]
    base += ["--frames", str(paths["frames"])]
    cases = [
        (
            [
                "--geometry",
                str(paths["geometry"]),
                "--frames",
                str(two),
                "--geometry",
                str(geometry),
            ],
            "camera 1's 3, camera 2's 2): give --frames-range 0:1",
        ),
        (
            [
                "--calibration",
                str(calibration),
                "--frames",
                str(frames),
                "--calibration",
                str(calibration),
            ],
            "a JointTrack calibration places its camera in a frame of its own",
        ),
        (
            [
                "--geometry",
                str(paths["geometry"]),
                "--frames",
                str(frames),
                "--calibration",
                str(calibration),
            ],
            "not both",
        ),
        (
            [
                "--geometry",
                str(paths["geometry"]),
                "--geometry",
                str(geometry),
                "--frames",
                str(frames),
                "--frames",
                str(frames),
            ],
            "--frames given 3 times for 2 cameras",
        ),
        (
            [
                "--geometry",
                str(paths["geometry"]),
                "--frames",
                str(frames),
                "--geometry",
                str(away),
                "--initial",
                str(paths["initial"]),
            ],
            "camera 2 (",
        ),
    ]
    pose = tmp_path / "pose.txt"
    np.savetxt(pose, np.eye(4))
    sheared = tmp_path / "sheared.txt"
    np.savetxt(sheared, np.diag([1.0, 1.01, 1.0, 1.0]))
    jointtrack = ["--frames", str(frames), "--calibration", str(calibration)]
    cases += [
        (
            ["--calibration", str(calibration), *jointtrack, "--camera-pose", str(pose)],
            "--camera-pose given 1 times for 2 cameras",
        ),
        (["--geometry", str(paths["geometry"]), "--camera-pose", str(pose)], "carries its own"),
        (
            [
                "--calibration",
                str(calibration),
                "--camera-pose",
                str(pose),
                *jointtrack,
                "--camera-pose",
                str(sheared),
            ],
            "rotation is not one",
        ),
    ]
    for k, (more, said) in enumerate(cases):
        out = tmp_path / f"out{k}"
        result = runner.invoke(app, [*base, *more, "--out", str(out)], terminal_width=400)
        assert result.exit_code == 2, (more, result.output)
        assert said in result.output, (more, result.output)
        assert not out.exists()
