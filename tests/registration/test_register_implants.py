"""``cbct register --implant``: components tracked from their meshes through frames rendered
from the same meshes at known poses, the view from a JointTrack calibration, TIFF frames; its
JointTrack poses, overlays, and the refusals of bad input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
import trimesh
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from registration.implants import implant_model
from registration.jointtrack import camera_view, read_poses, write_calibration, write_poses
from registration.meshes import MATERIALS
from registration.poses import read_poses as read_csv
from study.cli import app

runner = CliRunner()
FRAMES = 3
ROWS = COLS = 384
PITCH = 0.373  # a 1024-pixel 0.373 mm panel, cropped to the knee
DISTANCE = 1198.0
DEPTH_MM = {"femur": 2.0, "tibia": 5.0}
"""Depth bound of each component: twice what half a pixel of its silhouette's size resolves."""


def arc_band(r_in: float, r_out: float, span_deg: float, height: float, n: int = 64):
    """A C-shaped prism (a band of an annulus over ``span_deg``, extruded along z), closed."""
    angles = np.radians(np.linspace(-span_deg / 2, span_deg / 2, n))
    rings = [(r_out, -height / 2), (r_in, -height / 2), (r_in, height / 2), (r_out, height / 2)]
    vertices = np.array(
        [(r * np.cos(a), r * np.sin(a), z) for r, z in rings for a in angles], dtype=float
    )
    faces = []
    for j in range(4):  # the four walls: outer bottom -> inner bottom -> inner top -> outer top
        a, b = j * n, ((j + 1) % 4) * n
        for i in range(n - 1):
            faces += [(a + i, b + i, a + i + 1), (a + i + 1, b + i, b + i + 1)]
    for i in (0, n - 1):  # the two ends
        quad = [j * n + i for j in range(4)]
        faces += [(quad[0], quad[1], quad[2]), (quad[0], quad[2], quad[3])]
    mesh = trimesh.Trimesh(vertices, faces, process=True)
    trimesh.repair.fix_normals(mesh)
    return mesh


def component(kind: str) -> trimesh.Trimesh:
    """A femoral-component-like C (a thick arc) or a tray-like T (a plate on a keel), mm."""
    if kind == "femur":
        return arc_band(20.0, 28.0, 250.0, 60.0)
    plate = trimesh.creation.box(extents=(70.0, 4.0, 50.0))
    keel = trimesh.creation.cylinder(radius=6.0, height=40.0)
    keel.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (1, 0, 0)))
    keel.apply_translation((8.0, -22.0, 0.0))  # under the plate, off its centre
    return trimesh.util.concatenate([plate, keel])


def poses(rng: np.random.Generator, base: tuple[float, float, float]) -> list[np.ndarray]:
    """A small motion: each frame turned and shifted a little from the last."""
    out, T = [], np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", rng.uniform(-20, 20, 3), degrees=True).as_matrix()
    T[:3, 3] = base
    for _ in range(FRAMES):
        out.append(T.copy())
        step = np.eye(4)
        step[:3, :3] = Rotation.from_rotvec(np.radians(rng.uniform(-2, 2, 3))).as_matrix()
        T = T @ step
        T[:3, 3] += rng.uniform(-1, 1, 3)
    return out


@pytest.fixture(scope="module")
def case(tmp_path_factory, seed):
    """Two components' meshes, their true poses in the camera frame, TIFF frames rendered
    with them (8 bit, implants dark, quantum-like noise), the calibration."""
    folder = tmp_path_factory.mktemp("implants")
    rng = np.random.default_rng(10 + seed)
    view = camera_view(DISTANCE, 0.0, 0.0, PITCH, ROWS, COLS)
    write_calibration(folder / "calibration.txt", view)
    truth, models = {}, {}
    for name, base in (("femur", (10.0, 25.0, -1080.0)), ("tibia", (-5.0, -30.0, -1085.0))):
        mesh = component(name)
        mesh.export(folder / f"{name}.stl")
        models[name] = implant_model(name, mesh, MATERIALS["CoCr"])
        truth[name] = poses(rng, base)
        write_poses(folder / f"{name}_true.jts", truth[name])
    (folder / "frames").mkdir()
    for k in range(FRAMES):
        shadow = sum(models[b].render(view, truth[b][k]) for b in models)
        intensity = 200.0 * (1.0 - np.clip(shadow, 0.0, 1.0)) + 40.0
        noisy = rng.poisson(intensity).clip(0, 255).astype(np.uint8)
        sitk.WriteImage(sitk.GetImageFromArray(noisy), str(folder / "frames" / f"f_{k:02d}.tif"))
    return folder, truth


