"""``cbct demo``: the main job on the simulated scanner, in one study folder (docs/design.md).

1. calibrate the flat panel in the knee scan's and the calibration scan's read-out modes
   (darks and floods: offset, gain, defect and lag maps, which every scanned frame is
   corrected with);
2. plan the knee reverse spiral on the scanner (IK, clearance, timing), then scan the
   steel-ball phantom on the vibrating mock arms;
3. calibrate every view;
4. scan the standing knee phantom on the same plan, reconstructing while it acquires (the
   volume is written as stage 6 when the last view is in);
5. simulate lateral fluoroscopy of a flexion-extension with a varus imbalance mid-motion, and
   one exposure of the dewarp grid (the panel's distortion);
6. weighted FDK with the calibrated geometry (NIfTI, MetaImage, DICOM series, preview):
   written by stage 4, or made from the stored scan when a resumed demo lacks it;
7. segment femur, tibia-fibula and patella (labels, meshes);
8. dewarp the frames, track the bones with BoneAxis-Reg, scored against the simulation's
   truth;
9. assess the registered motion (report, plots, metrics, 4D series);
10. merge every stage's rerun recording into ``recording.rrd``.

Stages 1-5 are the simulated acquisitions (:func:`acquire`, also used to make cohorts), 6-9
the derived stages of ``study.stages`` that ``cbct batch`` runs too.

Each stage is marked in ``study.json`` when complete, with its files' checksums; a stage
writes into ``<stage>.partial/`` and is renamed when done, so ``--resume`` redoes only what
is missing (the scans continue from their last stored view).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import yaml

from assessment.flags import frames_text
from calibration.calibrate import calibrate
from calibration.dewarp_grid import DewarpGridSpec
from calibration.phantom import BBPhantomSpec
from recon.config import ScanProtocol, load_config, load_protocol
from recon.fdk import Progress
from recon.io import read_projections, write_projections
from recon.iterative import MIN_SPARSE_VIEWS
from registration.settings import Settings
from scanner.detector_calibration import calibrate_session
from scanner.inputs import SessionInputs, read_inputs
from scanner.session import scan_stage
from scanner.study_folder import Study, StudyError
from sim.backend import SimBackendSpec
from sim.fluoro import lateral_view, save_sequence, simulate_dewarp_grid, simulate_fluoroscopy
from sim.motion import flexion_extension
from sim.phantoms.knee import KneePhantomSpec
from study import tka as tka_stages
from study.jobs.simulate import Status
from study.live_recon import LiveRecon
from study.stages import (
    Say,
    assessment_stage,
    derived_folder,
    recon_stage,
    registration_settings_file,
    registration_stage,
    run_stage,
    segmentation_stage,
)
from study.study_recording import merge_recordings

Bars = Callable[[str, str], Progress]
"""A factory of progress callbacks: (description, unit) -> callback(done, total)."""


def _bar(bars: Bars | None, description: str, unit: str) -> Progress:
    """The callback ``bars`` makes, or one that shows nothing."""
    return bars(description, unit) if bars is not None else lambda _done, _total: None


def _fit_bars(bars: Bars | None) -> Callable[[str, int, int], None]:
    """A progress callback of the motion estimate's fits: a bar per fit."""
    made: dict[str, Progress] = {}

    def update(fit: str, done: int, total: int) -> None:
        if fit not in made:
            made[fit] = _bar(bars, f"recon: motion, {fit}: views registered", "views")
        made[fit](done, total)

    return update


