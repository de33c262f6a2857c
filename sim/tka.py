"""A knee replacement to simulate: the grand-challenge subject DM's implant components on its
resected bones, placed by its OpenSim model, moved by its knee kinematics measured over gait.

The data (``../shared/data/grand-challenge-tka``, Apache-2.0; its README says what each file
is) give the meshes in metres, each in its OpenSim body's frame or in an offset frame of it
(``DM.osim``: the components' ``femur_implant``, ``tibia_implant`` frames), and the knee's
six degrees of freedom over 101 samples of gait (``kinematics/fluoroscopic_gait.sto``).

How we read them:

- OpenSim's body frames (x anterior, y superior, z to the right) are turned into the world's
  LPS (:data:`OSIM_TO_LPS`); the femur's frame sits so that the knee joint's centre (the
  ``knee_r`` joint's femoral frame) is at :func:`tka_motion`'s ``center_mm``.
- A ``CustomJoint`` of linear functions (``knee_r``, ``pf_r``) moves its child frame from its
  parent frame by the rotations about its three axes in turn (body-fixed), then the
  translations along the parent's axes.
- The gait file's three angles are the rotations about the knee joint's x, y and z axes, in
  that order, whatever their names: the columns named flex, add and rot hold -1..+2 deg,
  -10..+7 deg and -53..-5 deg, and only the last, about z (the model's flexion axis, whose
  coefficient is -1), has a gait's swing-phase flexion. Its translations (along x, y, z:
  anterior, superior, lateral) sit in another origin than the model's (its superior 41.5 mm
  would lift the tibia through the femur), so the model's default translations carry the
  file's changes from its first sample.
- The patella rides on the femur at the model's default ``pf_r`` coordinates.
- The camera follows the knee: the thigh and the shank share the flexion and the adduction
  about the knee's centre (the femur turns by half of each, the tibia by the other half), as a
  fluoroscope tracking the knee through gait sees it.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from scipy.ndimage import gaussian_filter
from scipy.spatial.transform import Rotation

from recon.geometry import DetectorSpec, View
from registration.implants import ray_lengths
from registration.meshes import ATTACHABLE, Material, read_mesh, size_range_mm
from sim.fluoro import lateral_view, turned_view
from sim.phantoms.knee import KneePhantomSpec

OSIM_TO_LPS = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
"""OpenSim's right-leg frame (x anterior, y superior, z right) in the world's LPS axes: its
columns are x -> posterior's opposite (-y), y -> superior (+z), z -> right (-x)."""

PARTS = {
    "femoral_component": ("femoral_component_decimated.stl", "femur_r", "CoCr"),
    "tibial_tray": ("tibial_tray_decimated.stl", "tibia_r", "CoCr"),
    "tibial_insert": ("tibial_insert_decimated.stl", "tibia_r", "UHMWPE"),
    "patellar_button": ("patellar_button_decimated.stl", "patella_r", "UHMWPE"),
    "femur": ("femur.stl", "femur_r", "bone"),
    "tibia": ("tibia.stl", "tibia_r", "bone"),
    "fibula": ("fibula.stl", "tibia_r", "bone"),
    "patella": ("patella.stl", "patella_r", "bone"),
}
"""Each part of the knee: its mesh file, the OpenSim body that carries it, its material."""

TRACKED = {"femoral_component": (), "tibial_tray": ("tibial_insert",)}
"""The tracked components (each plays the bone it replaces: registration.roles), and the parts
fixed to each that move with it (the tray's insert)."""
FIXED_BONES = {"femoral_component": ("femur",), "tibial_tray": ("tibia", "fibula")}
"""The bones each tracked component is fixed to."""


