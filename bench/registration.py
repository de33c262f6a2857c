"""Benchmark: 2D-3D registration of simulated knee fluoroscopy (BoneAxis-Reg and ablations).

The regimes (docs/system.md, issue "4D virtual imaging"; docs/implants.md for the last two):

- ``matched``: the paper's setting. Bone models come from the phantom itself (its attenuation
  and labels); targets are our own scene DRRs of those models at the true poses (the same
  renderer family), with quantum and readout noise and the panel's pincushion (0.6 mm at the
  corners: 1 px at 512^2).
- ``independent``: bones segmented from the RECONSTRUCTED volume of a simulated CBCT scan of
  the phantom; targets rendered by sim.fluoro from the rasterised phantom at full detector
  resolution with beam hardening, scatter, detector blur, distortion, Poisson + readout noise
  and soft tissue that deforms non-rigidly and is displaced by the bones.

- ``cross_renderer``: data made elsewhere. Frames rendered by itk-rtk's Joseph forward
  projector (sim.fluoro's scene with RTK as its projector: every bone's excess volume through
  its moved view, the deformed soft tissue) from a 0.5 mm raster of the whole leg of a knee of
  other proportions (:data:`CROSS_SPEC`), with Poisson noise; the registered static volume is
  a 0.8 mm raster of the same knee whose box (:data:`CUT_GRID`) cuts the femur and the tibia
  90 mm from the joint line, so the frames show the bones going on past the model's cut. The
  third sequence keeps the tibia still (sim.motion.flexion_extension: the femur flexes over
  it). No panel distortion, no dewarp.

- ``real_tka``: real fluoroscopy. JTML's 16 flat-panel frames of a left knee replacement
  (``../shared/data/tka-fluoro-jtml``: 8-bit, implants dark, shutter bars), its calibration and
  the two components' meshes (CoCr); both components tracked from frame 0 started at the
  reference poses (another program's single-plane estimates) moved by up to +-5 mm / +-5 deg
  per axis in the image plane and +-20 mm in depth, one start per ``--seeds`` seed, with the
  implant settings (configs/registration_implants.yaml). Reported per component: the medians
  of the differences from the reference along the camera's axes (in-plane, depth, rotation),
  the Dice of our silhouettes with JTML's masks (which are the reference poses' own
  silhouettes: agreement with the reference, not with the image), how far the outlines sit
  from the frame's Canny edges (sigma 2 px) beside the reference poses' outlines, the frames
  tracked and the seconds per frame. With ``--edge-fit``, a third estimate: each component
  fitted to the frame's edges alone, started at the reference pose (:func:`edge_optimum`, a
  fit of JointTrack's kind), and how far it lies from the reference and from ours.
- ``biplane``: two cameras. The matched regime's bone models and image model (without the
  panel's distortion) seen by the lateral view and by a second view :data:`BIPLANE_ANGLES_DEG`
  away (sim.fluoro.biplane_views; the angle cycles over the sequences), every frame tracked
  from both views at once (registration.views; entry ``biplane``), and the same frames from
  the lateral camera alone (entry ``biplane_one_camera``), both by ``boneaxis_kpm``: in-plane
  and depth errors are along the lateral view's axes, the seconds are per time point.
- ``tka``: a simulated knee replacement with ground truth (sim.tka: the Grand Challenge
  subject's components on its bones, moved by its knee kinematics measured over gait, 5 to
  53 deg of flexion over ``--frames`` frames; lateral frames of the share of the beam stopped,
  every part and the leg's water, bent at the knee, by exact ray lengths, Poisson photons);
  the femoral component and the tray tracked with the gait settings
  (configs/registration_gait.yaml) from frame 0 started 4 mm / 4 deg off, one noise and start
  seed per sequence, the tray with its insert. Reported
  as the bone regimes (TRE, RSR, per-axis errors, in-plane and depth, over the components'
  own points), and per component.
- ``tka_bones``: the same, each component tracked with the true bones it is fixed to as well
  (sim.tka.FIXED_BONES: the femur; the tibia and the fibula): what the tracker does when the
  bones' place on the components is known exactly.
- ``tka_sparse``: the ``tka`` regime on every :data:`SPARSE_STEP`-th sample of the gait
  (11 frames over the cycle, ``--frames`` ignored): as a study sampled every 20th video frame,
  the tray moves beyond the search about its last pose in swing; ``marked_failed`` counts the
  registrations the tracker flagged, beside the RSR against the truth.
- ``biplane_tka``: the ``tka`` regime's gait seen by two cameras, the lateral one (its frames
  seed for seed) and one turned :data:`BIPLANE_ANGLES_DEG` about the vertical through the
  knee's centre (sim.tka.simulate_tka_fluoro's ``turn_deg``), tracked from both at once (entry
  ``biplane_tka``) and from the lateral camera alone (``biplane_tka_one_camera``); depth is
  along the lateral view's rays, the seconds per time point.

In the first two regimes the frames are dewarped first (calibration.dewarp_grid), with the warp
fitted to one exposure of the dewarp grid through the same image model as the frames
(``--no-dewarp`` registers the distorted frames as they are); ``dewarp_rms_mm`` is the fit's
residual.

Per regime, every method runs the same sequences (squat motions with different seeds), from the
same start perturbation of the first frame: ``boneaxis_kpm`` (PCA + differential evolution on
the first frame, KPM prediction and line search, Powell + Nelder-Mead coarse to fine),
``boneaxis`` (the same without KPM: each frame starts from the previous pose),
``powell_nelder_mead`` (no global initialisation, no KPM) and ``nelder_mead`` (Nelder-Mead
alone). The matched entries also carry ``floor_start_at_truth``: frame 0 refined from the
TRUE poses on three noise realisations, without and with the distortion, i.e. the error that
noise and uncorrected distortion alone leave. Prints one JSON object ``{"regimes": [...]}``.

Usage: ``python bench/registration.py [--sequences 3] [--frames 30] [--panel 512]
[--max-flexion 90] [--methods ...] [--regimes ...] [--ablation-sequences N] [--no-dewarp]``;
``--quick`` runs 1 sequence of 12 frames of a 40 degree squat per regime.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numba
import numpy as np
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from calibration.dewarp_grid import DewarpGridSpec, fit_distortion  # noqa: E402
from recon.config import load_config, load_protocol  # noqa: E402
from recon.distortion import Distortion  # noqa: E402
from recon.fdk import fdk_reconstruct  # noqa: E402
from recon.geometry import DetectorSpec  # noqa: E402
from recon.rtk_peer import rtk_forward_project  # noqa: E402
from recon.volume import Volume, VolumeGrid  # noqa: E402
from registration.drr import SoftTissue, bone_models, scene  # noqa: E402
from registration.frames import read_frames  # noqa: E402
from registration.implants import implant_model  # noqa: E402
from registration.jointtrack import read_calibration  # noqa: E402
from registration.jointtrack import read_poses as read_jts  # noqa: E402
from registration.meshes import MATERIALS, read_mesh  # noqa: E402
from registration.metrics import (  # noqa: E402
    camera_differences,
    edge_distances_px,
    edge_fit_px,
    pose_error,
    summarize,
)
from registration.overlays import silhouette  # noqa: E402
from registration.se3 import compose  # noqa: E402
from registration.segment import segment_bones  # noqa: E402
from registration.settings import Settings  # noqa: E402
from registration.tracker import Tracker  # noqa: E402
from sim.fluoro import (  # noqa: E402
    DISTORTION_MAX_MM,
    add_fluoro_noise,
    biplane_views,
    distort,
    lateral_view,
    simulate_dewarp_grid,
    simulate_fluoroscopy,
)
from sim.motion import flexion_extension, squat_motion  # noqa: E402
from sim.phantoms.knee import KneePhantomSpec, rasterize_knee  # noqa: E402
from sim.scan import simulate_knee_scan  # noqa: E402
from sim.tka import FIXED_BONES as TKA_FIXED_BONES  # noqa: E402
from sim.tka import TRACKED as TKA_TRACKED  # noqa: E402
from sim.tka import load_tka, part_poses, read_gait, simulate_tka_fluoro, tka_motion  # noqa: E402

METHODS = {
    "boneaxis_kpm": Settings(kpm=True, global_init=True, powell=True),
    "boneaxis": Settings(kpm=False, global_init=True, powell=True),
    "powell_nelder_mead": Settings(kpm=False, global_init=False, powell=True),
    "nelder_mead": Settings(kpm=False, global_init=False, powell=False),
}
TRACKED = ("femur", "tibia_fibula", "patella")
START_PERTURBATION = (4.0, 4.0)
"""First-frame start: the truth moved by up to this many mm and degrees per axis."""
CBCT_GRID = VolumeGrid.centered((175, 175, 400), 0.8, (0.0, 0.0, 520.0))
"""The registration's CBCT volume: the leg's whole cross-section (140 x 140 mm) and 320 mm of it
from 120 mm below the joint line, 0.8 mm voxels, like the demo's (study.stages.RECON_EXTENT_MM).
The soft tissue ends where this box does: the former 84 x 100 x 264 mm box at 0.6 mm cut the
leg and left its faces in the DRRs (one 30-frame 90-degree independent sequence: TRE mean
1.68 -> 1.23 mm, RSR 68.9 -> 76.7 % with the whole leg)."""
SIMULATION_GRID = VolumeGrid.centered((187, 187, 640), 0.75, (0.0, 0.0, 490.0))
"""The simulated scan's leg: 480 mm about the joint line, more than the cone covers."""
CROSS_SPEC = KneePhantomSpec(scale=1.08, soft_tissue_radius_mm=66.0, fat_thickness_mm=12.0)
"""The cross-renderer knee: bones 8 % larger, a thicker leg and fat layer than the others'."""
CUT_GRID = VolumeGrid.centered((175, 175, 225), 0.8, (0.0, 0.0, CROSS_SPEC.joint_line_height_mm))
"""The cross-renderer's static scan: the leg's whole cross-section, but only 90 mm above and
below the joint line, inside the lateral view's field (about +-100 mm at the knee): the box
cuts the femoral and tibial shafts and the leg in view."""
CROSS_VOXEL_MM = 0.5
"""The cross-renderer frames' raster (the registered volume's is CUT_GRID's 0.8 mm)."""


