"""The report's 3D view and its synchronised player, on the phantom knee flexing: the scene's
points where the assessment measured them, and the page in headless Chromium (offline, the
3D canvas drawn and moving with the frames, the plots' markers following)."""

from __future__ import annotations

import html
import json
import re
import subprocess

import matplotlib.image
import numpy as np
import pytest

from assessment.knee import assess_knee
from assessment.plots import PLOTS
from assessment.report import frame_overlays, write_report
from assessment.series import bone_mesh
from assessment.viewer import MAX_FACES, motion_scene, scene_json
from recon.volume import Volume, VolumeGrid
from registration.labels import BONE_LABELS
from registration.poses import BodyPose
from sim.motion import flexion_extension
from sim.phantoms.knee import KneePhantomSpec, rasterize_knee

FRAMES = 9
BONES = ("femur", "tibia_fibula", "patella")


def _knee(side: str):
    """The phantom knee (2 mm labels) flexing 0 -> 80 -> 0 deg over FRAMES frames: its
    assessment, motion and meshes."""
    spec = KneePhantomSpec(side=side)
    grid = VolumeGrid.centered((70, 70, 160), 2.0, (0.0, -4.0, 490.0))
    labels = Volume(rasterize_knee(spec, grid, supersample=1)[0], grid, "label")
    motion = flexion_extension(spec, frames=FRAMES, max_flexion_deg=80.0)
    poses = {b: motion.poses["tibia" if b == "tibia_fibula" else b] for b in BONES}
    listed = [BodyPose(int(f), b, poses[b][i]) for i, f in enumerate(motion.frames) for b in BONES]
    assessment = assess_knee(labels, listed, side)
    meshes = {b: bone_mesh(labels, BONE_LABELS[b]) for b in BONES}
    return assessment, np.asarray(motion.frames), poses, meshes, listed


@pytest.fixture(scope="module", params=["right", "left"])
def knee(request):
    return _knee(request.param)


def test_the_condyle_points_lie_on_the_femur_at_the_measured_distance_from_the_plane(knee):
    """Each frame's lowest medial and lateral points: the femur's own condyle points carried by
    its pose (the left knee's mirrored back), at the assessment's distance from the TP plane
    carried by the tibia's (both to 1e-6 mm: the same algebra, undone)."""
    assessment, frames, poses, meshes, _ = knee
    scene = motion_scene(assessment, frames, poses, meshes)
    kin, femur = assessment.kinematics, assessment.femur
    mirror = np.diag([-1.0, 1.0, 1.0]) if kin.side == "left" else np.eye(3)
    for j, (condyle, distance) in enumerate(
        (
            (femur.medial_condyle_mm, kin.medial_distance_mm),
            (femur.lateral_condyle_mm, kin.lateral_distance_mm),
        )
    ):
        on_femur = condyle @ mirror.T  # the static femur's points, in the world
        for k in range(len(frames)):
            T_f, T_t = poses["femur"][k], poses["tibia_fibula"][k]
            back = np.linalg.solve(T_f[:3, :3], scene.condyles[k, j] - T_f[:3, 3])
            assert np.min(np.linalg.norm(on_femur - back, axis=1)) < 1e-6
            corners = scene.plane @ T_t[:3, :3].T + T_t[:3, 3]
            normal = np.cross(corners[1] - corners[0], corners[3] - corners[0])
            normal /= np.linalg.norm(normal)
            normal *= np.sign(normal @ T_t[:3, 2])  # proximal, as the assessment's
            gap = (scene.condyles[k, j] - corners[0]) @ normal
            assert gap == pytest.approx(distance[k], abs=1e-6)
    for vertices, faces in scene.meshes.values():
        assert len(faces) <= MAX_FACES and faces.max() < len(vertices)
    payload = json.loads(scene_json(scene))
    assert len(payload["bodies"]) == 3 and len(payload["bodies"][0]["poses"]) == FRAMES


def test_the_report_plays_the_knee_in_3d_offline(tmp_path, browse, render_report, artefacts):
    """The right knee's report with overlays and the 3D view, opened by Chromium at frame 0 and
    at the deepest flexion: no request leaves the file (the same net-log check catches a page
    that makes one); the canvas is drawn, and differs between the frames where the femur moved;
    the caption and every plot's marker follow the frame. Screenshots kept in ``artefacts``."""
    assessment, frames, poses, meshes, listed = _knee("right")
    kin = assessment.kinematics
    overlays = tmp_path / "overlays"
    overlays.mkdir()
    for frame in frames:
        image = np.full((16, 16, 3), 0.2 + 0.6 * frame / FRAMES)
        matplotlib.image.imsave(overlays / f"frame_{frame:04d}.png", image)
    written = write_report(
        kin,
        tmp_path / "report",
        title="3D",
        overlays=frame_overlays(overlays, kin, listed),
        scene=motion_scene(assessment, frames, poses, meshes),
    )
    page = written["report"]
    assert page.stat().st_size < 3e6
    figure = matplotlib.image.imread(written["frames_beside_4d"])
    assert figure[figure.shape[0] // 2 :, :, :3].std() > 0.05  # the 4D row is drawn
    deepest = int(np.argmax(kin.flexion_deg))
    pages = {k: browse(page, f"frame={frames[k]}&probe") for k in (0, deepest)}
    leak = tmp_path / "leak.html"
    leak.write_text('<img src="http://127.0.0.1:9/x.png">', encoding="utf-8")
    assert browse(leak).requests == ["http://127.0.0.1:9/x.png"]  # the check sees a request

    canvases = {}
    for k, shown in pages.items():
        assert shown.requests == []
        assert f'data-view3d-frame="{k}"' in shown.dom  # the view drew this frame
        caption = re.search(r'<span id="motion-caption">([^<]*)</span>', shown.dom).group(1)
        assert html.unescape(caption).startswith(f"frame {frames[k]}: NCC")
        canvases[k] = shown.canvas()
        assert canvases[k].std() > 0.05  # bones on a white ground, not blank
        matplotlib.image.imsave(artefacts / f"report_3d_frame_{frames[k]}.png", canvases[k])
        marks = re.findall(r'class="marker"[^>]*style="left: ([\d.]+)%', shown.dom)
        expected = [100 * xy[k][0] for p in PLOTS.values() for xy in p(kin).markers]
        np.testing.assert_allclose([float(v) for v in marks], expected, atol=0.0051)  # 1e-4
    changed = np.abs(canvases[0] - canvases[deepest]).max(axis=2) > 0.1
    assert changed.mean() > 0.02  # the femur flexed 80 degrees
    rows = np.nonzero(changed.any(axis=1))[0]
    assert rows.min() < canvases[0].shape[0] // 2  # above the joint: the femur, not the tibia
    subprocess.run(
        [
            render_report.find_chromium(),
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--enable-unsafe-swiftshader",
            f"--user-data-dir={tmp_path / 'chromium-profile'}",
            "--window-size=1400,1600",
            "--virtual-time-budget=4000",
            f"--screenshot={artefacts / 'report_page.png'}",
            f"{page.as_uri()}#frame={frames[deepest]}",
        ],
        capture_output=True,
        timeout=120,
        check=True,
    )
    assert (artefacts / "report_page.png").stat().st_size > 10_000