FULL = {
    "views": 180,
    "panel": 256,
    "calibration_panel": 512,
    "phantom_voxel_mm": 0.75,
    "recon_voxel_mm": 0.8,
    "fluoro_panel": 512,
    "fluoro_voxel_mm": 0.5,
    "frames": 30,
    "max_flexion_deg": 90.0,
    "motion_rounds": 2,
}
QUICK = {
    "views": 90,
    "panel": 256,
    "calibration_panel": 512,
    "phantom_voxel_mm": 1.0,
    "recon_voxel_mm": 1.0,
    "fluoro_panel": 512,
    "fluoro_voxel_mm": 0.5,
    "frames": 8,
    "max_flexion_deg": 40.0,
    "motion_rounds": 1,
}
SMOKE = {
    "views": 40,
    "panel": 128,
    "calibration_panel": 512,
    "phantom_voxel_mm": 1.0,
    "recon_voxel_mm": 1.0,
    "fluoro_panel": 128,
    "fluoro_voxel_mm": 1.5,
    "frames": 3,
    "max_flexion_deg": 20.0,
    "motion_rounds": 1,
    "registration": {
        "de_popsize": 5,
        "de_maxiter": 10,
        "powell_maxfev": 100,
        "nelder_mead_maxfev": 40,
    },
}
"""The smallest demo that runs every stage (about a minute on one core): it checks an
installation, not the accuracy. Its 40 views are too few to follow the patient's sway (the
recon stage says so and reconstructs as scanned), and at its coarse fluoroscopy the
registrations fail (the report says so) whatever the first frame's search costs, so it
searches with a sixth of the settings' differential evolution and a quarter or a third of
their Powell and Nelder-Mead evaluations (``registration``: fields of the settings it
overrides).
Smaller breaks a stage: the calibration needs the panel read out at 512 to find the steel
balls."""
SIZES = {"full": FULL, "quick": QUICK, "smoke": SMOKE}
"""The demo's sizes by name (``cbct demo --size``)."""
TKA = {"fluoro_panel": 512, "recon_voxel_mm": 0.8}
"""What ``--tka`` changes in either size: the knee replacement's fluoroscopy (gait frames on
the panel read out 512^2, as bench/registration.py's tka regime) and the MAR
reconstruction's voxels."""
TKA_FRAMES_AT_LEAST = 30
"""Frames the gait is sampled at, at least: at 12 the tray turns up to 28 degrees against the
femoral component between frames in swing, beyond any start the tracker finds (docs/implants.md)."""
DETECTOR_FRAMES = 16
"""Dark and flood frames of the demo's panel calibration, each."""
VARUS_DEG = 3.0
"""Varus tilt built into the fluoroscopy motion (frames 40-60 % of the way through)."""
FLUORO_PANEL_MM = 307.2
"""Fluoroscopy panel width (the 0.3 mm x 1024 panel), read out binned."""
FLUORO_NATIVE_PIXELS = 1024
"""The dewarp grid is imaged unbinned: its 2 mm balls need the native 0.3 mm pixels, and the
warp (in mm) serves every read-out of the panel."""
STAGES = (
    "detector",
    "calibration_scan",
    "calibration",
    "scan",
    "fluoro",
    "recon",
    "segmentation",
    "registration",
    "assessment",
    "recording",
)
"""The demo's stages in order (``plan`` is made by the first scan; ``recording`` merges every
stage's recording into ``recording.rrd``)."""
TKA_STAGES = (*STAGES[:7], "placement", *STAGES[7:])
"""``--tka``'s stages: the components are placed on the metal after the segmentation."""


STANDING_SWAY_MM = 1.5
"""The demo patient's sway at the knee during the static scan, mm (a person standing still)."""
MAX_SWAY_MM = 20.0
"""Largest sway the simulator takes, mm (sim.sway.SwaySpec)."""

PHANTOM_FILES = {"knee": "knee.yaml", "bb": "bb_helix.yaml", "tka": "tka.yaml"}
"""Each simulated subject's config in configs/phantoms/."""


FULL_PROTOCOL_VIEWS = 360
"""Views of the full clinical protocol (knee_reverse_spiral_360) that a protocol given to the
demo is a share of."""


def _stages(size: dict) -> tuple[str, ...]:
    """The stages of a demo of ``size`` (:data:`TKA_STAGES` for ``--tka``)."""
    return TKA_STAGES if size.get("tka") else STAGES


