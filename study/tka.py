"""The knee replacement's stages of ``cbct demo --tka`` (docs/guide/demo.md): its fluoroscopy
through the measured gait, the static scan reconstructed with metal artefact reduction, the
bones segmented next to the metal, the components placed on the metal, tracked through the
frames and assessed.

Each stage is a folder of the study (study.stages' conventions: written into
``<stage>.partial/``, renamed when done, marked in study.json with its figures); on the
simulator each is scored against the truth (sim.tka_ct).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from assessment.components import assess_components
from recon.fdk import Progress
from recon.geometry import DetectorSpec, Geometry
from recon.io import read_projections, read_volume, write_projections, write_volume
from recon.mar import nmar
from recon.preview import save_orthogonal_slices
from recon.rtk_xml import write_rtk_geometry
from recon.volume import Volume
from registration.meshes import read_mesh
from registration.placement import place_components
from registration.poses import BodyPose, read_poses, write_poses
from registration.se3 import compose
from registration.segment import bone_surfaces, segment_bones_with_metal
from registration.settings import Settings
from scanner.study_folder import Study
from sim.phantoms.tka import TkaPhantomSpec
from sim.tka import TRACKED, load_tka, part_poses, read_gait, simulate_tka_fluoro, tka_motion
from sim.tka_ct import METAL_LABEL, tka_scene, tka_truth
from study.jobs import ImplantSpec, RegisterOptions, assess_files
from study.stages import (
    Say,
    ScanGeometry,
    derived_folder,
    kinematics_summary,
    recon_grid,
    require,
    run_stage,
    scan_protocol,
    track_fluoro,
)
from study.study_recording import record_volume

FLUORO_CENTER_MM = np.array([0.0, 0.0, 490.0])
"""Where the knee's joint centre stands in the fluoroscope's world, mm."""
FLUORO_PHOTONS = 2.0e4
"""Unattenuated photons per pixel of the fluoroscopy (as bench/registration.py's tka regime)."""
START_OFFSET = (3.0, 3.0)
"""The first frame's start (an operator's, as JointTrack users place a component by hand): the
true pose moved by up to this many mm and degrees per axis, seeded."""
FLUORO_PANEL_MM = 307.2
"""The fluoroscopy panel's width, mm."""
COMPONENTS = {
    "femur": "femoral_component",
    "tibia": "tibial_tray",
}
"""The tracked components by the role each plays (registration.roles)."""
INSERT = "tibial_insert"
"""The polyethylene insert: the TKA report's plateau plane (in the tray's frame)."""


def tka_phantom(study: Study) -> TkaPhantomSpec:
    """The knee replacement the study's simulated scan imaged."""
    phantom = dict(study.manifest["config"]["scan"]["phantom"])
    if phantom.pop("kind", None) != "tka":
        raise ValueError(f"{study.path}: its scan did not image the simulated knee replacement")
    return TkaPhantomSpec.model_validate(phantom)


def fluoro_stage(study: Study, frames: int, panel: int, seed: int, say: Say) -> bool:
    """Lateral fluoroscopy of the knee replacement through the subject's measured gait ->
    ``fluoro/`` (frames, view, true poses, the first frame's start: ``initial.csv``), with the
    components' meshes (``components/``, in their bodies' frames, mm: the CAD meshes the
    tracking and the report take)."""

    def fill(folder: Path) -> dict:
        spec = tka_phantom(study)
        knee = load_tka(spec.data)
        gait = read_gait(Path(spec.data) / "kinematics" / "fluoroscopic_gait.sto")
        motion = tka_motion(knee, gait, frames, FLUORO_CENTER_MM)
        detector = DetectorSpec(rows=panel, cols=panel, pixel_pitch_mm=FLUORO_PANEL_MM / panel)
        say(f"rendering {frames} frames of {panel}^2 through the gait")
        view, images = simulate_tka_fluoro(
            knee, motion, detector, FLUORO_CENTER_MM, FLUORO_PHOTONS, seed=seed
        )
        write_projections(folder / "frames.mha", images, view.pitch_u_mm)
        write_rtk_geometry(folder / "view.xml", Geometry([view] * frames))
        components = folder / "components"
        components.mkdir()
        for part in (*COMPONENTS.values(), INSERT):
            knee.meshes[part].export(components / f"{part}.stl")
        poses, centroids = [], {}
        for body in TRACKED:
            moved = part_poses(knee, motion, body)
            poses += [BodyPose(k, body, moved[k]) for k in range(frames)]
            centroids[body] = np.asarray(knee.meshes[body].centroid)
        poses.sort(key=lambda p: (p.frame, p.body))
        write_poses(folder / "poses.csv", poses, centroids)
        rng = np.random.default_rng([seed, 35])
        t, r = START_OFFSET
        start = [
            BodyPose(
                0,
                p.body,
                compose(
                    np.concatenate((rng.uniform(-t, t, 3), rng.uniform(-r, r, 3))),
                    p.T_world_body,
                    centroids[p.body],
                ),
            )
            for p in poses
            if p.frame == 0
        ]
        write_poses(folder / "initial.csv", start, centroids)
        flexion = motion.flexion_deg
        return {
            "frames": frames,
            "panel": panel,
            "flexion_deg": [round(float(flexion.min()), 1), round(float(flexion.max()), 1)],
        }

    require(study, "scan")
    return run_stage(study, "fluoro", lambda: derived_folder(study, "fluoro", fill), say)


def recon_stage(study: Study, voxel_mm: float, progress: Progress | None, say: Say) -> bool:
    """The static scan with normalised metal artefact reduction -> ``recon/`` (the volume,
    the metal's mask, the uncorrected volume, a preview); against the truth: the RMSE outside
    the metal, with and without MAR."""

    def fill(folder: Path) -> dict:
        protocol = scan_protocol(study)
        stack = read_projections(study.path / "scan" / "projections.mha")
        views = ScanGeometry.of(study, protocol, stack.header)
        grid = recon_grid(protocol, voxel_mm)
        result = nmar(
            stack.data,
            views.rays,
            grid,
            fdk=lambda projections, on: views.fdk(projections, on, progress),
            say=say,
        )
        write_volume(folder / "volume.nii.gz", result.volume)
        write_volume(folder / "uncorrected.nii.gz", result.uncorrected)
        write_volume(folder / "metal.nii.gz", Volume(result.metal.astype(np.uint8), grid, "label"))
        save_orthogonal_slices(result.volume, folder / "slices.png", title="weighted FDK + NMAR")
        record_volume(result.volume, folder / "recording.rrd")
        truth = tka_truth(tka_scene(tka_phantom(study)), grid, protocol.exposure.tube_kv)
        details = {
            "voxel_mm": voxel_mm,
            "metal_cm3": round(result.metal_mm3 / 1000.0, 2),
            "rmse_outside_metal_per_mm": truth.rmse_outside_metal(result.volume.data),
            "rmse_outside_metal_uncorrected_per_mm": truth.rmse_outside_metal(
                result.uncorrected.data
            ),
        }
        (folder / "metrics.json").write_text(json.dumps(details, indent=2), encoding="utf-8")
        return details

    require(study, "scan")
    return run_stage(study, "recon", lambda: derived_folder(study, "recon", fill), say)


def segmentation_stage(study: Study, say: Say) -> bool:
    """The bones next to the metal -> ``segmentation/`` (labels with the metal
    :data:`sim.tka_ct.METAL_LABEL`, a mesh per bone); against the truth: the Dice of the bones
    within 20 mm of the metal."""

    def fill(folder: Path) -> dict:
        volume = read_volume(study.path / "recon" / "volume.nii.gz", unit="1/mm")
        metal = read_volume(study.path / "recon" / "metal.nii.gz", unit="label").data > 0
        labels = segment_bones_with_metal(volume, metal, METAL_LABEL, side="right")
        write_volume(folder / "labels.nii.gz", labels)
        for name, mesh in bone_surfaces(labels).items():
            mesh.export(folder / f"{name}.stl")
        protocol = scan_protocol(study)
        truth = tka_truth(tka_scene(tka_phantom(study)), volume.grid, protocol.exposure.tube_kv)
        dice = truth.near_metal_scores(labels.data)
        (folder / "dice.json").write_text(json.dumps(dice, indent=2), encoding="utf-8")
        return {"side": "right", "dice_near_metal": dice}

    require(study, "recon")
    return run_stage(
        study, "segmentation", lambda: derived_folder(study, "segmentation", fill), say
    )


def placement_stage(study: Study, say: Say) -> bool:
    """The components' meshes placed on the static scan's metal -> ``placement/``
    (placement.json: each component's pose in the scan, its fit; against the truth: the
    rotation and the centroid's distance from the scene's pose)."""

    def fill(folder: Path) -> dict:
        metal = read_volume(study.path / "recon" / "metal.nii.gz", unit="label")
        components = study.path / "fluoro" / "components"
        meshes = {}
        for body, part in COMPONENTS.items():
            path = components / f"{part}.stl"
            meshes[body] = (read_mesh(path)[0], path)
        placed = place_components(meshes, metal.data > 0, metal.grid)
        scene = tka_scene(tka_phantom(study))
        details = {}
        for body, placement in placed.items():
            part = COMPONENTS[body]
            T, truth = placement.T_world_body, scene.poses[part]
            centroid = np.asarray(meshes[body][0].centroid)
            moved = (T[:3, :3] @ centroid + T[:3, 3]) - (truth[:3, :3] @ centroid + truth[:3, 3])
            angle = Rotation.from_matrix(T[:3, :3] @ truth[:3, :3].T).magnitude()
            details[body] = {
                "mesh": placement.path,
                "T_world_body": np.round(T, 6).tolist(),
                "surface_distance_mm": round(placement.surface_distance_mm, 3),
                "volume_ratio": round(placement.volume_ratio, 3),
                "error_deg": round(float(np.degrees(angle)), 3),
                "error_mm": round(float(np.linalg.norm(moved)), 3),
            }
        (folder / "placement.json").write_text(json.dumps(details, indent=2), encoding="utf-8")
        return {
            body: {k: v for k, v in d.items() if k not in ("mesh", "T_world_body")}
            for body, d in details.items()
        }

    require(study, "recon", "fluoro")
    return run_stage(study, "placement", lambda: derived_folder(study, "placement", fill), say)


def registration_stage(
    study: Study, settings: Settings | None, say: Say, progress: Progress | None
) -> bool:
    """The components tracked through the frames from their meshes (from the first frame's
    start, ``fluoro/initial.csv``) -> ``registration/``, scored against the true poses."""

    def work() -> dict:
        components = study.path / "fluoro" / "components"
        implants = tuple(
            ImplantSpec(body, components / f"{part}.stl") for body, part in COMPONENTS.items()
        )
        inputs = {
            "implants": implants,
            "truth": study.path / "fluoro" / "poses.csv",
            "initial": study.path / "fluoro" / "initial.csv",
        }
        options = RegisterOptions(polarity="bright", settings=settings)
        return track_fluoro(study, say, progress, inputs, options)

    require(study, "fluoro")
    return run_stage(study, "registration", work, say)


def assessment_stage(study: Study, say: Say) -> bool:
    """The knee's kinematics from the tracked components -> ``assessment/`` (the TKA report:
    the plateau plane of the insert, the femoral component's condylar points, MLD, DDV)."""

    def fill(folder: Path) -> dict:
        components = study.path / "fluoro" / "components"
        folder.rmdir()  # assess_files makes its own new folder
        insert = components / f"{INSERT}.stl"
        kin = assess_files(
            study.path / "registration" / "poses.csv",
            None,
            folder,
            "right",
            implants={role: components / f"{part}.stl" for role, part in COMPONENTS.items()},
            insert=insert,
            overlays=study.path / "registration" / "overlays",
        ).kinematics
        femoral = read_mesh(components / f"{COMPONENTS['femur']}.stl")[0]
        truth = read_poses(study.path / "fluoro" / "poses.csv")
        truth_kin = assess_components(femoral, read_mesh(insert)[0], truth).kinematics
        return kinematics_summary(kin, truth_kin)

    require(study, "registration")
    return run_stage(study, "assessment", lambda: derived_folder(study, "assessment", fill), say)
