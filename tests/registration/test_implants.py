"""Implant components as tracked bodies: meshes read and checked, voxelised with exact
partial volumes, rendered where JointTrack's reference poses put them."""

from __future__ import annotations

import importlib.util
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from recon.config import load_config
from registration.autostart import binning
from registration.implants import (
    COARSE_SHAPE_SHARE,
    OUTLINE_FACES,
    implant_model,
    ray_lengths,
)
from registration.jointtrack import camera_view, read_calibration, read_poses
from registration.meshes import MATERIALS, read_mesh, voxelize
from registration.scene import Scene
from registration.settings import Settings
from registration.tracker import Tracker

DATA = Path(__file__).resolve().parents[3] / "shared" / "data" / "tka-fluoro-jtml"
IMPLANTS = Path(__file__).resolve().parents[2] / "configs" / "registration_implants.yaml"


def test_a_sphere_voxelises_to_its_volume_and_centre():
    """Exact along z, 4 x 4 rays across each voxel: the fractions add up to the mesh's volume
    (to the sampling of the columns: 1e-4 here) and centre where it is."""
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=10.0)
    sphere.apply_translation([3.3, -2.1, 480.7])
    fraction, grid = voxelize(sphere, 0.25)
    assert 0.0 <= fraction.min() and fraction.max() <= 1.0
    volume = fraction.sum() * 0.25**3
    assert volume == pytest.approx(sphere.volume, rel=1e-4)
    x, y, z = grid.axes_mm()
    centre = [
        (fraction.sum(axis=(0, 1)) * x).sum(),
        (fraction.sum(axis=(0, 2)) * y).sum(),
        (fraction.sum(axis=(1, 2)) * z).sum(),
    ] / fraction.sum()
    np.testing.assert_allclose(centre, [3.3, -2.1, 480.7], atol=0.01)


def test_a_mesh_in_another_unit_or_open_beyond_repair_is_refused(tmp_path):
    """Units checked; one missing face closed, a fin of no volume removed, a flat hole capped
    to the volume of the closed solid, a round one capped; open edges that are no loops
    refused."""
    box = trimesh.creation.box(extents=(0.06, 0.05, 0.07))  # metres, as OpenSim's meshes
    box.export(tmp_path / "box.stl")
    with pytest.raises(ValueError, match=r"0.07 mm across.*give its unit"):
        read_mesh(tmp_path / "box.stl")
    mesh, report = read_mesh(tmp_path / "box.stl", unit="m")
    assert report.size_mm == pytest.approx((60.0, 50.0, 70.0)) and mesh.is_watertight
    with pytest.raises(ValueError, match="mesh unit 'furlong'"):
        read_mesh(tmp_path / "box.stl", unit="furlong")
    nicked = trimesh.creation.box(extents=(60.0, 50.0, 70.0))
    nicked.update_faces(np.arange(len(nicked.faces)) != 3)  # one triangle missing: closable
    nicked.export(tmp_path / "nicked.stl")
    mesh, report = read_mesh(tmp_path / "nicked.stl")
    assert mesh.is_watertight and report.repairs == ("closed 1 missing faces",)
    box = trimesh.creation.box(extents=(60.0, 50.0, 70.0))
    a, b = box.edges_unique[0]  # a flat fin of no volume on one of its edges (CAD exports)
    tip = len(box.vertices)
    fin = trimesh.Trimesh(
        np.vstack((box.vertices, 0.5 * (box.vertices[a] + box.vertices[b]) + 9.0)),
        np.vstack((box.faces, [[a, b, tip], [b, a, tip]])),
        process=False,
    )
    assert not fin.is_watertight
    fin.export(tmp_path / "fin.stl")
    mesh, report = read_mesh(tmp_path / "fin.stl")
    assert mesh.is_watertight and report.repairs == ("removed 1 piece(s) of no volume",)
    assert mesh.volume == pytest.approx(60.0 * 50.0 * 70.0)
    can = trimesh.creation.cylinder(radius=30.0, height=40.0, sections=48)
    cut = can.copy()
    cut.update_faces(cut.face_normals[:, 2] < 0.99)  # its top gone, as CAD exports lose one
    cut.export(tmp_path / "cut.stl")
    mesh, report = read_mesh(tmp_path / "cut.stl")  # a flat hole of 48 edges: capped flat
    assert mesh.is_watertight and report.repairs == ("capped 1 hole(s) of 48 edges",)
    assert mesh.volume == pytest.approx(can.volume, rel=1e-6)  # STL keeps float32 vertices
    dome = trimesh.creation.icosphere(subdivisions=3, radius=30.0)
    dome.update_faces(dome.triangles_center[:, 2] > -5.0)  # a cap cut off: a round hole
    dome.export(tmp_path / "dome.stl")
    mesh, report = read_mesh(tmp_path / "dome.stl")
    assert mesh.is_watertight and report.repairs[-1].startswith("capped 1 hole(s) of ")
    flap = trimesh.Trimesh(fin.vertices, fin.faces[:-1], process=False)  # one-sided: no loop
    flap.export(tmp_path / "flap.stl")
    with pytest.raises(ValueError, match="its open edges form no loops to close"):
        read_mesh(tmp_path / "flap.stl")