def _protocols(configs: Path, size: dict) -> tuple[ScanProtocol, ScanProtocol]:
    """The knee protocol and its calibration read-out (same plan, finer pixels).

    With ``size["protocol"]`` (a protocol file): its exposure, dose limit and reconstruction,
    and its share of a full protocol's views (:data:`FULL_PROTOCOL_VIEWS`) taken of the full
    demo's (a 90-view protocol scans a quarter of :data:`FULL`'s views, whole passes, no more
    than ``size``'s own), on the demo's panel and spiral."""
    base = load_protocol(configs / "protocols" / "demo_knee.yaml")
    views = size["views"]
    if size.get("protocol"):
        given = load_protocol(size["protocol"])
        passes = base.orbit.passes
        share = FULL["views"] * given.orbit.views / FULL_PROTOCOL_VIEWS
        views = min(
            views, passes * max(round(share / passes), math.ceil(MIN_SPARSE_VIEWS / passes))
        )
        base = ScanProtocol.model_validate(
            base.model_dump()
            | {
                "orbit": base.orbit.model_dump() | {"views": views},
                "name": given.name,
                "description": given.description,
                "exposure": given.exposure.model_dump(),
                "dose_limit_mas": given.dose_limit_mas,
                "reconstruction": given.reconstruction.model_dump(),
            }
        )
    orbit = base.orbit.model_copy(update={"views": views})

    def readout(n: int) -> ScanProtocol:
        width = base.detector.width_mm
        panel = base.detector.model_copy(update={"rows": n, "cols": n, "pixel_pitch_mm": width / n})
        data = base.model_copy(update={"detector": panel, "orbit": orbit}).model_dump()
        return ScanProtocol.model_validate(data)

    return readout(size["panel"]), readout(size["calibration_panel"])