@dataclass(frozen=True)
class TkaKnee:
    """The knee replacement's parts in their bodies' frames (mm).

    Attributes:
        meshes: Each part's closed mesh in its body's frame, mm.
        bodies: Each part's body: "femur_r", "tibia_r" or "patella_r".
        materials: Each part's material.
        knee: The ``knee_r`` joint (femur to tibia).
        patella_mm: The patella's frame in the femur's at the ``pf_r`` defaults (4x4, mm).
        repairs: What reading the meshes repaired, by part.
    """

    meshes: dict[str, trimesh.Trimesh]
    bodies: dict[str, str]
    materials: dict[str, Material]
    knee: Joint
    patella_mm: np.ndarray
    repairs: dict[str, tuple[str, ...]]


def _frame(translation_m: str, orientation_rad: str) -> np.ndarray:
    """4x4 (mm) of an OpenSim offset: translation (m) and body-fixed x-y-z angles (rad)."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("XYZ", [float(v) for v in orientation_rad.split()]).as_matrix()
    T[:3, 3] = 1000.0 * np.array([float(v) for v in translation_m.split()])
    return T


def _offset(element: ET.Element, name: str, where: str) -> np.ndarray:
    """The PhysicalOffsetFrame ``name`` under ``element`` as 4x4 (mm)."""
    frame = element.find(f".//PhysicalOffsetFrame[@name='{name}']")
    if frame is None:
        raise ValueError(f"{where}: no offset frame {name!r}")
    return _frame(frame.findtext("translation"), frame.findtext("orientation"))


@dataclass(frozen=True)
class Joint:
    """An OpenSim ``CustomJoint`` of linear functions.

    Attributes:
        name: The joint's name.
        parent_mm: Its frame on the parent body (4x4, mm).
        child_mm: Its frame on the child body (4x4, mm).
        defaults: Its coordinates' default values (rad, m).
        axes: Per transform axis (3 rotations, then 3 translations): the coordinate, the
            axis (3,) and the linear function's (slope, intercept).
    """

    name: str
    parent_mm: np.ndarray
    child_mm: np.ndarray
    defaults: dict[str, float]
    axes: tuple[tuple[str, np.ndarray, tuple[float, float]], ...]

    def transform(self, values: dict[str, float] | None = None) -> np.ndarray:
        """The child frame in the parent frame (4x4, mm) at ``values`` (the defaults for
        any not given): the rotations about the joint's axes in turn, then the translations
        along the parent's axes."""
        q = {**self.defaults, **(values or {})}
        T = np.eye(4)
        for i, (coordinate, axis, (slope, intercept)) in enumerate(self.axes):
            amount = slope * q[coordinate] + intercept
            if i < 3:
                T[:3, :3] = T[:3, :3] @ Rotation.from_rotvec(amount * axis).as_matrix()
            else:
                T[:3, 3] += 1000.0 * amount * axis
        return self.parent_mm @ T @ np.linalg.inv(self.child_mm)


def read_joint(model: ET.Element, name: str, where: str) -> Joint:
    """The ``CustomJoint`` ``name`` of an OpenSim model; ValueError naming ``where`` if it is
    missing or uses another function than a linear one."""
    joint = model.find(f".//CustomJoint[@name='{name}']")
    if joint is None:
        raise ValueError(f"{where}: no CustomJoint {name!r}")
    parent = _offset(joint, joint.findtext("socket_parent_frame"), where)
    child = _offset(joint, joint.findtext("socket_child_frame"), where)
    defaults = {c.get("name"): float(c.findtext("default_value")) for c in joint.iter("Coordinate")}
    axes = []
    for axis in joint.find("SpatialTransform"):
        linear = axis.find("LinearFunction")
        if linear is None:
            raise ValueError(f"{where}: joint {name} axis {axis.get('name')}: not linear")
        slope, intercept = (float(v) for v in linear.findtext("coefficients").split())
        direction = np.array([float(v) for v in axis.findtext("axis").split()])
        axes.append((axis.findtext("coordinates").strip(), direction, (slope, intercept)))
    if len(axes) != 6:
        raise ValueError(f"{where}: joint {name} has {len(axes)} transform axes, not 6")
    return Joint(name, parent, child, defaults, tuple(axes))