def log(msg: str) -> None:
    print(f"[bench/registration] {msg}", file=sys.stderr, flush=True)


def cbct(spec: KneePhantomSpec) -> tuple[Volume, Volume]:
    """A simulated weight-bearing CBCT scan of the phantom, reconstructed and segmented."""
    protocol = load_protocol(ROOT / "configs" / "protocols" / "knee_reverse_spiral_360.yaml")
    panel = protocol.detector.model_copy(update={"rows": 512, "cols": 512, "pixel_pitch_mm": 1.2})
    orbit = protocol.orbit.model_copy(
        update={"z_step_mm": None, "z_travel_mm": 120.0, "isocenter_mm": (0.0, 0.0, 490.0)}
    )
    protocol = protocol.model_copy(update={"detector": panel, "orbit": orbit})
    scan = simulate_knee_scan(protocol, spec, seed=7, grid=SIMULATION_GRID)
    volume = fdk_reconstruct(scan.projections, scan.geometry, CBCT_GRID).volume
    return volume, segment_bones(volume, side=spec.side)


def phantom_volumes(spec: KneePhantomSpec, grid: VolumeGrid = CBCT_GRID) -> tuple[Volume, Volume]:
    labels, mu = rasterize_knee(spec, grid, supersample=2)
    return Volume(mu, grid, "1/mm"), Volume(labels, grid, "label")