def acquire(
    study: Study,
    configs: Path,
    size: dict,
    *,
    seed: int = 0,
    varus_deg: float = VARUS_DEG,
    say: Say = lambda _m: None,
    bars: Bars | None = None,
    live_recon: bool = True,
) -> None:
    """The simulated acquisitions of one study: steel-ball calibration scan and fit, the knee
    scan, and a lateral fluoroscopy of a flexion-extension with ``varus_deg`` mid-motion
    (stages ``calibration_scan``, ``calibration``, ``scan``, ``fluoro``; complete ones skipped).
    ``live_recon``: the knee scan reconstructs while it acquires and writes the ``recon`` stage
    (a cohort's studies leave it to ``cbct batch``). ``seed`` varies the arms' tracking noise,
    the panels' quantum noise and the fluoroscopy's. ``bars(description, unit)`` gives a
    progress callback per long step (views scanned, views fitted)."""
    protocol, cal_protocol = _protocols(configs, size)
    stages = _stages(size)
    tka = stages is TKA_STAGES
    subject = "tka" if tka else "knee"
    knee = load_config(configs / "phantoms" / "knee.yaml", KneePhantomSpec)
    bb = load_config(configs / "phantoms" / "bb_helix.yaml", BBPhantomSpec)
    backend = load_config(configs / "backends" / "sim.yaml", SimBackendSpec)
    maps = study.path / "detector"
    sway = backend.sway.model_copy(update={"peak_mm": size.get("sway_mm", 0.0), "seed": seed})
    update = {"seed": seed, "detector_maps": str(maps), "sway": sway}
    backend = backend.model_copy(update=update)

    def inputs(p: ScanProtocol, phantom: str) -> SessionInputs:
        base = read_inputs(
            p,
            configs / "scanner.yaml",
            "sim",
            configs / "backends" / "sim.yaml",
            configs / "phantoms" / PHANTOM_FILES[phantom],
            phantom_voxel_mm=size["phantom_voxel_mm"],
            phantom_kind=phantom,
        )
        return replace(base, backend=backend)

    number = iter(range(1, len(stages) + 1))

    def stage(name: str, title: str) -> Say:
        say(f"stage {next(number)}/{len(stages)} {name}: {title}")
        return lambda msg: say(f"  {msg}")

    def scan(name: str, p: ScanProtocol, phantom: str, sink: LiveRecon | None = None) -> None:
        started_before = name in study.manifest["config"]
        new_inputs = None if started_before else inputs(p, phantom)
        counts = _bar(bars, f"{name}: views stored", "views")
        scan_stage(
            study,
            new_inputs,
            name,
            say=say,
            sink=sink,
            progress=lambda p: counts(p.views_done, p.views),
        )

    def detector(folder: Path) -> dict:
        found = {}
        for p in (cal_protocol, protocol):
            done = _bar(bars, f"detector: {p.detector.cols}x{p.detector.rows} frames", "frames")
            made, _ = calibrate_session(inputs(p, subject), folder, DETECTOR_FRAMES, progress=done)
            s = made.summary()
            found[made.mode] = {k: s[k] for k in ("defective_pixels", "lag", "dark_noise_adu")}
        return found

    run_stage(
        study,
        "detector",
        lambda: derived_folder(study, "detector", detector),
        stage("detector", "calibrate the panel: darks and floods in both read-out modes"),
    )
    run_stage(
        study,
        "calibration_scan",
        lambda: scan("calibration_scan", cal_protocol, "bb"),
        stage("calibration_scan", "plan, then scan the steel-ball phantom"),
    )

    def calibration() -> dict:
        stack = read_projections(study.path / "calibration_scan" / "projections.mha")
        planned = cal_protocol.orbit.geometry(cal_protocol.detector)
        fitted = _bar(bars, "calibration: views fitted", "views")
        cal = calibrate(stack.data, planned, bb, cal_protocol, progress=fitted)
        cal.save(study.path / "calibration")
        study.adopt("calibration")
        summary = cal.summary()
        return {k: v for k, v in summary.items() if not isinstance(v, (list, dict))}

    run_stage(
        study,
        "calibration",
        calibration,
        stage("calibration", "fit every view's projection matrix"),
    )
    live = LiveRecon(size["recon_voxel_mm"]) if live_recon and not tka else None
    title = "scan the standing knee" + (" replacement" if tka else "")
    title += ", reconstructing while it acquires" if live else ""
    say_scan = stage("scan", title)
    try:
        ran = run_stage(study, "scan", lambda: scan("scan", protocol, subject, live), say_scan)
    except BaseException:
        if live is not None:
            live.close()
        raise
    if ran and live is not None:  # the volume of the views as they came in is the recon stage
        scanned = time.perf_counter()
        result = live.finish()
        recon_stage(
            study,
            size["recon_voxel_mm"],
            say=say_scan,
            result=result,
            written=live.volume_path,
            fit_progress=_fit_bars(bars),
            motion_rounds=size["motion_rounds"],
            iteration_progress=_bar(bars, "recon: iterations", "subsets"),
        )
        say_scan(f"recon stage written {time.perf_counter() - scanned:.1f} s after the scan")

    def fluoro(folder: Path) -> dict:
        n = size["frames"]
        first, last = round(0.4 * (n - 1)), round(0.6 * (n - 1))
        motion = flexion_extension(knee, n, size["max_flexion_deg"], varus_deg, (first, last))
        panel = protocol.detector.model_copy(
            update={
                "rows": size["fluoro_panel"],
                "cols": size["fluoro_panel"],
                "pixel_pitch_mm": FLUORO_PANEL_MM / size["fluoro_panel"],
            }
        )
        view = lateral_view(knee, panel)
        sequence = simulate_fluoroscopy(
            knee, motion, view, voxel_mm=size["fluoro_voxel_mm"], seed=seed, status=say
        )
        save_sequence(sequence, folder)
        grid = load_config(configs / "phantoms" / "dewarp_grid.yaml", DewarpGridSpec)
        native = panel.model_copy(
            update={
                "rows": FLUORO_NATIVE_PIXELS,
                "cols": FLUORO_NATIVE_PIXELS,
                "pixel_pitch_mm": FLUORO_PANEL_MM / FLUORO_NATIVE_PIXELS,
            }
        )
        image = simulate_dewarp_grid(grid, lateral_view(knee, native), seed=seed + 1)
        write_projections(folder / "dewarp_grid.mha", image[None], native.pixel_pitch_mm)
        (folder / "dewarp_grid.yaml").write_text(yaml.safe_dump(grid.model_dump()))
        return {"frames": n, "max_flexion_deg": size["max_flexion_deg"], "varus_deg": varus_deg}

    if tka:
        title = "lateral fluoroscopy of the knee replacement through the measured gait"
        tka_stages.fluoro_stage(
            study, size["frames"], size["fluoro_panel"], seed, stage("fluoro", title)
        )
        return
    run_stage(
        study,
        "fluoro",
        lambda: derived_folder(study, "fluoro", fluoro),
        stage("fluoro", "lateral fluoroscopy of a flexion-extension, and the dewarp grid"),
    )