def load_tka(folder: Path | str) -> TkaKnee:
    """The grand-challenge knee replacement from its folder (meshes/, DM.osim).

    Args:
        folder: The data folder (``../shared/data/grand-challenge-tka``).

    Returns:
        Its parts in their bodies' frames.
    """
    folder = Path(folder)
    where = folder / "DM.osim"
    if not where.is_file():
        raise FileNotFoundError(f"{where}: no such OpenSim model")
    model = ET.parse(where).getroot()
    meshes, bodies, materials, repairs = {}, {}, {}, {}
    for part, (file, body, material) in PARTS.items():
        mesh, report = read_mesh(folder / "meshes" / file, "m", size_range_mm(material))
        body_element = model.find(f".//Body[@name='{body}']")
        osim_name = file.replace("_", " ")  # "Femoral Component decimated.stl", in any case
        placed = np.eye(4)
        for frame in body_element.iter("PhysicalOffsetFrame"):
            names = [m.findtext("mesh_file", "").lower() for m in frame.iter("Mesh")]
            if osim_name in names:
                placed = _frame(frame.findtext("translation"), frame.findtext("orientation"))
        mesh.apply_transform(placed)
        meshes[part], bodies[part], repairs[part] = mesh, body, report.repairs
        materials[part] = ATTACHABLE[material]
    knee = read_joint(model, "knee_r", str(where))
    if not np.allclose(knee.child_mm, np.eye(4)):
        raise ValueError(f"{where}: the knee joint's tibial frame is not the tibia's own")
    patella = read_joint(model, "pf_r", str(where))
    return TkaKnee(meshes, bodies, materials, knee, patella.transform(), repairs)


@dataclass(frozen=True)
class TkaMotion:
    """Each body's pose (``T_world_body``: body frame mm -> world LPS mm) in every frame.

    Attributes:
        frames: Frame numbers (F,).
        poses: "femur_r", "tibia_r", "patella_r" -> (F, 4, 4).
        flexion_deg: The knee's flexion per frame (the gait file's), deg.
    """

    frames: np.ndarray
    poses: dict[str, np.ndarray]
    flexion_deg: np.ndarray


def read_gait(path: Path | str) -> dict[str, np.ndarray]:
    """The columns of an OpenSim ``.sto`` (after ``endheader``) by name."""
    lines = Path(path).read_text(encoding="utf-8").splitlines()
    try:
        start = lines.index("endheader") + 1
    except ValueError:
        raise ValueError(f"{path}: no 'endheader' line: not an OpenSim storage file") from None
    names = lines[start].split()
    rows = np.array([[float(v) for v in line.split()] for line in lines[start + 1 :] if line])
    return {name: rows[:, i] for i, name in enumerate(names)}