def _args(folder: Path, out: Path, *extra: str) -> list[str]:
    return [
        "register",
        "--frames",
        str(folder / "frames"),
        "--view-file",
        str(folder / "calibration.txt"),
        "--implant",
        f"femur={folder / 'femur.stl'}",
        "--implant",
        f"tibia={folder / 'tibia.stl'}",
        "--out",
        str(out),
        *extra,
    ]


def test_components_are_tracked_and_handed_on_as_jointtrack_poses(case, measured):
    """Started 2 mm / 2 deg off in the image plane and 8 mm in depth, each component ends
    within 0.2 mm of its true pose in the image plane in every frame, and in depth within what
    its size resolves: a width W at distance Z from the source grows by W / Z on the image per
    mm of depth (x 1.1 magnification, over 0.373 mm pixels: 0.25 px/mm for the 56 mm C, 0.19
    px/mm for the 70 mm tray), so half a pixel of silhouette is 2 mm (C) and 2.6 mm (tray):
    bounds of 2 and 5 mm (measured over seeds 0-2 with the implant settings, the default for
    implants alone: in-plane 0.03 mm at most, depth 0.19 mm (C) and 0.93 mm (tray) at most).
    femur.jts and tibia.jts hold the poses in the calibration's camera frame; an overlay per
    frame."""
    folder, truth = case
    start = {}
    for name in truth:
        T = truth[name][0].copy()
        T[:3, :3] = Rotation.from_rotvec(np.radians([2.0, -2.0, 2.0])).as_matrix() @ T[:3, :3]
        T[:3, 3] += (2.0, -2.0, 8.0)
        start[name] = write_poses(folder / f"{name}_start.jts", [T])
    out = folder / "run"
    initial = [f"--initial={b}={p}" for b, p in start.items()]
    result = runner.invoke(app, _args(folder, out, *initial))
    assert result.exit_code == 0, result.output
    assert "femur.jts, tibia.jts" in result.output
    for name in truth:
        ours = read_poses(out / f"{name}.jts")
        assert len(ours) == FRAMES
        for k in range(FRAMES):
            d = ours[k][:3, 3] - truth[name][k][:3, 3]
            measured(f"{name}_in_plane_mm", float(np.hypot(d[0], d[1])), below=0.2)
            measured(f"{name}_depth_mm", abs(float(d[2])), below=DEPTH_MM[name])
    assert sorted(p.name for p in (out / "overlays").iterdir()) == [
        f"frame_{k:04d}.png" for k in range(FRAMES)
    ]
    names = {p.body for p in read_csv(out / "poses.csv")}  # each plays the bone it replaces
    assert names == {"femoral_component", "tibial_tray"}


def test_bad_input_is_refused_before_any_work(case, tmp_path):
    folder, truth = case
    short = write_poses(tmp_path / "short.jts", truth["femur"][:1])
    given = ["--truth", f"femur={short}", "--truth", f"tibia={folder / 'tibia_true.jts'}"]
    result = runner.invoke(app, _args(folder, tmp_path / "a", *given))
    assert (
        result.exit_code == 2
        and "true poses of femoral_component for 1 frames, not 3" in result.output
    )
    wrong = tmp_path / "calibration.txt"
    wrong.write_text("JT_INTCALIB\n1198\n0\n0\n0.373\n")
    args = _args(folder, tmp_path / "b")
    args[args.index("--view-file") + 1] = str(wrong)
    result = runner.invoke(app, [*args, "--pixel-pitch-mm", "0.75"])
    assert result.exit_code == 2 and "pixel size 0.373 mm, the frames'" in result.output
    args[args.index("--view-file")] = "--calibration"  # JointTrack's word for the same file
    result = runner.invoke(app, [*args, "--pixel-pitch-mm", "0.75"])
    assert result.exit_code == 2 and "pixel size 0.373 mm, the frames'" in result.output
    result = runner.invoke(app, [*_args(folder, tmp_path / "c"), "--implant-unit", "m"])
    assert result.exit_code == 2 and "give its unit" in result.output
    result = runner.invoke(app, [*_args(folder, tmp_path / "d"), "--material", "knee=CoCr"])
    assert result.exit_code == 2 and "body 'knee': one of femur, tibia, patella" in result.output
    result = runner.invoke(app, [*_args(folder, tmp_path / "e"), "--attach", "tibia=a.stl:steel"])
    assert result.exit_code == 2 and "give BODY=MESH:MATERIAL, MATERIAL one of" in result.output
    result = runner.invoke(app, [*_args(folder, tmp_path / "f"), "--attach", "patella=b.stl:bone"])
    assert result.exit_code == 2 and "patella has no --implant" in result.output
    lost = tmp_path / "lost.stl"
    result = runner.invoke(app, [*_args(folder, tmp_path / "g"), "--attach", f"tibia={lost}:bone"])
    assert result.exit_code == 2 and "lost.stl: no such mesh file" in result.output
    assert not any((tmp_path / x).exists() for x in "abcdefg")