@dataclass(frozen=True)
class Demo:
    """A demo study ready to run: its folder, sizes, seed and registration settings."""

    study: Study
    size: dict
    seed: int
    settings: Settings


def open_demo(
    out: Path,
    configs: Path,
    *,
    size: str = "full",
    resume: bool = False,
    seed: int = 0,
    tka: bool = False,
    sway_mm: float = STANDING_SWAY_MM,
    protocol: Path | None = None,
) -> Demo:
    """The demo's study, before anything runs: new at ``out`` (a new or empty folder), or the
    one to continue (``resume``; its own seed). Raises StudyError or ConfigError.

    Args:
        out: The study folder.
        configs: The configs folder (protocols, phantoms, registration settings).
        size: Which demo (:data:`SIZES`): "full" (:data:`FULL`), "quick" (:data:`QUICK`) or
            "smoke" (:data:`SMOKE`).
        resume: Continue the study at ``out``: redo only its incomplete stages.
        seed: The noise seed of a new demo (:func:`acquire`).
        tka: The knee replacement (:data:`TKA_STAGES`) instead of the native knee.
        sway_mm: How far the standing patient sways at the knee during the static scan, mm
            (0: perfectly still; the knee replacement's scene always stands still).
        protocol: A scan protocol whose exposure, dose limit, reconstruction and share of
            the views the knee scan takes (:func:`_protocols`); default the demo's own.
    """
    if not 0.0 <= sway_mm <= MAX_SWAY_MM:
        raise ValueError(f"sway_mm must be in [0, {MAX_SWAY_MM:g}] mm, got {sway_mm!r}")
    if size not in SIZES:
        raise ValueError(f"size {size!r}: choose one of {', '.join(SIZES)}")
    grids = {**SIZES[size], "sway_mm": 0.0 if tka else float(sway_mm)}
    if protocol is not None:
        if tka:
            raise ValueError("--protocol is for the native knee's demo, not --tka")
        load_protocol(protocol)  # refused here, before the study is made
        grids["protocol"] = str(protocol.resolve())
    if tka:
        grids = {**grids, **TKA, "tka": True}
        grids["frames"] = max(grids["frames"], TKA_FRAMES_AT_LEAST)
    settings_file = (
        configs / "registration_gait.yaml"
        if tka
        else registration_settings_file(configs, meshes_alone=False)
    )
    settings = load_config(settings_file, Settings)
    settings = Settings.model_validate({**settings.model_dump(), **grids.get("registration", {})})
    if resume:
        study = Study.open(out)
        made = study.manifest["config"].get("demo", {})
        if made.get("size") != grids:
            raise StudyError(
                f"{out} was made with other demo settings (--size, --tka, --sway-mm or "
                "--protocol differs)"
            )
        return Demo(study, grids, made.get("seed", 0), settings)
    demo = {"size": grids, "varus_deg": VARUS_DEG, "seed": seed}
    return Demo(Study.create(out, {"demo": demo}), grids, seed, settings)