def truth_of(motion, k: int) -> dict[str, np.ndarray]:
    return {b: motion.poses[b][k] for b in TRACKED}


def perturbed(poses: dict[str, np.ndarray], models, rng) -> dict[str, np.ndarray]:
    t, r = START_PERTURBATION
    return {
        b: compose(
            np.concatenate((rng.uniform(-t, t, 3), rng.uniform(-r, r, 3))), T, models[b].centroid_mm
        )
        for b, T in poses.items()
    }


def run(method: str, view, frames, models, soft, motion, start) -> dict:
    """Track ``frames`` through ``view`` (or lists of each, one per camera: the errors along
    the first view's axes)."""
    tracker = Tracker(view, frames, models, METHODS[method], soft)
    view = tracker.view
    started = time.perf_counter()
    results = tracker.track(start)
    log(f"  {method}: {time.perf_counter() - started:.0f} s")
    errors, first, warm = [], 0.0, []
    for result in results:
        seconds = sum(r.seconds for r in result.bodies.values())
        if result.frame == 0:
            first = seconds
        else:
            warm.append(seconds)
        for bone, r in result.bodies.items():
            errors.append(
                pose_error(
                    bone,
                    result.frame,
                    r.T_world_body,
                    motion.poses[bone][result.frame],
                    models[bone].points_mm,
                    view,
                )
            )
    return {"errors": errors, "first": first, "warm": warm}


def matched_frames(clean: np.ndarray, view, photons: float, rng) -> np.ndarray:
    """The matched regime's image model: quantum and readout noise, the panel's distortion."""
    noisy = add_fluoro_noise(clean, photons, rng)[1]
    return distort(noisy, DISTORTION_MAX_MM / view.pitch_u_mm)


def dewarp_of(regime: str, spec: KneePhantomSpec) -> Distortion:
    """The panel's warp, fitted to one exposure of the dewarp grid at the panel's native pitch
    (1024 pixels of 0.3 mm) through the regime's image model (calibration.dewarp_grid)."""
    grid = DewarpGridSpec()
    native = lateral_view(spec, DetectorSpec(rows=1024, cols=1024, pixel_pitch_mm=0.3))
    if regime == "matched":
        ideal = simulate_dewarp_grid(grid, native, realism="ideal")
        photons = 2.0e4  # per 0.3 mm pixel, as the frames
        image = matched_frames(ideal, native, photons, np.random.default_rng(900))
    else:
        image = simulate_dewarp_grid(grid, native, seed=900)
    return fit_distortion(image, native, grid)


def optimum_spread(
    view, models, soft, motion, photons: float, distorted: bool, dewarp: Distortion | None
) -> dict:
    """The matched regime's floor: register frame 0 starting AT the truth (refinement only)
    on 3 noise realisations; the TRE reached measures what noise (and distortion, dewarped or
    not) alone allow."""
    truth = truth_of(motion, 0)
    clean = scene(view, models, truth, soft)[None]
    errors = []
    for seed in range(3):
        rng = np.random.default_rng(500 + seed)
        if distorted:
            frame = matched_frames(clean, view, photons, rng)
            frame = frame if dewarp is None else dewarp.undistort(frame, view.pitch_u_mm)
        else:
            frame = add_fluoro_noise(clean, photons, rng)[1]
        settings = Settings(kpm=False, global_init=False, powell=True)
        result = Tracker(view, frame, models, settings, soft).register(0, truth, [])
        errors += [
            pose_error(b, 0, r.T_world_body, truth[b], models[b].points_mm, view)
            for b, r in result.bodies.items()
        ]
    return {
        "distortion_mm": DISTORTION_MAX_MM if distorted else 0.0,
        "dewarped": dewarp is not None,
        "tre_mm": float(np.mean([e.tre_mm for e in errors])),
        "in_plane_mm_median": float(np.median([e.in_plane_mm for e in errors])),
        "out_of_plane_mm_median": float(np.median([e.out_of_plane_mm for e in errors])),
    }