def tka_motion(
    knee: TkaKnee,
    gait: dict[str, np.ndarray],
    frames: int,
    center_mm: np.ndarray,
) -> TkaMotion:
    """The knee's bodies through gait, ``frames`` samples evenly spaced over the file's.

    Args:
        knee: The knee replacement.
        gait: The gait file's columns (:func:`read_gait`).
        frames: How many frames.
        center_mm: Where the knee joint's centre stands in the world (3,), mm.

    Returns:
        Every body's pose per frame.
    """
    samples = np.linspace(0, len(gait["time"]) - 1, frames)
    at = {k: np.interp(samples, np.arange(len(v)), v) for k, v in gait.items()}
    turns = {"knee_add_r": ("knee_flex_r", 1.0), "knee_rot_r": ("knee_add_r", 1.0)}
    turns["knee_flex_r"] = ("knee_rot_r", -1.0)  # about z, the model's flexion is minus it
    moved = {"knee_tx_r": "knee_ant_r", "knee_ty_r": "knee_sup_r", "knee_tz_r": "knee_lat_r"}
    world = np.eye(4)
    world[:3, :3] = OSIM_TO_LPS
    poses = {body: np.empty((frames, 4, 4)) for body in ("femur_r", "tibia_r", "patella_r")}
    for k in range(frames):
        values = {name: sign * at[column][k] for name, (column, sign) in turns.items()}
        for model_name, gait_name in moved.items():
            values[model_name] = (
                knee.knee.defaults[model_name] + at[gait_name][k] - at[gait_name][0]
            )
        femur_tibia = knee.knee.transform(values)
        half = np.eye(4)  # the thigh's share of the flexion and adduction, about the knee
        half[:3, :3] = Rotation.from_rotvec(
            0.5 * values["knee_flex_r"] * np.array([0.0, 0.0, 1.0])
            - 0.5 * values["knee_add_r"] * np.array([1.0, 0.0, 0.0])
        ).as_matrix()
        place = np.eye(4)
        place[:3, 3] = center_mm
        femur = place @ world @ half @ np.linalg.inv(knee.knee.parent_mm)
        poses["femur_r"][k] = femur
        poses["tibia_r"][k] = femur @ femur_tibia
        poses["patella_r"][k] = femur @ knee.patella_mm
    return TkaMotion(np.arange(frames), poses, -np.degrees(at["knee_rot_r"]))


def part_poses(knee: TkaKnee, motion: TkaMotion, part: str) -> np.ndarray:
    """A part's ``T_world_part`` per frame (its mesh is in its body's frame)."""
    return motion.poses[knee.bodies[part]]


LEG_RADIUS_MM = 60.0
"""The soft tissue about the knee: cylinders of water this wide about the thigh's and the
shank's axes, through the knee's centre."""
WATER_PER_MM = 0.0193
"""Water's linear attenuation at 70 keV, 1/mm."""


def cylinder_chords(
    view: View,
    center_mm: np.ndarray,
    radius_mm: float = LEG_RADIUS_MM,
    axis: np.ndarray | tuple[float, float, float] = (0.0, 0.0, 1.0),
    side: np.ndarray | None = None,
) -> np.ndarray:
    """Each pixel centre's ray length (rows, cols), mm, through a cylinder of ``radius_mm``
    about the line through ``center_mm`` along ``axis`` (vertical by default), cut to the
    half-space ``(x - center) . side >= 0`` when ``side`` is given."""
    v, u = np.mgrid[: view.rows, : view.cols].astype(np.float64)
    d = view.pixel_to_world(u, v) - view.source_mm
    a = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    w = view.source_mm - np.asarray(center_mm, dtype=np.float64)
    d_across = d - (d @ a)[..., None] * a
    w_across = w - (w @ a) * a
    qa = np.sum(d_across**2, axis=-1)
    qb = 2.0 * (d_across @ w_across)
    qc = w_across @ w_across - radius_mm**2
    root = np.sqrt(np.maximum(qb * qb - 4.0 * qa * qc, 0.0))
    t0 = np.clip((-qb - root) / (2.0 * qa), 0.0, 1.0)
    t1 = np.clip((-qb + root) / (2.0 * qa), 0.0, 1.0)
    if side is not None:  # w . n + t d . n >= 0
        dn, wn = d @ side, float(w @ side)
        with np.errstate(divide="ignore", invalid="ignore"):
            t_cut = -wn / dn
        t0 = np.where(dn > 0, np.maximum(t0, t_cut), t0)
        t1 = np.where(dn < 0, np.minimum(t1, t_cut), t1)
        if wn < 0:  # the source is on the other side: rays parallel to the cut miss it
            t1 = np.where(dn == 0, t0, t1)
    return np.maximum(t1 - t0, 0.0) * np.linalg.norm(d, axis=-1)