def run(
    demo: Demo, configs: Path, *, status: Status | None = None, bars: Bars | None = None
) -> str:
    """Run the demo's stages (those not complete yet); returns the summary.

    Args:
        demo: The study from :func:`open_demo`.
        configs: The configs folder.
        status: Takes a line per stage.
        bars: ``bars(description, unit)`` gives a progress callback per long step (views
            scanned and fitted, views reconstructed, frames registered).
    """
    say = status or (lambda _msg: None)
    study, size, seed, settings = demo.study, demo.size, demo.seed, demo.settings
    out = study.path
    started = time.perf_counter()
    acquire(study, configs, size, seed=seed, say=say, bars=bars)
    stages = _stages(size)
    tka = stages is TKA_STAGES
    number = iter(range(stages.index("recon") + 1, len(stages) + 1))

    def stage(name: str, title: str) -> Say:
        say(f"stage {next(number)}/{len(stages)} {name}: {title}")
        return lambda msg: say(f"  {msg}")

    if tka:
        tka_stages.recon_stage(
            study,
            size["recon_voxel_mm"],
            _bar(bars, "recon: views backprojected", "views"),
            stage("recon", "weighted FDK with metal artefact reduction (NMAR)"),
        )
        tka_stages.segmentation_stage(study, stage("segmentation", "bones next to the metal"))
        tka_stages.placement_stage(study, stage("placement", "components on the metal (3D-3D)"))
        tka_stages.registration_stage(
            study,
            settings,
            stage("registration", "the components tracked from their meshes"),
            _bar(bars, "registration: frames tracked", "frames"),
        )
        tka_stages.assessment_stage(study, stage("assessment", "the knee replacement's report"))
    else:
        recon_stage(
            study,
            size["recon_voxel_mm"],
            _bar(bars, "recon: views backprojected", "views"),
            stage("recon", "weighted FDK with the calibrated geometry, through the patient's sway"),
            fit_progress=_fit_bars(bars),
            motion_rounds=size["motion_rounds"],
            iteration_progress=_bar(bars, "recon: iterations", "subsets"),
        )
        segmentation_stage(study, stage("segmentation", "bones from the reconstruction"))
        registration_stage(
            study,
            settings,
            stage("registration", "BoneAxis-Reg tracking"),
            _bar(bars, "registration: frames tracked", "frames"),
        )
        assessment_stage(
            study,
            "Demo: registered weight-bearing flexion-extension",
            stage("assessment", "knee kinematics report"),
        )

    def recording() -> None:
        parts = [
            out / "plan" / "recording.rrd",
            *sorted((out / "calibration_scan").glob("recording*.rrd")),
            *sorted((out / "scan").glob("recording*.rrd")),
            out / "recon" / "recording.rrd",
            out / "assessment" / "series.rrd",
        ]
        (out / "recording.rrd").unlink(missing_ok=True)  # an interrupted merge: made again
        merge_recordings(parts, out / "recording.rrd")
        study.adopt("recording.rrd")

    run_stage(study, "recording", recording, stage("recording", "one recording of every stage"))
    if tka:
        return _tka_summary(study, out, time.perf_counter() - started)
    return _summary(study, out, time.perf_counter() - started)


def _assessment_text(assess: dict) -> str:
    """What the demo's summary says of the report: measured frames, flags, the truth's."""
    if assess["max_abs_mld_mm"] is None:
        return "no frame measured: tracking insufficient"
    flagged = frames_text(assess["flagged_frames"]) or "no frame"
    text = (
        f"{assess['measured_frames']} of {assess['frames']} frames measured, max |MLD| "
        f"{assess['max_abs_mld_mm']:.2f} mm, {flagged} flagged"
    )
    if not assess["tracking_sufficient"]:
        text += "; tracking insufficient: no clinical flag"
    if "truth_flagged_frames" in assess:
        text += f"; the true poses flag {frames_text(assess['truth_flagged_frames']) or 'none'}"
    return text


def _method_text(recon: dict) -> str:
    """What the demo's summary says of an iterative reconstruction (nothing for FDK)."""
    method = recon.get("reconstruction", {})
    if method.get("method", "fdk") == "fdk":
        return ""
    if not method["ran"]:
        return f"  method:     {method['why']}\n"
    return (
        f"  method:     {method['method'].upper()}, {method['iterations']} iterations from FDK; "
        f"RMSE vs phantom {recon['rmse_calibrated_per_mm']:.5f} /mm "
        f"({recon['rmse_fdk_per_mm']:.5f} FDK)\n"
    )