def test_a_radiolucent_part_is_not_tracked_alone():
    box = trimesh.creation.box(extents=(60.0, 50.0, 70.0))
    with pytest.raises(ValueError, match="UHMWPE is radiolucent"):
        implant_model("insert", box, MATERIALS["UHMWPE"])


def test_an_attached_part_adds_its_own_attenuation():
    """A tray with its insert fixed on top, seen from above: a ray through both stops
    1 - exp(-(mu_CoCr 3 + mu_UHMWPE 12)) of the beam, one through the insert alone (beyond the
    tray's edge) 1 - exp(-mu_UHMWPE 12), the chords being the boxes' heights (rays 0.6 deg
    from the axis at most: lengths within 1e-4 of them)."""
    view = camera_view(1198.0, 0.0, 0.0, 0.373, 64, 64)
    tray = trimesh.creation.box(extents=(6.0, 20.0, 3.0))
    tray.apply_translation((0.0, 0.0, -1.5))
    insert = trimesh.creation.box(extents=(20.0, 20.0, 12.0))
    insert.apply_translation((0.0, 0.0, -9.0))
    model = implant_model(
        "tibia_fibula", tray, MATERIALS["CoCr"], attached=[(insert, MATERIALS["UHMWPE"])]
    )
    T = np.eye(4)
    T[:3, 3] = (0.0, 0.0, -1000.0)
    shadow = model.render(view, T)
    mu = {m: MATERIALS[m].mu_per_mm(70.0) for m in ("CoCr", "UHMWPE")}
    both, insert_only = shadow[32, 32], shadow[32, 32 + 12]  # 12 px: 4.5 mm at the panel / 1.2
    assert both == pytest.approx(1.0 - np.exp(-(3.0 * mu["CoCr"] + 12.0 * mu["UHMWPE"])), abs=1e-4)
    assert insert_only == pytest.approx(1.0 - np.exp(-12.0 * mu["UHMWPE"]), abs=1e-4)
    points = model.points_mm  # the tray's own 1 mm voxels only: none in the insert below it
    assert len(points) > 0 and points[:, 2].min() >= -3.0 and np.abs(points[:, 0]).max() <= 3.0


def test_a_sphere_renders_its_chords_and_a_shadow_flat_inside():
    """Ray lengths through a closed mesh are its chords (a sphere: 2 sqrt(r^2 - d^2), to the
    facets' sag), and the rendered shadow of 20 mm of CoCr is flat inside."""
    view = camera_view(1198.0, 0.0, 0.0, 0.373, 128, 128)
    sphere = trimesh.creation.icosphere(subdivisions=6, radius=10.0)
    T = np.eye(4)
    T[:3, 3] = (1.3, -0.7, -1080.0)
    L = ray_lengths(view, np.asarray(sphere.vertices), np.asarray(sphere.faces), T)
    rays = view.pixel_to_world(*np.meshgrid(np.arange(128.0), np.arange(128.0))) - view.source_mm
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    along = rays @ T[:3, 3]
    miss = np.sqrt(np.maximum(np.sum(T[:3, 3] ** 2) - along**2, 0.0))
    chord = 2.0 * np.sqrt(np.maximum(100.0 - miss**2, 0.0))
    inside = miss < 9.0  # away from the rim, where a facet's sag is a fraction of the chord
    np.testing.assert_allclose(L[inside], chord[inside], atol=0.05)
    mesh = sphere.copy()
    model = implant_model("femur", mesh, MATERIALS["CoCr"])
    shadow = model.render(view, T)
    assert shadow[inside & (chord > 10.0)].min() > 0.999 and shadow.max() <= 1.0