def leg_chords(
    view: View, center_mm: np.ndarray, T_femur: np.ndarray, T_tibia: np.ndarray
) -> np.ndarray:
    """Each pixel centre's ray length (rows, cols), mm, through the leg bent at the knee: a
    cylinder of :data:`LEG_RADIUS_MM` along the femur's long axis (its body's y) above the
    plane that halves the knee's angle, one along the tibia's below it."""
    up = T_femur[:3, 1] / np.linalg.norm(T_femur[:3, 1])
    down = -T_tibia[:3, 1] / np.linalg.norm(T_tibia[:3, 1])
    side = (up - down) / np.linalg.norm(up - down)
    return cylinder_chords(view, center_mm, axis=up, side=side) + cylinder_chords(
        view, center_mm, axis=down, side=-side
    )


def simulate_tka_fluoro(
    knee: TkaKnee,
    motion: TkaMotion,
    detector: DetectorSpec,
    center_mm: np.ndarray,
    photons: float,
    seed: int,
    supersample: int = 3,
    blur_mm: float = 0.3,
    turn_deg: float = 0.0,
) -> tuple[View, np.ndarray]:
    """Lateral fluoroscopy of the knee replacement through ``motion`` (or a camera turned from
    the lateral one), as an image intensifier's video shows it: per pixel the share of the beam
    stopped, ``1 - I / I0``.

    Every part (metal, polyethylene, bone) and the leg's soft tissue (:func:`leg_chords`: the
    thigh's and the shank's water, bent at the knee as the bones are) attenuate along each of
    ``supersample`` x ``supersample`` rays per pixel; the transmitted photons are Poisson
    (``photons`` unattenuated per pixel: metal starves them), then the imaging chain blurs by a
    Gaussian of ``blur_mm`` at the panel.

    Args:
        knee: The knee replacement.
        motion: Its bodies' poses per frame.
        detector: The panel.
        center_mm: The knee's centre, on the central ray (3,), mm.
        photons: Unattenuated photons per pixel.
        seed: The noise's seed.
        supersample: Rays per pixel along each axis.
        blur_mm: The imaging chain's Gaussian sigma at the panel, mm.
        turn_deg: The camera (source and panel) turned about the vertical through
            ``center_mm``, degrees (sim.fluoro.biplane_views's sense: 90 looks from the front);
            0: the lateral view.

    Returns:
        The view, and the frames (F, rows, cols) float32 in [0, 1].
    """
    spec = KneePhantomSpec(side="right")
    center_mm = np.asarray(center_mm, dtype=np.float64)
    # the right knee's medial source swings to the front
    view = turned_view(lateral_view(spec, detector, target_mm=center_mm), center_mm, -turn_deg)
    s = supersample
    fine_panel = DetectorSpec(
        rows=detector.rows * s, cols=detector.cols * s, pixel_pitch_mm=detector.pixel_pitch_mm / s
    )
    fine = turned_view(lateral_view(spec, fine_panel, target_mm=center_mm), center_mm, -turn_deg)
    rng = np.random.default_rng(seed)
    frames = np.empty((len(motion.frames), detector.rows, detector.cols), dtype=np.float32)
    for k in range(len(motion.frames)):
        femur, tibia = (motion.poses[body][k] for body in ("femur_r", "tibia_r"))
        total = WATER_PER_MM * leg_chords(fine, center_mm, femur, tibia)
        for part, mesh in knee.meshes.items():
            lengths = ray_lengths(
                fine,
                np.asarray(mesh.vertices),
                np.asarray(mesh.faces),
                part_poses(knee, motion, part)[k],
            )
            total += knee.materials[part].mu_per_mm(70.0) * lengths
        shown = np.exp(-total).reshape(detector.rows, s, detector.cols, s).mean(axis=(1, 3))
        counts = rng.poisson(photons * shown)
        frames[k] = gaussian_filter(1.0 - counts / photons, blur_mm / detector.pixel_pitch_mm)
    return view, frames