def _motion_text(study: Study, out: Path) -> str:
    """What the demo's summary says of the patient's sway during the static scan."""
    recon = study.manifest["stages"]["recon"]
    motion = recon.get("motion")
    if motion is None:
        return ""
    swayed = study.manifest["config"]["demo"]["size"].get("sway_mm", 0.0)
    text = f"  sway:       the patient swayed {swayed:g} mm at the knee; {motion['verdict']}"
    if "rmse_uncompensated_per_mm" in recon:
        text += (
            f"; RMSE vs phantom {recon['rmse_uncompensated_per_mm']:.5f} /mm before, "
            f"{recon['rmse_calibrated_per_mm']:.5f} after"
        )
    if not motion.get("estimated", True):
        return f"{text}\n"
    if "error_mm" in motion:
        text += f"; motion error median {motion['error_mm']['median']:.2f} mm"
    return f"{text} ({out}/recon/motion.png)\n"


def _summary(study: Study, out: Path, seconds: float) -> str:
    stages = study.manifest["stages"]
    recon = stages["recon"]
    reg = stages["registration"]
    assess = stages["assessment"]
    return (
        f"[green]demo finished[/] in {seconds:.0f} s -> {out}\n"
        f"  report:     {out}/assessment/report.html ({_assessment_text(assess)})\n"
        f"  recording:  rerun {out}/recording.rrd\n"
        f"  3D Slicer:  {out}/assessment/export/scene.mrml (ITK transforms and Autoscoper "
        f".tra beside it)\n"
        f"  volume:     {out}/recon/volume.nii.gz (+ .mha, dicom/), preview "
        f"{out}/recon/slices.png; RMSE vs phantom {recon['rmse_calibrated_per_mm']:.5f} /mm "
        f"with the calibrated geometry ({recon['rmse_recorded_per_mm']:.5f} recorded, "
        f"{recon['rmse_true_per_mm']:.5f} true)\n"
        f"{_method_text(recon)}"
        f"{_motion_text(study, out)}"
        f"  registration: TRE mean {reg['tre_mm']:.2f} mm (median {reg['tre_mm_median']:.2f}), "
        f"RSR {reg['rsr_pct']:.1f} %  ({out}/registration/poses.csv)\n"
        f"  study:      {out}/study.json (every stage, every file's sha256)"
    )


def _tka_summary(study: Study, out: Path, seconds: float) -> str:
    stages = study.manifest["stages"]
    recon, seg = stages["recon"], stages["segmentation"]
    placed, reg, assess = stages["placement"], stages["registration"], stages["assessment"]
    placement = ", ".join(
        f"{body} {p['error_deg']:.2f} deg / {p['error_mm']:.2f} mm"
        for body, p in placed.items()
        if isinstance(p, dict) and "error_deg" in p
    )
    return (
        f"[green]demo (knee replacement) finished[/] in {seconds:.0f} s -> {out}\n"
        f"  report:     {out}/assessment/report.html ({_assessment_text(assess)})\n"
        f"  volume:     {out}/recon/volume.nii.gz with NMAR (metal {out}/recon/metal.nii.gz); "
        f"RMSE outside the metal {recon['rmse_outside_metal_per_mm']:.5f} /mm "
        f"({recon['rmse_outside_metal_uncorrected_per_mm']:.5f} without MAR)\n"
        f"  bones:      Dice within 20 mm of the metal "
        f"{seg['dice_near_metal']['bone']:.3f} ({out}/segmentation/labels.nii.gz)\n"
        f"  placement:  {placement} from the truth ({out}/placement/placement.json)\n"
        f"  tracking:   TRE median {reg['tre_mm_median']:.2f} mm, RSR {reg['rsr_pct']:.1f} %, "
        f"depth median {reg['out_of_plane_mm_median']:.2f} mm ({out}/registration/poses.csv)\n"
        f"  study:      {out}/study.json (every stage, every file's sha256)"
    )