def test_a_large_mesh_s_coarse_outline_is_its_silhouette_at_a_few_faces(seed, measured):
    """A 20,480-face torus's coarse mesh has OUTLINE_FACES faces (its volume is then within
    0.06 % of the torus's), and its silhouettes on the automatic search's 3 mm pixels are the
    full mesh's but for a few rim pixels (the decimation moves the surface by a small share of
    a pixel: measured at most 1.2 % of the silhouette's pixels over 60 poses, seeds 0-2)."""
    torus = trimesh.creation.torus(25.0, 8.0, major_sections=160, minor_sections=64)
    model = implant_model("femoral_component", torus, MATERIALS["CoCr"])
    assert len(model.coarse_mesh[1]) == OUTLINE_FACES < len(torus.faces)
    view = camera_view(1198.0, 0.0, 0.0, 0.373, 1024, 1024)
    coarse = view.binned(binning(view))
    rng = np.random.default_rng(seed)
    differ = []
    for _ in range(20):
        T = np.eye(4)
        T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
        T[:3, 3] = (*rng.uniform(-40.0, 40.0, 2), -1080.0)
        full = model.silhouette(coarse, T)
        differ.append((full ^ model.silhouette(coarse, T, outline=True)).sum() / full.sum())
    measured("outline_pixels_differing_share", max(differ), below=0.03)


def test_a_coarse_level_renders_each_part_from_its_coarse_mesh(seed, measured):
    """A 20,480-face cobalt-chrome torus with a 20,480-face polyethylene sphere attached: the
    coarse mesh keeps each part's attenuation, and its volume and area within
    COARSE_SHAPE_SHARE on as few faces as that allows from its share of OUTLINE_FACES (the
    sphere at 2,000 and 4,000 faces keeps 99.78 and 99.90 % of its volume: 8,000; the torus at
    2,000 keeps 99.71 %: 4,000), renders on the pyramid's coarse level (1.5 mm at the panel) as
    the full mesh does but for a share of its rim (measured 0.17-0.19 % of the shadow's sum at
    most over 10 poses, seeds 0-2), and the differential evolution renders it there only, never
    on the finest level (0.75 mm), and the least squares never."""
    torus = trimesh.creation.torus(25.0, 8.0, major_sections=160, minor_sections=64)
    ball = trimesh.creation.icosphere(subdivisions=5, radius=12.0)
    ball.apply_translation((0.0, 0.0, 30.0))
    cocr, pe = MATERIALS["CoCr"], MATERIALS["UHMWPE"]
    model = implant_model("femoral_component", torus, cocr, attached=[(ball, pe)])
    face_mu = model.coarse_mesh[2]
    shares = {m.name: np.sum(face_mu == m.mu_per_mm(70.0)) for m in (cocr, pe)}
    assert shares == {"CoCr": OUTLINE_FACES, "UHMWPE": 2 * OUTLINE_FACES}
    vertices, faces = model.coarse_mesh[:2]
    for part, material in ((torus, cocr), (ball, pe)):
        coarse = trimesh.Trimesh(vertices, faces[face_mu == material.mu_per_mm(70.0)])
        assert abs(coarse.volume / part.volume - 1.0) <= COARSE_SHAPE_SHARE
        assert abs(coarse.area / part.area - 1.0) <= COARSE_SHAPE_SHARE
    view = camera_view(1198.0, 0.0, 0.0, 0.375, 512, 512)
    scene = Scene(
        view,
        np.zeros((1, 512, 512), np.float32),
        {model.name: model},
        load_config(IMPLANTS, Settings),
    )
    assert [scene._coarse(level, model.name, True) for level in scene.levels] == [True, False]
    assert not any(scene._coarse(level, model.name) for level in scene.levels)
    coarse = view.binned(scene.levels[0])
    rng = np.random.default_rng(seed)
    differ = []
    for _ in range(10):
        T = np.eye(4)
        T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
        T[:3, 3] = (*rng.uniform(-20.0, 20.0, 2), -1000.0)
        full = model.render(coarse, T)
        differ.append(np.abs(model.render(coarse, T, coarse=True) - full).sum() / full.sum())
    measured("coarse_mesh_render_differing_share", max(differ), below=0.01)