def drr_ms_256(models, view) -> float:
    numba.set_num_threads(2)
    coarse = view.binned(max(1, view.cols // 256))
    femur = models["femur"]
    femur.render(coarse, np.eye(4))
    started = time.perf_counter()
    for _ in range(20):
        femur.render(coarse, np.eye(4))
    return (time.perf_counter() - started) / 20 * 1000.0


REGIMES = (
    "matched",
    "independent",
    "cross_renderer",
    "biplane",
    "real_tka",
    "tka",
    "tka_bones",
    "tka_sparse",
    "biplane_tka",
)
BIPLANE_ANGLES_DEG = (90.0, 60.0)
"""The biplane regime's angles between the two central rays, cycled over the sequences."""
GC_DATA = ROOT.parent / "shared" / "data" / "grand-challenge-tka"
TKA_CENTER_MM = np.array([0.0, 0.0, 490.0])
"""Where the simulated knee replacement's joint centre stands (the phantom knee's height)."""
TKA_PHOTONS = 2.0e4
"""Unattenuated photons per 0.6 mm pixel of the simulated TKA frames."""
SPARSE_STEP = 10
"""The ``tka_sparse`` regime takes every so many of the gait file's samples (0 to 100 % of the
cycle in 1 % steps)."""


def tka_scene(frames: int, panel: int, bones: bool = False):
    """The simulated knee replacement's gait (see the ``tka`` regime): the knee, its motion,
    the panel, the gait settings, the tracked components' models (with ``bones``, the bones
    fixed to them too) and their true poses per frame."""
    knee = load_tka(GC_DATA)
    gait = read_gait(GC_DATA / "kinematics" / "fluoroscopic_gait.sto")
    motion = tka_motion(knee, gait, frames, TKA_CENTER_MM)
    detector = DetectorSpec(rows=panel, cols=panel, pixel_pitch_mm=307.2 / panel)
    settings = load_config(ROOT / "configs" / "registration_gait.yaml", Settings)
    models = {
        body: implant_model(
            body,
            knee.meshes[body],
            knee.materials[body],
            attached=[
                (knee.meshes[p], knee.materials[p])
                for p in (*attached, *(TKA_FIXED_BONES[body] if bones else ()))
            ],
        )
        for body, attached in TKA_TRACKED.items()
    }
    truth = {body: part_poses(knee, motion, body) for body in TKA_TRACKED}
    return knee, motion, detector, settings, models, truth


def tka_errors(results, truth, models, view) -> list:
    """Every registration's error against the true poses (depth along ``view``'s rays)."""
    return [
        pose_error(
            body, res.frame, r.T_world_body, truth[body][res.frame], models[body].points_mm, view
        )
        for res in results
        for body, r in res.bodies.items()
    ]


def tka_entry(regime: str, errors: list, first: list, warm: list, models) -> dict:
    """A knee replacement regime's figures: the bone regimes' (summarize), per-axis medians and
    per component."""
    entry = {"regime": regime, **summarize(errors, warm, float(np.mean(first)))}
    dof = np.abs(np.array([e.dof for e in errors]))
    entry["per_axis_median_abs"] = {
        axis: round(float(np.median(dof[:, i])), 3)
        for i, axis in enumerate(("tx_mm", "ty_mm", "tz_mm", "rx_deg", "ry_deg", "rz_deg"))
    }
    medians = {"tre_mm": "tre_mm_median", "in_plane_mm": "in_plane_mm_median"}
    medians["out_of_plane_mm"] = "depth_mm_median"
    entry["by_component"] = {
        body: {
            key: round(float(np.median([getattr(e, field) for e in errors if e.body == body])), 3)
            for field, key in medians.items()
        }
        for body in models
    }
    return entry


def tka(sequences: int, frames: int, panel: int, bones: bool = False, sparse: bool = False) -> dict:
    """The ``tka`` regime's entry, or with ``bones`` the ``tka_bones`` one, or with ``sparse``
    the ``tka_sparse`` one (every :data:`SPARSE_STEP`-th sample of the gait, ``frames``
    ignored) (see the module docstring)."""
    regime = "tka_bones" if bones else "tka_sparse" if sparse else "tka"
    if not GC_DATA.is_dir():
        return {"regime": regime, "skipped": f"no data at {GC_DATA}"}
    if sparse:
        samples = len(read_gait(GC_DATA / "kinematics" / "fluoroscopic_gait.sto")["time"])
        frames = (samples - 1) // SPARSE_STEP + 1
    knee, motion, detector, settings, models, truth = tka_scene(frames, panel, bones)
    errors, first, warm, render_s, marked = [], [], [], [], 0
    for seq in range(sequences):
        started = time.perf_counter()
        view, images = simulate_tka_fluoro(
            knee, motion, detector, TKA_CENTER_MM, TKA_PHOTONS, seed=300 + seq, supersample=2
        )
        render_s.append((time.perf_counter() - started) / frames)
        start = perturbed({b: truth[b][0] for b in models}, models, np.random.default_rng(seq))
        log(f"tka sequence {seq}: tracking {frames} frames")
        results = Tracker(view, images, models, settings).track(start)
        first.append(sum(r.seconds for r in results[0].bodies.values()))
        warm += [sum(r.seconds for r in res.bodies.values()) for res in results[1:]]
        errors += tka_errors(results, truth, models, view)
        marked += sum(r.failed for res in results for r in res.bodies.values())
    entry = tka_entry(regime, errors, first, warm, models)
    entry |= {
        "marked_failed": marked,
        "s_per_frame_max": round(float(np.max(warm)), 2),
        "sequences": sequences,
        "frames": frames,
        "panel": panel,
        "flexion_deg": [
            round(float(motion.flexion_deg.min()), 1),
            round(float(motion.flexion_deg.max()), 1),
        ],
        "photons_per_pixel": TKA_PHOTONS,
        "s_render_per_frame": round(float(np.mean(render_s)), 2),
    }
    return entry


def biplane_tka(sequences: int, frames: int, panel: int) -> list[dict]:
    """The ``biplane_tka`` regime's two entries: the knee replacement's gait seen by the
    lateral camera (the ``tka`` regime's frames, seed for seed) and by one turned
    :data:`BIPLANE_ANGLES_DEG` from it (cycled over the sequences), tracked from both at once
    (``biplane_tka``) and from the lateral camera alone (``biplane_tka_one_camera``)."""
    names = ("biplane_tka", "biplane_tka_one_camera")
    if not GC_DATA.is_dir():
        return [{"regime": name, "skipped": f"no data at {GC_DATA}"} for name in names]
    knee, motion, detector, settings, models, truth = tka_scene(frames, panel)
    runs = {name: {"errors": [], "first": [], "warm": []} for name in names}
    angles = []
    for seq in range(sequences):
        angle = BIPLANE_ANGLES_DEG[seq % len(BIPLANE_ANGLES_DEG)]
        angles.append(angle)
        log(f"biplane_tka sequence {seq}: {frames} frames in two views {angle:g} deg apart")
        views, stacks = [], []
        for k, turn in enumerate((0.0, angle)):
            view, images = simulate_tka_fluoro(
                knee,
                motion,
                detector,
                TKA_CENTER_MM,
                TKA_PHOTONS,
                seed=300 + seq + 1000 * k,
                supersample=2,
                turn_deg=turn,
            )
            views.append(view)
            stacks.append(images)
        start = perturbed({b: truth[b][0] for b in models}, models, np.random.default_rng(seq))
        for name, (view, stack) in zip(
            names, ((views, stacks), (views[0], stacks[0])), strict=True
        ):
            results = Tracker(view, stack, models, settings).track(start)
            runs[name]["first"].append(sum(r.seconds for r in results[0].bodies.values()))
            runs[name]["warm"] += [
                sum(r.seconds for r in res.bodies.values()) for res in results[1:]
            ]
            runs[name]["errors"] += tka_errors(results, truth, models, views[0])
    entries = []
    for name, data in runs.items():
        entry = tka_entry(name, data["errors"], data["first"], data["warm"], models)
        entry |= {"angles_deg": angles, "sequences": sequences, "frames": frames, "panel": panel}
        entries.append(entry)
        log(f"{name}: {json.dumps(entry)}")
    return entries


TKA_DATA = ROOT.parent / "shared" / "data" / "tka-fluoro-jtml"
TKA_COMPONENTS = {
    "femoral_component": ("KR_left_8_fem.stl", "fem"),
    "tibial_tray": ("KR_left_8_tib.stl", "tib"),
}
"""The JTML components: the tracked body -> (mesh, JTML's short name)."""


def edge_optimum(
    distances_px: np.ndarray | None, model, view, T: np.ndarray, maxfev: int = 300
) -> tuple[np.ndarray, float]:
    """Where a frame's edges alone put a component started at pose ``T`` (4x4, mm): the pose
    whose outline lies nearest, on average, the frame's edges (:func:`edge_fit_px` with the
    frame's ``distances_px``), by Nelder-Mead over a move (mm) and a turn about the centroid
    (deg). Returns the pose and its mean outline distance (px)."""

    def mean_distance(x: np.ndarray) -> float:
        fit = edge_fit_px(distances_px, silhouette(model, view, compose(x, T, model.centroid_mm)))
        return math.inf if math.isnan(fit) else fit

    x0 = np.zeros(6)
    steps = np.diag([0.5, 0.5, 3.0, 0.5, 0.5, 0.5])  # the view's axis is z: depth moves more
    best = minimize(
        mean_distance,
        x0,
        method="Nelder-Mead",
        options={
            "maxfev": maxfev,
            "initial_simplex": np.vstack((x0, x0 + steps)),
            "xatol": 0.02,
            "fatol": 1e-4,
        },
    )
    return compose(best.x, T, model.centroid_mm), float(best.fun)


def real_tka(
    seeds: list[int],
    settings: Settings | None = None,
    supersample: int = 3,
    frames: int | None = None,
    start: tuple[float, float, float] = (5.0, 20.0, 5.0),
    global_init: bool = True,
    edge_fit: bool = False,
) -> dict:
    """The ``real_tka`` regime's entry (see the module docstring); ``settings`` default to
    configs/registration_implants.yaml, ``supersample``: the components' rays per pixel per
    axis (registration.implants.ImplantModel); ``frames``: the first so many (all: None);
    ``start``: the largest start offsets in-plane (mm), in depth (mm) and about each axis
    (deg); ``global_init`` False: the first frame refined only (a start near the answer);
    ``edge_fit``: each component also fitted to the frames' edges from the reference
    (:func:`edge_optimum`)."""
    if not TKA_DATA.is_dir():
        return {"regime": "real_tka", "skipped": f"no data at {TKA_DATA}"}
    import SimpleITK as sitk

    files = sorted(TKA_DATA.glob("HL_V1_K1_*.tif"))[:frames]
    calibration = TKA_DATA / "calibration.txt"
    pitch = read_calibration(calibration, 1, 1).pitch_u_mm
    stack = read_frames(str(TKA_DATA / "HL_V1_K1_*.tif"), pitch)
    stack = replace(stack, data=stack.data[: len(files)])
    view = read_calibration(calibration, *stack.data.shape[1:])
    if settings is None:
        settings = load_config(ROOT / "configs" / "registration_implants.yaml", Settings)
    settings = settings.model_copy(update={"global_init": global_init})
    models, reference, masks = {}, {}, {}
    for name, (stl, short) in TKA_COMPONENTS.items():
        mesh, _ = read_mesh(TKA_DATA / stl)
        models[name] = implant_model(name, mesh, MATERIALS["CoCr"], supersample=supersample)
        reference[name] = read_jts(TKA_DATA / f"{short}.jts")
        masks[name] = [
            sitk.GetArrayFromImage(
                sitk.ReadImage(str(TKA_DATA / "Labels" / short / f"{f.stem}_label_{short}.tif"))
            ).reshape(stack.data.shape[1:])
            > 0
            for f in files
        ]
    images = [
        sitk.GetArrayFromImage(sitk.ReadImage(str(f))).reshape(stack.data.shape[1:]) for f in files
    ]
    distances = [edge_distances_px(image) for image in images]  # to each frame's edges
    reference_fit = {
        name: [
            edge_fit_px(distances[k], silhouette(models[name], view, reference[name][k]))
            for k in range(len(files))
        ]
        for name in models
    }
    camera = np.eye(4)  # the calibration's view is in JointTrack's camera frame
    edge_poses: dict[str, list[tuple[np.ndarray, float]]] = {}
    if edge_fit:
        log("real_tka: each component fitted to the frames' edges from the reference")
        edge_poses = {
            name: [
                edge_optimum(distances[k], models[name], view, reference[name][k])
                for k in range(len(files))
            ]
            for name in models
        }
    rows = {name: [] for name in models}
    ours_to_edges = {name: [] for name in models}
    seconds, first, failed = [], [], 0
    for seed in seeds:
        rng = np.random.default_rng(seed)
        starts = {}
        for name, model in models.items():
            mm, depth, deg = start
            shift = rng.uniform(-1.0, 1.0, 6) * (mm, mm, depth, deg, deg, deg)
            T = np.eye(4)
            T[:3, :3] = Rotation.from_rotvec(np.radians(shift[3:])).as_matrix()
            c = reference[name][0][:3, :3] @ model.centroid_mm + reference[name][0][:3, 3]
            T[:3, 3] = c + shift[:3] - T[:3, :3] @ c  # turned about the centroid, then moved
            starts[name] = T @ reference[name][0]
        log(f"real_tka seed {seed}: tracking {len(files)} frames")
        results = Tracker(view, stack.data, models, settings, None, stack.field).track(starts)
        first.append(sum(b.seconds for b in results[0].bodies.values()))
        seconds += [sum(b.seconds for b in r.bodies.values()) for r in results[1:]]
        for r in results:
            for name, bone in r.bodies.items():
                failed += bone.failed
                k = r.frame
                d = camera_differences(
                    bone.T_world_body, reference[name][k], models[name].centroid_mm, camera
                )
                ours = silhouette(models[name], view, bone.T_world_body)
                mask = masks[name][k]
                dice = 2.0 * (ours & mask).sum() / (ours.sum() + mask.sum())
                rows[name].append(
                    (*d, dice, edge_fit_px(distances[k], ours), reference_fit[name][k])
                )
                if edge_poses:
                    ours_to_edges[name].append(
                        camera_differences(
                            bone.T_world_body,
                            edge_poses[name][k][0],
                            models[name].centroid_mm,
                            camera,
                        )
                    )
    entry = {"regime": "real_tka", "seeds": seeds, "frames": len(files), "start": list(start)}
    for name, data in rows.items():
        a = np.array(data)
        entry[name] = {
            "in_plane_mm_median": round(float(np.median(np.hypot(a[:, 0], a[:, 1]))), 3),
            "depth_mm_median": round(float(np.median(np.abs(a[:, 2]))), 3),
            "rotation_deg_median": round(float(np.median(np.linalg.norm(a[:, 3:6], axis=1))), 3),
            "per_axis_median_abs": {
                axis: round(float(np.median(np.abs(a[:, i]))), 3)
                for i, axis in enumerate(("x_mm", "y_mm", "z_mm", "rx_deg", "ry_deg", "rz_deg"))
            },
            "depth_mm_median_signed": round(float(np.median(a[:, 2])), 3),
            "dice_with_masks_median": round(float(np.median(a[:, 6])), 4),
            "dice_with_masks_min": round(float(a[:, 6].min()), 4),
            "edge_distance_px_median": round(float(np.median(a[:, 7])), 3),
            "reference_edge_distance_px_median": round(float(np.median(a[:, 8])), 3),
        }
        if edge_poses:
            fits = edge_poses[name]
            e = np.array(
                [
                    camera_differences(T, reference[name][k], models[name].centroid_mm, camera)
                    for k, (T, _) in enumerate(fits)
                ]
            )
            o = np.array(ours_to_edges[name])
            entry[name]["edge_fit"] = {
                "minus_reference_x_mm_median": round(float(np.median(e[:, 0])), 3),
                "minus_reference_y_mm_median": round(float(np.median(e[:, 1])), 3),
                "reference_in_plane_mm_median": round(
                    float(np.median(np.hypot(e[:, 0], e[:, 1]))), 3
                ),
                "ours_in_plane_mm_median": round(float(np.median(np.hypot(o[:, 0], o[:, 1]))), 3),
                "ours_minus_x_mm_median": round(float(np.median(o[:, 0])), 3),
                "edge_distance_px_median": round(float(np.median([f for _, f in fits])), 3),
            }
    entry["registrations_failed"] = int(failed)
    entry["s_per_frame"] = round(float(np.mean(seconds)), 3)
    entry["s_first_frame"] = round(float(np.mean(first)), 3)
    entry["settings"] = settings.model_dump()
    return entry


def biplane(
    sequences: int, frames: int, flexion: float, detector: DetectorSpec, photons: float
) -> list[dict]:
    """The biplane regime's two entries: both cameras, and the lateral one alone."""
    spec = KneePhantomSpec()
    volume, labels = phantom_volumes(spec)
    models, soft = bone_models(volume, labels), SoftTissue.of(volume, labels)
    runs = {
        name: {"errors": [], "first": [], "warm": []} for name in ("biplane", "biplane_one_camera")
    }
    angles = []
    for seq in range(sequences):
        angle = BIPLANE_ANGLES_DEG[seq % len(BIPLANE_ANGLES_DEG)]
        angles.append(angle)
        views = biplane_views(spec, detector, angle)
        motion = squat_motion(spec, frames=frames, max_flexion_deg=flexion, seed=seq)
        log(f"regime biplane, sequence {seq}: {frames} frames in two views {angle:g} deg apart")
        stacks = []
        for k, view in enumerate(views):
            clean = np.stack(
                [scene(view, models, truth_of(motion, i), soft) for i in range(frames)]
            )
            rng = np.random.default_rng(100 + 10 * seq + k)
            stacks.append(add_fluoro_noise(clean, photons, rng)[1])
        start = perturbed(truth_of(motion, 0), models, np.random.default_rng(seq))
        for name, (view, stack) in (
            ("biplane", (list(views), stacks)),
            ("biplane_one_camera", (views[0], stacks[0])),
        ):
            out = run("boneaxis_kpm", view, stack, models, soft, motion, start)
            runs[name]["errors"] += out["errors"]
            runs[name]["first"].append(out["first"])
            runs[name]["warm"] += out["warm"]
    entries = []
    for name, data in runs.items():
        entry = {"regime": name, "method": "boneaxis_kpm", "angles_deg": angles}
        entry |= summarize(data["errors"], data["warm"], float(np.mean(data["first"])))
        entry |= {"sequences": sequences, "frames": frames}
        entries.append(entry)
        log(f"{name}: {json.dumps(entry)}")
    return entries


def static_scan(regime: str) -> tuple[KneePhantomSpec, Volume, Volume]:
    """The regime's knee and the static volume registered (attenuation, labels)."""
    if regime == "matched":
        return KneePhantomSpec(), *phantom_volumes(KneePhantomSpec())
    if regime == "independent":
        return KneePhantomSpec(), *cbct(KneePhantomSpec())
    return CROSS_SPEC, *phantom_volumes(CROSS_SPEC, CUT_GRID)


def motion_of(regime: str, spec: KneePhantomSpec, seq: int, frames: int, flexion: float):
    """Sequence ``seq``'s motion: squats of different seeds; the cross renderer's third
    sequence keeps the tibia still while the femur flexes over it."""
    if regime == "cross_renderer" and seq == 2:
        return flexion_extension(spec, frames=frames, max_flexion_deg=flexion)
    return squat_motion(spec, frames=frames, max_flexion_deg=flexion, seed=seq)


def frames_of(regime, spec, motion, view, models, soft, photons: float, seq: int) -> np.ndarray:
    """The regime's frames of ``motion`` (before any dewarp)."""
    if regime == "matched":
        rng = np.random.default_rng(100 + seq)
        n = len(motion.frames)
        clean = np.stack([scene(view, models, truth_of(motion, k), soft) for k in range(n)])
        return matched_frames(clean, view, photons, rng)
    if regime == "independent":
        return simulate_fluoroscopy(spec, motion, view, seed=seq).frames
    clean = simulate_fluoroscopy(
        spec,
        motion,
        view,
        voxel_mm=CROSS_VOXEL_MM,
        realism="ideal",
        projector=rtk_forward_project,
    ).frames
    return add_fluoro_noise(clean, photons, np.random.default_rng(200 + seq))[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sequences", type=int, default=3)
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument(
        "--panel",
        type=int,
        default=512,
        help="pixels across (0.3 mm panel binned to 307 mm / panel)",
    )
    parser.add_argument("--methods", nargs="+", default=list(METHODS))
    parser.add_argument(
        "--ablation-sequences",
        type=int,
        default=None,
        help="sequences for the methods other than boneaxis_kpm (default: all)",
    )
    parser.add_argument("--regimes", nargs="+", default=list(REGIMES), choices=REGIMES)
    parser.add_argument("--max-flexion", type=float, default=90.0, help="peak flexion, deg")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument(
        "--seeds", type=int, nargs="+", default=[0, 1, 2], help="real_tka: one start per seed"
    )
    parser.add_argument(
        "--edge-fit",
        action="store_true",
        help="real_tka: also fit each component to the frames' edges from the reference",
    )
    parser.add_argument(
        "--no-dewarp", action="store_true", help="register the distorted frames as they are"
    )
    args = parser.parse_args()
    if args.quick:
        args.sequences, args.frames, args.max_flexion = 1, 12, 40.0
    detector = DetectorSpec(rows=args.panel, cols=args.panel, pixel_pitch_mm=307.2 / args.panel)
    photons = 2.0e4 * (detector.pixel_pitch_mm / 0.3) ** 2
    entries = []
    for regime in args.regimes:
        if regime == "real_tka":
            entries.append(real_tka(args.seeds, edge_fit=args.edge_fit))
            log(f"real_tka: {json.dumps(entries[-1])}")
            continue
        if regime in ("tka", "tka_bones", "tka_sparse"):
            bones, sparse = regime == "tka_bones", regime == "tka_sparse"
            entries.append(tka(args.sequences, args.frames, args.panel, bones, sparse))
            log(f"{regime}: {json.dumps(entries[-1])}")
            continue
        if regime == "biplane":
            entries += biplane(args.sequences, args.frames, args.max_flexion, detector, photons)
            continue
        if regime == "biplane_tka":
            entries += biplane_tka(args.sequences, args.frames, args.panel)
            continue
        log(f"regime {regime}: bone models")
        spec, volume, labels = static_scan(regime)
        view = lateral_view(spec, detector)
        models = bone_models(volume, labels)
        soft = SoftTissue.of(volume, labels)
        drr_ms = drr_ms_256(models, view)
        runs = {m: {"errors": [], "first": [], "warm": []} for m in args.methods}
        warped = regime != "cross_renderer"  # the panel's pincushion in the image model
        dewarp = dewarp_of(regime, spec) if warped and not args.no_dewarp else None
        if dewarp is not None:
            log(f"dewarp: {dewarp.summary()}")
        floor = []
        if regime == "matched":
            motion = squat_motion(spec, frames=2, seed=0)
            floor = [
                optimum_spread(view, models, soft, motion, photons, distorted, warp)
                for distorted, warp in ((False, None), (True, dewarp), (True, None))
                if distorted or dewarp is not None
            ]
            log(f"matched floor (start at truth): {floor}")
        for seq in range(args.sequences):
            motion = motion_of(regime, spec, seq, args.frames, args.max_flexion)
            log(f"regime {regime}, sequence {seq}: rendering {args.frames} frames")
            frames = frames_of(regime, spec, motion, view, models, soft, photons, seq)
            if dewarp is not None:
                frames = dewarp.undistort(frames, view.pitch_u_mm)
            start = perturbed(truth_of(motion, 0), models, np.random.default_rng(seq))
            for method in args.methods:
                if method != "boneaxis_kpm" and seq >= (args.ablation_sequences or args.sequences):
                    continue
                out = run(method, view, frames, models, soft, motion, start)
                runs[method]["errors"] += out["errors"]
                runs[method]["first"].append(out["first"])
                runs[method]["warm"] += out["warm"]
        for method, data in runs.items():
            entry = {"regime": regime, "method": method}
            entry |= summarize(data["errors"], data["warm"], float(np.mean(data["first"])))
            entry["drr_ms_256"] = round(drr_ms, 2)
            entry["dewarp_rms_mm"] = None if dewarp is None else round(dewarp.rms_mm, 4)
            entry["sequences"] = len(data["first"])
            entry["frames"] = args.frames
            if floor:
                entry["floor_start_at_truth"] = floor
            entries.append(entry)
            log(f"{regime} {method}: {json.dumps(entry)}")
    print(json.dumps({"benchmark": "registration", "regimes": entries}, indent=1))


if __name__ == "__main__":
    main()
