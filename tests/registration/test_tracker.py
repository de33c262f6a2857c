"""Tests of registration.drr and registration.tracker on the small matched knee case
(conftest.py). Sub-voxel means TRE below the case's 1 mm voxel. The random starts (and the
case's motion and noise) follow the ``seed`` option; accuracy figures go through
``measured``."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter, map_coordinates
from scipy.spatial.transform import Rotation

import registration
from recon.geometry import DetectorSpec, Geometry
from recon.project import JosephProjector, forward_project
from recon.volume import Volume, VolumeGrid
from registration.drr import SoftTissue, along_axis, bone_models, scene, soft_tissue_level
from registration.metrics import pose_error
from registration.objective import OutOfView
from registration.priors import patellofemoral_deviation, predict
from registration.se3 import compose
from registration.search import at_once
from registration.segment import BONE_UNITS
from registration.settings import Settings
from registration.tracker import Tracker
from sim.fluoro import add_fluoro_noise, biplane_views
from sim.motion import squat_motion
from sim.phantoms.knee import KneePhantomSpec

BONES = tuple(BONE_UNITS)  # the static scan's bones, the bodies tracked

VOXEL_MM = 1.0
SETTINGS = Settings(pyramid_mm=(3.84, 1.92), de_popsize=8, de_maxiter=15, powell_maxfev=250)


def _start(truth: dict, models, shift: float, seed: int = 0, least: float = 0.0) -> dict:
    """Each body's pose moved by up to ``shift`` per axis (mm, deg) and at least ``least``
    (the same draw for every ``least``, stretched away from zero)."""
    rng = np.random.default_rng(seed)
    starts = {}
    for b, T in truth.items():
        x = rng.uniform(-shift, shift, 6)
        starts[b] = compose(
            np.sign(x) * (least + np.abs(x) * (1.0 - least / shift)), T, models[b].centroid_mm
        )
    return starts


def test_pooled_volume_keeps_the_line_integrals(knee_case, measured) -> None:
    c = knee_case
    models, view, truth = c.models, c.view, c.truth
    femur = models["femur"]
    fine = femur.render(view, truth[0]["femur"])
    coarse = femur.render(view, truth[0]["femur"], coarse=True)
    # 2x2x2 means conserve attenuation: the projected total agrees to the resampling error
    measured("pooled_total_rel_error", abs(coarse.sum() - fine.sum()) / fine.sum(), below=0.01)
    mean_error = np.abs(coarse - fine).mean() / fine[fine > 0.02].mean()
    measured("pooled_mean_abs_error_rel", mean_error, below=0.05)


def test_rendering_a_moved_bone_equals_projecting_the_moved_volume(knee_case, measured) -> None:
    c = knee_case
    volume, labels, models, view = c.volume, c.labels, c.models, c.view
    T = compose(np.array([4.0, -3.0, 6.0, 0.0, 0.0, 0.0]), np.eye(4), np.zeros(3))
    rendered = models["patella"].render(view, T)
    # the patella's excess attenuation on the whole grid, the grid shifted by T
    mask = np.isin(labels.data, BONE_UNITS["patella"])
    excess = np.where(mask, volume.data - soft_tissue_level(volume, labels), 0.0)
    moved = VolumeGrid(
        labels.grid.shape,
        labels.grid.spacing_mm,
        tuple(np.asarray(labels.grid.origin_mm) + T[:3, 3]),
    )
    expected = forward_project(excess.astype(np.float32), moved, Geometry([view]))[0]
    assert expected.max() > 0.3  # ~25 mm of patella at ~0.02 /mm over soft tissue
    # the fine level samples every other slice along the ray (each the mean of two): rays
    # within 7 degrees of the axis move their samples by < 0.1 voxel across, which changes
    # the line integrals by < 2 % of the peak at the sharpest edges and far less on average
    difference = np.abs(rendered - expected) / expected.max()
    measured("moved_drr_max_error_rel", difference.max(), below=0.02)
    measured("moved_drr_mean_error_rel", difference.mean(), below=1e-3)


def test_soft_tissue_bends_with_the_knee_and_moves_rigidly_with_the_leg(
    knee_case, measured
) -> None:
    c = knee_case
    soft, view = c.soft, c.view
    rest = {b: np.eye(4) for b in BONES}
    data, w, grid = soft.deformed(np.eye(4), np.eye(4))
    # at the static scan's pose the lattice is the scan's and nothing moves
    assert grid == soft.grid and np.array_equal(data, soft.data)
    assert w.min() == 0.0 and w.max() == 1.0  # the tibia's below, the femur's above
    assert w[0].max() == 0.0 and w[-1].min() == 1.0  # slices are z-major, bottom first
    # both bones moved alike: the leg moves rigidly, as one rigid volume would
    T = compose(np.array([3.0, -2.0, 5.0, 4.0, -3.0, 2.0]), np.eye(4), soft.joint_mm)
    moved = soft.render(view, {**rest, "femur": T, "tibia_fibula": T})
    rigid = forward_project(soft.data, soft.grid, Geometry([view.transformed(np.linalg.inv(T))]))
    inside = rigid[0] > 0.1 * rigid.max()
    # trilinear resampling of the 2 mm lattice blurs edges by under a voxel
    rigid_error = np.abs(moved - rigid[0])[inside].mean() / rigid.max()
    measured("rigid_soft_mean_error_rel", rigid_error, below=0.01)
    # bending the knee: what each bone carries and what stays add up to the deformed tissue
    bent = {**rest, "femur": c.truth[-1]["femur"], "tibia_fibula": c.truth[-1]["tibia_fibula"]}
    deformed = soft.deformed(bent["femur"], bent["tibia_fibula"], view)
    # every voxel is the scan trilinearly interpolated (scipy) at the blend of its pull-backs
    x, y, z = np.meshgrid(*deformed[2].axes_mm(), indexing="ij")
    points = np.stack((x, y, z), axis=-1).transpose(2, 1, 0, 3)  # (z, y, x, 3) like the data
    pulled = [
        (points - T[:3, 3]) @ T[:3, :3] for T in (bent["tibia_fibula"], bent["femur"])
    ]  # inv(T) p
    share = deformed[1][..., None]
    blend = (1.0 - share) * pulled[0] + share * pulled[1]
    index = (blend - soft.grid.origin_mm) / soft.grid.spacing_mm
    expected = map_coordinates(
        soft.data, list(index[..., ::-1].transpose(3, 0, 1, 2)), order=1, mode="grid-constant"
    )
    trilinear_error = np.abs(deformed[0] - expected).max() / soft.data.max()
    measured("deformed_vs_scipy_max_error_rel", trilinear_error, below=1e-4)
    # what each bone carries (its share, averaged over pairs of slices along the rays) and
    # what stays render as the projectors of numpy's products do, to the bit
    data, w, lattice = deformed
    rays = Geometry([view])
    for name, share in (("femur", w), ("tibia_fibula", 1.0 - w)):
        for axis in range(3):  # the rays' main axis is x here; pairs along any axis
            stays, carried = soft.split(deformed, name, axis)
            expected = along_axis(data * share, lattice, axis).project(rays)
            assert np.array_equal(carried.project(rays), expected), (name, axis)
        expected = JosephProjector(data * (1.0 - share), lattice).project(rays)
        assert np.array_equal(stays.project(rays), expected), name
    stays, carried = soft.split(deformed, "patella", 0)
    assert carried is None
    assert np.array_equal(stays.project(rays), JosephProjector(data, lattice).project(rays))
    # the field cut keeps every ray's integral
    whole = soft.deformed(bent["femur"], bent["tibia_fibula"])
    full = forward_project(whole[0], whole[2], Geometry([view]))[0]
    measured(
        "scene_vs_projector_max_error", np.abs(scene(view, {}, bent, soft) - full).max(), below=1e-4
    )


@pytest.fixture(scope="module")
def first_frame(knee_case, seed) -> tuple[Tracker, dict, object]:
    """The lateral view's first frame registered from starts 1.5-3 mm and deg off the truth
    per axis (a uniform draw within 3 put seed 2's patella 1.3 mm off): the tracker, the starts
    and the frame's result."""
    c = knee_case
    tracker = Tracker(c.view, c.frames[:1], c.models, SETTINGS, c.soft)
    start = _start(c.truth[0], c.models, 3.0, seed, least=1.5)
    return tracker, start, tracker.register(0, start, [])


def test_known_pose_round_trip_reaches_sub_voxel_tre(knee_case, first_frame, measured) -> None:
    c = knee_case
    models, view, truth = c.models, c.view, c.truth
    tracker, start, result = first_frame
    tre, ncc = {}, {}
    for name, bone in result.bodies.items():
        error = pose_error(name, 0, bone.T_world_body, truth[0][name], models[name].points_mm, view)
        start_error = pose_error(name, 0, start[name], truth[0][name], models[name].points_mm, view)
        assert start_error.tre_mm > 2.0
        assert not bone.failed, (name, bone.reason)
        tre[name], ncc[name] = error.tre_mm, bone.ncc
    measured("tre_mm", max(tre.values()), below=VOXEL_MM)
    measured("ncc_shortfall", 1.0 - min(ncc.values()), below=0.1)
    # the frames are the DRRs' own renderer: no blur beyond a third of a pixel matches better
    # (at most 0.5 mm, a value of the blur grid: the bound is inclusive)
    blur = max(max(blur) for blur in tracker.frame_blur_mm.values())
    measured("frame_blur_mm", blur, below=np.nextafter(0.5, 1.0))


def test_kpm_prediction_beats_the_previous_pose_on_smooth_motion(knee_case, seed, measured) -> None:
    models, view = knee_case.models, knee_case.view
    motion = squat_motion(KneePhantomSpec(), frames=30, seed=1 + seed)
    ratio = {}
    for name in BONES:
        poses = motion.poses[name]
        points = models[name].points_mm
        stay = [
            pose_error(name, k, poses[k - 1], poses[k], points, view).tre_mm for k in range(2, 30)
        ]
        kpm = [
            pose_error(
                name,
                k,
                predict(poses[k - 2], poses[k - 1], models[name].centroid_mm),
                poses[k],
                points,
                view,
            ).tre_mm
            for k in range(2, 30)
        ]
        # half-cosine flexion ramps of ~13 frames: staying errs by the velocity (f' dt), the
        # constant-velocity prediction by the acceleration (f'' dt^2); on average their ratio
        # is pi dt / T = pi / 13 = 0.24
        ratio[name] = np.mean(kpm) / np.mean(stay)
    measured("kpm_to_stay_tre_ratio", max(ratio.values()), below=0.4)


def test_tracking_follows_a_sequence(knee_case, seed, measured) -> None:
    c = knee_case
    models, soft, view, truth, frames = c.models, c.soft, c.view, c.truth, c.frames
    tracker = Tracker(view, frames[:4], models, SETTINGS, soft)
    results = tracker.track(_start(truth[0], models, 2.0, seed))
    in_plane, tre = [], {"patella": [], "long_bones": []}
    for r in results:
        for name, bone in r.bodies.items():
            error = pose_error(
                name, r.frame, bone.T_world_body, truth[r.frame][name], models[name].points_mm, view
            )
            # depth (along the ray) is ~20x less constrained than in-plane position: 1 mm of
            # depth rescales the image by 1/800, moving the 45 mm patella's edges by 0.03 mm
            # (0.02 px here), so its depth is held to 3 mm and the long bones' TRE to the RSR
            # success threshold
            in_plane.append(error.in_plane_mm)
            tre["patella" if name == "patella" else "long_bones"].append(error.tre_mm)
    measured("in_plane_mm", max(in_plane), below=0.5 * VOXEL_MM)
    measured("tre_mm_patella", max(tre["patella"]), below=3.0)
    measured("tre_mm_long_bones", max(tre["long_bones"]), below=1.5)


def test_a_bone_leaving_the_field_is_flagged_not_guessed(knee_case) -> None:
    c = knee_case
    models, soft, view, truth, frames = c.models, c.soft, c.view, c.truth, c.frames
    away = {b: T.copy() for b, T in truth[0].items()}
    away["patella"][:3, 3] += np.array([0.0, 0.0, 400.0])  # far above the panel
    tracker = Tracker(
        view, frames[:1], models, Settings(pyramid_mm=(3.84, 1.92), global_init=False), soft
    )
    result = tracker.register(0, away, [])
    patella = result.bodies["patella"]
    assert patella.failed and "field of view" in patella.reason
    assert np.isnan(patella.ncc)


def test_bad_models_are_refused(knee_case) -> None:
    volume, labels = knee_case.volume, knee_case.labels
    with pytest.raises(ValueError, match="does not match"):
        bone_models(
            volume,
            Volume(
                labels.data[:-1],
                VolumeGrid((219, 90, 90), (1.0, 1.0, 1.0), labels.grid.origin_mm),
                "label",
            ),
        )
    no_bone = Volume(
        np.where(labels.data > 1, 1, labels.data).astype(labels.data.dtype), labels.grid, "label"
    )
    with pytest.raises(ValueError, match="missing from the labels"):
        bone_models(volume, no_bone)


def test_patellofemoral_deviation_counts_only_out_of_plane_motion() -> None:
    """Medial-lateral axis x at the static scan: flexing the patella about any line along the
    femur's own x and sliding it in the femur's sagittal plane deviate nothing, however the
    femur has turned and leaned in the world; a shift along the femur's x and a tilt about
    its anterior-posterior axis are counted in full."""
    axis, center = np.array([1.0, 0.0, 0.0]), np.array([0.0, -40.0, 520.0])
    femur = compose(np.array([3.0, -2.0, 5.0, 20.0, 4.0, -6.0]), np.eye(4), np.zeros(3))
    about_tea = compose(np.array([0.0, 0.0, 0.0, 60.0, 0.0, 0.0]), np.eye(4), [0, 0, 500.0])
    slid = compose(np.array([0.0, 6.0, -4.0, 0.0, 0.0, 0.0]), np.eye(4), center)
    flexed = femur @ slid @ about_tea
    assert patellofemoral_deviation(femur, flexed, center, axis) == pytest.approx(
        (0.0, 0.0), abs=1e-9
    )
    shifted = femur @ compose(np.array([2.5, 0.0, 0.0, 0.0, 0.0, 0.0]), np.eye(4), center)
    tilted = femur @ compose(np.array([0.0, 0.0, 0.0, 0.0, 4.0, 0.0]), np.eye(4), center)
    assert patellofemoral_deviation(femur, shifted, center, axis) == pytest.approx((2.5, 0.0))
    assert patellofemoral_deviation(femur, tilted, center, axis) == pytest.approx((0.0, 4.0))


def test_resolution_matching_recovers_the_scan_blur_and_removes_its_depth_bias(
    knee_case, measured
) -> None:
    """Bones from a scan blurred by a 3D Gaussian of sigma s render the sharp bones' DRRs
    blurred by s x magnification (a Gaussian projects to a Gaussian): the first frame's
    estimate must find that blur, and matching it must shrink the femur's depth error the
    mismatch causes (a blurrier model fits a rescaled bone better). Measured over frames 0, 4
    and 8 (each registered cold from the truth): femur 1.2 mm unmatched, 0.25 mm matched. The
    tibia is left out: in this small box, cut 110 mm below the joint, it keeps 1-1.7 mm of
    depth error either way (the box's truncation, not the blur)."""
    c = knee_case
    sigma_mm = 1.2
    blurred = Volume(gaussian_filter(c.volume.data, sigma_mm), c.volume.grid, "1/mm")
    models = bone_models(blurred, c.labels)
    soft = SoftTissue.of(blurred, c.labels)
    femur = models["femur"]
    depth, blur_error = {}, []
    for blur in ((0.0, 0.0), None):
        settings = SETTINGS.model_copy(update={"global_init": False, "frame_blur_mm": blur})
        errors = []
        for k in (0, 4, 8):
            tracker = Tracker(c.view, c.frames[k : k + 1], models, settings, soft)
            pose = tracker.register(0, c.truth[k], []).bodies["femur"].T_world_body
            error = pose_error("femur", k, pose, c.truth[k]["femur"], femur.points_mm, c.view)
            errors.append(abs(error.dof[0]))
        depth[blur] = float(np.mean(errors))
        if blur is None:
            for name in ("femur", "tibia_fibula"):
                magnification = 1.0 / float(c.view.depth(models[name].centroid_mm)[0])
                # the parabola through the best three of a 0.5 mm grid, under quantum noise;
                # both panel axes see the same isotropic blur
                found = np.asarray(tracker.frame_blur_mm[name])
                blur_error.append(np.abs(found - sigma_mm * magnification).max())
    measured("frame_blur_error_mm", max(blur_error), below=0.25)
    measured("femur_depth_error_matched_mm", depth[None], below=0.5)
    measured("femur_depth_error_unmatched_mm", depth[0.0, 0.0], above=0.5)


def test_least_squares_residual_is_one_minus_ncc_plus_the_prior(knee_case, seed) -> None:
    c = knee_case
    tracker = Tracker(c.view, c.frames[:1], c.models, SETTINGS, c.soft)
    poses = _start(c.truth[0], c.models, 1.0, seed)
    objective = tracker.scene.objective(0, tracker.levels[-1], "patella", poses)
    x = np.array([0.5, -0.3, 0.2, 1.0, -2.0, 0.3])
    T = compose(x, poses["patella"], c.models["patella"].centroid_mm)
    r = objective.residuals(x)
    assert np.sum(objective.prior(T) ** 2) > 1e-4  # the patellofemoral prior is in the sum
    assert 0.5 * r @ r == pytest.approx(1.0 + objective.cost(T), abs=1e-9)


def test_residuals_of_several_poses_are_each_poses_own(knee_case) -> None:
    """An objective's residuals at several poses at once (as a Jacobian asks for them: the
    bone's and its carried soft tissue's renders each in one call) are each pose's own to the
    bit, and so are its costs (as the KPM's line asks for them): poses whose rays run along
    different axes of the volume, and a pose beyond the source (the worst) among them."""
    c = knee_case
    tracker = Tracker(c.view, c.frames[:1], c.models, SETTINGS, c.soft)
    objective = tracker.scene.objective(0, tracker.levels[-1], "femur", dict(c.truth[0]))
    assert objective.carried is not None  # the femur carries its share of the soft tissue
    xs = np.zeros((4, 6))
    xs[1] = (0.5, -0.3, 0.2, 1.0, -2.0, 0.3)
    xs[2, 5] = 60.0  # deg: the rays run along another axis of the bone's volume
    axes = {
        int(np.argmax(np.abs((c.view.detector_center_mm - c.view.source_mm) @ T[:3, :3])))
        for T in (compose(x, objective.T0, objective.body.centroid_mm) for x in xs[:3])
    }
    assert len(axes) == 2
    many = objective.residuals_many(xs[:3])
    assert objective.evaluations == 3
    for x, r in zip(xs[:3], many, strict=True):
        assert np.array_equal(r, objective.residuals(x))
    xs[3, :3] = 3.0 * (c.view.source_mm - objective.body.centroid_mm)  # beyond the source
    many = objective.residuals_many(xs)
    assert np.array_equal(many[3], objective.residuals(xs[3]))
    assert 0.5 * many[3] @ many[3] == pytest.approx(2.0)  # NCC -1: the worst
    for x, r in zip(xs[:3], many[:3], strict=True):
        assert np.array_equal(r, objective.residuals(x))
    Ts = np.array([compose(x, objective.T0, objective.body.centroid_mm) for x in xs])
    for n in (3, 4):  # the costs likewise, without and with the pose beyond the source
        assert np.array_equal(objective.costs(Ts[:n]), [objective.cost(T) for T in Ts[:n]])
    assert objective.cost(Ts[3]) == 1.0


def test_the_long_bones_searched_at_once_land_where_each_alone_does(knee_case) -> None:
    """The first frame's global searches of the long bones run at once (a thread each, one
    numba thread each) and land each where its search alone lands, to the bit, in as many
    evaluations: renders do not depend on the threads they run on."""
    c = knee_case
    settings = SETTINGS.model_copy(update={"de_popsize": 4, "de_maxiter": 3})
    tracker = Tracker(c.view, c.frames[:1], c.models, settings, c.soft)
    poses = _start(c.truth[0], c.models, 3.0, seed=1)
    long_bones = ["tibia_fibula", "femur"]
    together = at_once(
        [tracker.scene.prepared_global_search(0, name, poses, lone=True) for name in long_bones]
    )
    for name, (pose, evaluations) in zip(long_bones, together, strict=True):
        alone = tracker.scene.global_search(0, name, poses, lone=True)
        assert np.array_equal(pose, alone[0])
        # a Sobol start of the power of two from popsize x 6 (32), scored at each generation
        assert evaluations == alone[1] == 32 * (3 + 1)


def test_least_squares_refinement_reaches_the_derivative_free_optimum_with_fewer_renders(
    knee_case, seed, measured
) -> None:
    """From a start off by up to 1 mm / 1 deg per axis (a KPM prediction's error), the two
    Levenberg-Marquardt passes end as close to the truth as Powell + Nelder-Mead, on at most half
    the renders (0.27 to 0.31 of them over seeds 0-2)."""
    c = knee_case
    tracker = Tracker(c.view, c.frames, c.models, SETTINGS, c.soft)
    start = _start(c.truth[2], c.models, 1.0, seed=5 + seed)
    in_plane, excess, renders, scores = [], [], [], []
    for name in BONES:
        poses = {**c.truth[2], name: start[name]}
        pose, n, _ = tracker.scene.least_squares(2, name, poses, tracker.levels[:-1])
        pose, m, objective = tracker.scene.least_squares(
            2, name, {**poses, name: pose}, tracker.levels[-1:]
        )
        derivative_free, k = tracker.scene.refine(2, name, poses)
        k += tracker.scene.refine(2, name, {**poses, name: derivative_free}, 0.4, polish=True)[1]

        def tre(T, name=name):
            return pose_error(name, 2, T, c.truth[2][name], c.models[name].points_mm, c.view)

        assert tre(start[name]).tre_mm > 0.5
        in_plane.append(tre(pose).in_plane_mm)
        # depth is ~20x less constrained than in-plane position (see the tracking test)
        excess.append(tre(pose).tre_mm - tre(derivative_free).tre_mm)
        renders.append((n + m) / k)
        scores.append(objective.scores(pose)[0])
    measured("in_plane_mm", max(in_plane), below=0.5 * VOXEL_MM)
    measured("tre_mm_over_derivative_free", max(excess), below=0.25 * VOXEL_MM)
    measured("render_fraction", max(renders), below=0.5)
    measured("ncc_shortfall", 1.0 - min(scores), below=0.1)


def test_a_second_camera_resolves_the_depth_one_leaves_open(
    knee_case, first_frame, seed, measured
) -> None:
    """The first frame tracked from the lateral view alone and with the anterior-posterior
    view beside it (sim.fluoro.biplane_views, 90 degrees apart), from the same starts 3 mm
    off. Along the lateral ray, the depth single-plane tracking resolves worst, the two views
    put every body within the two-camera issue's 0.2 mm and at least 3x closer than one view
    does (over seeds 0-2 and 1-2 threads: 0.003-0.005 mm, 1/115 to 1/45 of one view's)."""
    c = knee_case
    lateral, ap = biplane_views(
        KneePhantomSpec(), DetectorSpec(rows=160, cols=160, pixel_pitch_mm=1.92)
    )
    np.testing.assert_allclose(lateral.matrix, c.view.matrix)
    clean = scene(ap, c.models, c.truth[0], c.soft)[None]
    ap_frames = add_fluoro_noise(clean, 2.0e5, np.random.default_rng(4 + seed))[1]
    _, start, one = first_frame
    both = Tracker([c.view, ap], [c.frames[:1], ap_frames], c.models, SETTINGS, c.soft)
    two = both.register(0, start, [])

    def depth(result) -> float:
        return max(
            pose_error(
                b, 0, r.T_world_body, c.truth[0][b], c.models[b].points_mm, c.view
            ).out_of_plane_mm
            for b, r in result.bodies.items()
        )

    assert not any(r.failed for r in two.bodies.values())
    measured("biplane_depth_mm", depth(two), below=0.2)
    measured("biplane_depth_over_single", depth(two) / depth(one), below=1.0 / 3.0)


def test_two_cameras_refine_in_fewer_least_squares_steps(knee_case, seed, measured) -> None:
    """From the same starts as the single-view least-squares test (1 mm / 1 deg off per axis),
    the lateral and the anterior-posterior view together take ls_max_steps_views (2 steps a
    level, each render both views'): every bone ends within a quarter voxel of the truth, and
    its depth, the axis one view leaves loose, at least 3x closer on average than the lateral
    view alone with its ls_max_steps (seeds 0-2, 1-2 threads: largest TRE 0.015-0.052 mm, mean
    depth 0.07-0.15 of one view's)."""
    c = knee_case
    ap = biplane_views(KneePhantomSpec(), DetectorSpec(rows=160, cols=160, pixel_pitch_mm=1.92))[1]
    clean = np.stack([scene(ap, c.models, c.truth[k], c.soft) for k in range(3)])
    ap_frames = add_fluoro_noise(clean, 2.0e5, np.random.default_rng(4 + seed))[1]
    settings = SETTINGS.model_copy(update={"ls_max_steps_views": (2, 2)})
    one = Tracker(c.view, c.frames[:3], c.models, settings, c.soft)
    both = Tracker([c.view, ap], [c.frames[:3], ap_frames], c.models, settings, c.soft)
    start = _start(c.truth[2], c.models, 1.0, seed=5 + seed)
    tre, depth, per_level = [], {"one": [], "both": []}, []
    for name in BONES:
        poses = {**c.truth[2], name: start[name]}
        for key, tracker in (("one", one), ("both", both)):
            pose, n, _ = tracker.scene.least_squares(2, name, poses, tracker.levels)
            error = pose_error(name, 2, pose, c.truth[2][name], c.models[name].points_mm, c.view)
            depth[key].append(error.out_of_plane_mm)
            if key == "both":
                tre.append(error.tre_mm)
                per_level.append(n / len(tracker.levels))
    # the coarse level's Broyden: the start, its Jacobian (12 renders of both views), the 2
    # steps, the last Jacobian and its step; the finest's MINPACK: 2 residuals, 2 Jacobians
    assert max(per_level) <= 1 + 12 + 2 + 12 + 1
    measured("tre_mm_two_cameras", max(tre), below=0.25 * VOXEL_MM)
    ratio = np.mean(depth["both"]) / np.mean(depth["one"])
    measured("depth_two_cameras_over_one", ratio, below=1 / 3)


def test_views_of_other_counts_or_pitches_are_refused(knee_case) -> None:
    c = knee_case
    ap = biplane_views(KneePhantomSpec(), DetectorSpec(rows=80, cols=80, pixel_pitch_mm=3.84))[1]
    with pytest.raises(ValueError, match="2 views, 1 frame stacks"):
        Tracker([c.view, ap], [c.frames], c.models, SETTINGS, c.soft)
    with pytest.raises(ValueError, match="view 2 has 1 frames, view 1 has 2"):
        Tracker([c.view, ap], [c.frames[:2], c.frames[:1, :80, :80]], c.models, SETTINGS)
    with pytest.raises(ValueError, match="view 2's pyramid"):
        Tracker([c.view, ap], [c.frames[:1], c.frames[:1, :80, :80]], c.models, SETTINGS)
    with pytest.raises(ValueError, match="1 frame stacks for 2 views"):
        registration.track([c.frames[:1]], [c.view, ap], c.models, start=c.truth[0])
    with pytest.raises(ValueError, match="angle_deg must be in"):
        biplane_views(KneePhantomSpec(), DetectorSpec(rows=80, cols=80, pixel_pitch_mm=3.84), 10.0)


def test_a_camera_without_a_frame_at_a_time_point_is_left_out_there(knee_case) -> None:
    """The AP camera's second frame dropped (NaN): the femur's objective there is the lateral
    view's alone, on the first frame both views'; no frame anywhere: out of view."""
    c = knee_case
    ap = biplane_views(KneePhantomSpec(), DetectorSpec(rows=160, cols=160, pixel_pitch_mm=1.92))[1]
    ap_frames = np.stack([scene(ap, c.models, c.truth[k], c.soft) for k in range(2)])
    ap_frames[1] = np.nan
    tracker = Tracker([c.view, ap], [c.frames[:2], ap_frames], c.models, SETTINGS, c.soft)
    level = tracker.levels[0]
    for frame, views in ((0, 2), (1, 1)):
        tracker.scene.start_frame(frame, {})
        objective = tracker.scene.objective(frame, level, "femur", c.truth[frame])
        assert len(objective.views) == views
        assert objective.scores(c.truth[frame]["femur"])[0] > 0.9
    blank = np.full_like(c.frames[:1], np.nan)
    lost = Tracker([c.view, ap], [blank, blank], c.models, SETTINGS, c.soft)
    lost.scene.start_frame(0, {})
    with pytest.raises(OutOfView, match="no camera's frame 0 holds an image"):
        lost.scene.objective(0, level, "femur", c.truth[0])


def test_a_body_lost_between_frames_is_found_along_its_joint(knee_case, seed, measured) -> None:
    """Frames sampled far apart: the femur flexed ~20 degrees over the tibia since the last
    frame tracked. Carried by the tibia at its last relative pose it starts ~20 degrees off;
    the scan along the screw of the femur's motion relative to the tibia in the frames before
    (registration.priors.joint_screw) starts it within the refinement's reach.

    The squat flexes the femur about an axis fixed in the tibia to within a few tenths of a
    degree, and the scan steps 3 degrees (1.5 at most from the truth: 2 mm at the femur's
    centroid, 80 mm from the knee), so the start is held to a third of the carried start's
    error and to 2.5 mm."""
    c = knee_case

    def bent(k: int) -> np.ndarray:  # the femur in the tibia's frame in frame k
        return np.linalg.inv(c.truth[k]["tibia_fibula"]) @ c.truth[k]["femur"]

    flexion = [
        np.degrees(Rotation.from_matrix((np.linalg.inv(bent(0)) @ bent(k))[:3, :3]).magnitude())
        for k in range(len(c.truth))
    ]
    far = int(np.argmax(flexion))
    assert flexion[far] > 15.0  # the case's squat reaches far enough for this test
    history = [c.truth[0], c.truth[2]]
    carried = c.truth[far]["tibia_fibula"] @ bent(2)
    poses = {**c.truth[far], "femur": carried}
    tracker = Tracker(c.view, c.frames, c.models, SETTINGS, c.soft)
    start, evaluations = tracker._along_joint(far, "femur", poses, history)
    points = c.models["femur"].points_mm

    def tre(T: np.ndarray) -> float:
        return pose_error("femur", far, T, c.truth[far]["femur"], points, c.view).tre_mm

    assert evaluations > 0 and tre(carried) > 5.0
    measured("joint_start_tre_mm", tre(start), below=min(2.5, tre(carried) / 3))