@pytest.mark.skipif(not DATA.is_dir(), reason=f"the real TKA data is not at {DATA}")
def test_components_render_where_jointtracks_reference_poses_put_them():
    """The JTML masks are the reference poses' silhouettes: ours at the same poses are the
    same pixels (Dice 1 on the first and last frames), so frames, calibration and poses are
    read the way JTML wrote them."""
    import SimpleITK as sitk

    view = read_calibration(DATA / "calibration.txt", 1024, 1024)
    frames = sorted(DATA.glob("HL_V1_K1_*.tif"))
    for short, stl in (("fem", "KR_left_8_fem.stl"), ("tib", "KR_left_8_tib.stl")):
        mesh, _ = read_mesh(DATA / stl)
        poses = read_poses(DATA / f"{short}.jts")
        assert len(poses) == len(frames)
        for k in (0, len(frames) - 1):
            label = DATA / "Labels" / short / f"{frames[k].stem}_label_{short}.tif"
            mask = sitk.GetArrayFromImage(sitk.ReadImage(str(label))).reshape(1024, 1024) > 0
            silhouette = ray_lengths(view, mesh.vertices, mesh.faces, poses[k]) > 0
            assert (silhouette == mask).all(), (short, k, (silhouette != mask).sum())


def _real_tka():
    spec = importlib.util.spec_from_file_location(
        "bench_registration", Path(__file__).resolve().parents[2] / "bench" / "registration.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.real_tka


@pytest.mark.skipif(not DATA.is_dir(), reason=f"the real TKA data is not at {DATA}")
def test_real_frames_are_tracked_as_the_reference_is(seed, measured):
    """JTML's first three real frames, both components started 2 mm / 2 deg off in-plane and
    5 mm off in depth from the reference poses: every frame tracked, the in-plane difference
    from the reference below twice the issue's target (0.5 mm) and the rotation below 1.5 times
    its 1 deg (the first frames, before the KPM has a motion to follow: 0.18-0.71 mm and
    0.70-1.30 deg over seeds 0-2; the targets on all 16 frames: the slow test), and our
    outlines no farther from the frame's edges than the reference's (0.20-0.38 px nearer)."""
    entry = _real_tka()([seed], frames=3, start=(2.0, 5.0, 2.0), global_init=False)
    assert entry["registrations_failed"] == 0
    for name in ("femoral_component", "tibial_tray"):
        figures = entry[name]
        measured(f"{name}_in_plane_mm", figures["in_plane_mm_median"], below=1.0)
        measured(f"{name}_rotation_deg", figures["rotation_deg_median"], below=1.5)
        excess = figures["edge_distance_px_median"] - figures["reference_edge_distance_px_median"]
        measured(f"{name}_edge_distance_excess_px", excess, below=0.1)


@pytest.mark.slow
@pytest.mark.skipif(not DATA.is_dir(), reason=f"the real TKA data is not at {DATA}")
@pytest.mark.xfail(
    reason="the tray's in-plane difference from the reference is 0.69 mm, a steady offset along "
    "x; fitted to the frames' edges alone from the reference, the tray moves 0.47 mm along x "
    "towards ours (docs/implants.md, 'Accuracy on real frames')",
    strict=False,
)
def test_real_frames_meet_the_issues_targets_from_a_far_start(seed, measured):
    """The bench's real_tka regime, one seed: all 16 frames from a start 5 mm / 5 deg off
    in-plane and 20 mm in depth; the issue's targets against the reference."""
    entry = _real_tka()([seed])
    assert entry["registrations_failed"] == 0
    for name in ("femoral_component", "tibial_tray"):
        measured(f"{name}_in_plane_mm", entry[name]["in_plane_mm_median"], below=0.5)
        measured(f"{name}_depth_mm", entry[name]["depth_mm_median"], below=2.0)
        measured(f"{name}_rotation_deg", entry[name]["rotation_deg_median"], below=1.0)


def test_the_depth_prior_weighs_a_move_along_the_view_axis_only():
    """The depth prior's residual, against the frame before: zero at that pose and for any
    move across the beam (the depth w is linear in the point), sqrt(prior_weight) per
    ``depth_step_sigma_mm`` of move along the view's axis; nothing on the first frame, nor
    for a body it does not name."""
    view = camera_view(1198.0, 0.0, 0.0, 0.373, 64, 64)
    ball = trimesh.creation.icosphere(subdivisions=2, radius=10.0)
    model = implant_model("femur", ball, MATERIALS["CoCr"])
    settings = Settings(depth_step_sigma_mm={"femur": 4.0}, prior_weight=0.005)
    tracker = Tracker(view, np.zeros((1, 64, 64)), {"femur": model}, settings)
    assert tracker.scene.prior("femur", {}) is None  # no frame before
    before = np.eye(4)
    before[:3, 3] = (0.0, 0.0, -900.0)
    tracker.scene.before = {"femur": before}
    prior = tracker.scene.prior("femur", {"femur": before})

    def moved(offset_mm: np.ndarray) -> np.ndarray:
        T = before.copy()
        T[:3, 3] += offset_mm
        return T

    assert prior(before) == pytest.approx([0.0], abs=1e-9)
    across = np.cross(view.normal, (1.0, 0.0, 0.0))
    assert prior(moved(7.0 * across / np.linalg.norm(across))) == pytest.approx([0.0], abs=1e-9)
    step = prior(moved(8.0 * view.normal))  # two sigmas along the axis
    assert np.abs(step) == pytest.approx([2.0 * np.sqrt(0.005)], rel=1e-9)
    unnamed = Settings(depth_step_sigma_mm={"tibia_fibula": 4.0})
    other = Tracker(view, np.zeros((1, 64, 64)), {"femur": model}, unnamed)
    other.scene.before = {"femur": before}
    assert other.scene.prior("femur", {"femur": before}) is None


def test_a_tracker_matches_a_mesh_s_blur_for_itself_alone():
    """The blur matched on the first frame is the frames' own, and stays the tracker's: the
    caller's models are untouched (a bench that tracks sequence after sequence with the same
    models once started each from the blur the one before had matched)."""
    view = camera_view(1198.0, 0.0, 0.0, 0.373, 96, 96)
    box = trimesh.creation.box(extents=(12.0, 8.0, 10.0))
    model = implant_model("femur", box, MATERIALS["CoCr"])
    pose = np.eye(4)
    pose[:3, 3] = (0.0, 0.0, -900.0)
    blur_mm = 0.6
    frame = replace(model, blur_mm=blur_mm).render(view, pose)
    models = {"femur": model}
    tracker = Tracker(view, frame[None], models, Settings(pyramid_mm=(0.373,)))
    tracker.scene.match_model_blur(0, "femur", {"femur": pose})
    ncc, _ = tracker.scene.score(0, "femur", {"femur": pose})
    step = 0.15  # the candidates' spacing (resolution.MODEL_BLUR_MM); the parabola does better
    assert tracker.bodies["femur"].blur_mm == pytest.approx(blur_mm, abs=step / 2)
    assert models["femur"].blur_mm == 0.0 and models["femur"] is model
    assert ncc > 0.99


@pytest.mark.parametrize("kpm_depth", ["extrapolate", "hold"])
def test_the_kpm_holds_a_depth_error_instead_of_extrapolating_it(kpm_depth):
    """A ball moves 2 mm across the beam per frame; the last frame's estimate is 2 mm too deep.
    Extrapolating that step doubles the depth error in the next frame's KPM start, and it grows
    from frame to frame so (a tray lost in swing); held, the start keeps the last frame's
    depth, and the in-plane motion is extrapolated either way (the ball's centre projects
    within 0.1 mm at the panel of where it truly is)."""
    view = camera_view(1198.0, 0.0, 0.0, 0.373, 96, 96)
    ball = trimesh.creation.icosphere(subdivisions=3, radius=10.0)
    model = implant_model("femur", ball, MATERIALS["CoCr"])
    across = np.cross(view.normal, (0.0, 1.0, 0.0))
    across /= np.linalg.norm(across)
    truth = [np.eye(4) for _ in range(3)]
    for k, T in enumerate(truth):
        T[:3, 3] = (0.0, 0.0, -900.0) + 2.0 * k * across
    frames = np.stack([model.render(view, T) for T in truth])
    history = [{"femur": truth[0]}, {"femur": truth[1].copy()}]
    history[1]["femur"][:3, 3] += 2.0 * view.normal  # too deep (or too shallow) by 2 mm
    settings = Settings(pyramid_mm=(0.746, 0.373), kpm_depth=kpm_depth)
    tracker = Tracker(view, frames, {"femur": model}, settings)
    start, _ = tracker._kpm(2, "femur", dict(history[-1]), history)
    depth_error = abs(float((start[:3, 3] - truth[2][:3, 3]) @ view.normal))
    assert depth_error == pytest.approx(4.0 if kpm_depth == "extrapolate" else 2.0, abs=0.1)
    on_panel = view.project(np.stack([start[:3, 3], truth[2][:3, 3]]))
    assert np.linalg.norm(on_panel[0] - on_panel[1]) * view.pitch_u_mm < 0.1
