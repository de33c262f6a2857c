"""The knee replacement on the simulated CBCT: the grand-challenge subject standing in the
scanner, projected polychromatically, so that its metal streaks as on a real scan.

Each view's pixel sees, along ``supersample`` x ``supersample`` rays, the length through every
part's mesh (sim.tka's parts at the stance's pose) and through the leg's soft tissue (a
vertical cylinder of water about the knee, less the parts in it). The tube's spectrum
(sim.spectrum) is attenuated along each ray by every material at every energy, so the metal
hardens the beam and starves the panel of photons (the simulated panel draws the photons'
Poisson noise from the signal left). The projection is ``-ln`` of the transmitted share.

:func:`tka_truth` rasterises the same scene on a volume grid: labels (the bones' as the knee
phantom's, the insert :data:`registration.labels.INSERT_LABEL`, metal :data:`METAL_LABEL`) and the
attenuation a reconstruction of this beam shows, to first order (each material's attenuation
averaged over the spectrum behind the leg).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np
import trimesh
from scipy import ndimage

from recon.geometry import View
from recon.volume import VolumeGrid
from registration.implants import ray_lengths
from registration.labels import INSERT_LABEL, LABELS
from registration.meshes import inside_fraction
from sim.phantoms.tka import TkaPhantomSpec
from sim.spectrum import COMPOSITIONS, Spectrum, tube_spectrum
from sim.sway import BODY_BONES, Sway, SwayingSubject, SwayPivots
from sim.tka import cylinder_chords, load_tka, part_poses, read_gait, tka_motion

BODY_OF_PART = {
    **{bone: body for body, bones in BODY_BONES.items() for bone in bones},
    "femoral_component": "thigh",
    "patellar_button": "thigh",
    "tibial_tray": "shank",
    "tibial_insert": "shank",
}
"""The swaying body (sim.sway) each part of the knee replacement moves with."""
ANKLE_SLAB_MM = 20.0
"""The ankle's centre: that of the tibia's lowest vertices within this of its lowest, mm."""
METAL_LABEL = 7
"""Label of a metal component in :func:`tka_truth`'s labels."""
PART_LABELS = {
    "femur": LABELS["femur"],
    "tibia": LABELS["tibia"],
    "fibula": LABELS["fibula"],
    "patella": LABELS["patella"],
    "tibial_insert": INSERT_LABEL,
    "patellar_button": INSERT_LABEL,
}
"""The truth label of each non-metal part (a metal part's is :data:`METAL_LABEL`)."""
CORTEX_MM = 1.5
"""A bone's cortex: the shell within this of its surface (its mesh moved inward along its
vertex normals), mm; inside, cancellous bone."""
KNEE_HALF_HEIGHT_MM = 40.0
"""The knee's cross-section, centred on the scanner's axis, is that of its parts within this
of the joint's height, mm."""
LEG_FILTRATION_MM = 120.0
"""The water a knee's rays cross on average: the spectrum behind it sets the truth's
attenuation (:func:`tka_truth`), mm."""


@dataclass(frozen=True)
class Layer:
    """A closed surface of the scene and what lies inside it.

    Attributes:
        part: The knee's part it belongs to (sim.tka.PARTS).
        vertices_mm: Its vertices in the world (V, 3), mm.
        faces: Its triangles (T, 3), outward by their winding.
        materials: Composition (sim.spectrum.COMPOSITIONS) -> the length it adds per length
            inside (a bone's outer surface adds cortex, its inner one turns cortex into
            cancellous bone: +1 cancellous, -1 cortex).
    """

    part: str
    vertices_mm: np.ndarray
    faces: np.ndarray
    materials: dict[str, float]

    @property
    def displaces(self) -> float:
        """The soft tissue it displaces per length inside (1 for a part's outer surface)."""
        return sum(self.materials.values())


@dataclass(frozen=True)
class TkaScene:
    """The knee replacement standing: its parts' surfaces in the world, and their materials.

    Attributes:
        spec: What it was made from.
        layers: Every surface: each part's outer one, and each bone's cortex's inner one.
        poses: Each part's ``T_world_part`` (its mesh in sim.tka's body frame, 4x4, mm).
    """

    spec: TkaPhantomSpec
    layers: tuple[Layer, ...]
    poses: dict[str, np.ndarray]

    def line_integrals(
        self, view: View, spectrum: Spectrum, poses: Mapping[str, np.ndarray] | None = None
    ) -> np.ndarray:
        """``-ln`` of the signal's transmitted share per pixel (rows, cols), float64: the
        polychromatic beam along every ray of the pixel, averaged over them.

        Args:
            view: the view.
            spectrum: the tube's.
            poses: ``T_world_body`` (4x4, mm) of the swaying patient's bodies (sim.sway's
                ``thigh`` and ``shank``: each part goes with :data:`BODY_OF_PART`'s, the leg's
                soft tissue with the thigh above the joint's height and with the shank below);
                None: the patient stands at the reference pose.
        """
        s = self.spec.supersample
        fine = _finer(view, s)
        lengths: dict[str, np.ndarray] = {}
        inside = np.zeros((fine.rows, fine.cols))
        for layer in self.layers:
            pose = np.eye(4) if poses is None else poses[BODY_OF_PART[layer.part]]
            length = ray_lengths(fine, layer.vertices_mm, layer.faces, pose).astype(float)
            for material, amount in layer.materials.items():
                lengths[material] = lengths.get(material, 0.0) + amount * length
            inside += layer.displaces * length
        leg = self._leg_chords(fine, poses)
        lengths["water"] = lengths.get("water", 0.0) + np.maximum(leg - inside, 0.0)
        mu = np.stack([COMPOSITIONS[n].mu_per_mm(spectrum.energies_kev) for n in lengths])
        shown = spectrum.transmission(mu, np.maximum(np.stack(list(lengths.values())), 0.0))
        shown = shown.reshape(view.rows, s, view.cols, s).mean(axis=(1, 3))
        return -np.log(np.maximum(shown, 1e-300))

    def _leg_chords(self, view: View, poses: Mapping[str, np.ndarray] | None) -> np.ndarray:
        """Each pixel's ray length through the leg's water cylinder, mm: whole, or in two
        halves cut at the joint's height, the upper moved with the thigh, the lower with the
        shank."""
        centre, radius = self.spec.center_mm, self.spec.leg_radius_mm
        if poses is None:
            return cylinder_chords(view, centre, radius)
        up = np.array([0.0, 0.0, 1.0])
        return sum(
            cylinder_chords(view.transformed(np.linalg.inv(poses[body])), centre, radius, side=side)
            for body, side in (("thigh", up), ("shank", -up))
        )


def _finer(view: View, s: int) -> View:
    """The view with every pixel split into ``s`` x ``s`` (their centres)."""
    if s == 1:
        return view
    shift = 0.5 * (1.0 / s - 1.0) * (view.pitch_u_mm * view.e_u + view.pitch_v_mm * view.e_v)
    return View(
        view.source_mm,
        view.detector_origin_mm + shift,
        view.e_u,
        view.e_v,
        view.pitch_u_mm / s,
        view.pitch_v_mm / s,
        view.rows * s,
        view.cols * s,
    )


def tka_scene(spec: TkaPhantomSpec) -> TkaScene:
    """The knee replacement of ``spec`` standing in the scanner.

    Raises:
        FileNotFoundError: no grand-challenge data at ``spec.data``.
    """
    folder = Path(spec.data)
    gait_path = folder / "kinematics" / "fluoroscopic_gait.sto"
    if not gait_path.is_file():
        raise FileNotFoundError(
            f"phantom data {folder}: no kinematics/fluoroscopic_gait.sto (the grand-challenge-tka "
            "folder of ../shared/data)"
        )
    knee = load_tka(folder)
    gait = read_gait(gait_path)
    samples = len(gait["time"])
    if spec.gait_sample >= samples:
        raise ValueError(f"gait_sample {spec.gait_sample}: the gait file has {samples} samples")
    one = {k: v[spec.gait_sample : spec.gait_sample + 1] for k, v in gait.items()}
    motion = tka_motion(knee, one, 1, spec.center_mm)
    poses = {part: part_poses(knee, motion, part)[0] for part in knee.meshes}
    near = np.concatenate(
        [m.vertices @ poses[p][:3, :3].T + poses[p][:3, 3] for p, m in knee.meshes.items()]
    )
    near = near[np.abs(near[:, 2] - spec.joint_height_mm) <= KNEE_HALF_HEIGHT_MM]
    shift = np.eye(4)  # the knee's cross-section centred on the scanner's axis
    shift[:2, 3] = -0.5 * (near[:, :2].min(axis=0) + near[:, :2].max(axis=0))
    poses = {part: shift @ pose for part, pose in poses.items()}
    layers = []
    for part, mesh in knee.meshes.items():
        placed = mesh.copy().apply_transform(poses[part])
        vertices, faces = np.asarray(placed.vertices, float), np.asarray(placed.faces)
        material = knee.materials[part]
        if material.name == "bone":
            layers.append(Layer(part, vertices, faces, {"cortical_bone": 1.0}))
            inner = vertices - CORTEX_MM * np.asarray(placed.vertex_normals)
            layers.append(
                Layer(part, inner, faces, {"cancellous_bone": 1.0, "cortical_bone": -1.0})
            )
        else:
            name = material.name if (spec.metal or not material.radiopaque) else "cancellous_bone"
            layers.append(Layer(part, vertices, faces, {name: 1.0}))
    return TkaScene(spec, tuple(layers), poses)


def tka_subject(
    scene: TkaScene, kvp: float, sway: Sway | None = None
) -> Callable[[View, float], np.ndarray]:
    """The scene as the simulated panel sees it at ``kvp``: polychromatic line integrals per
    view (the panel draws the photons' noise); the patient stands still at any time, or sways
    as ``sway`` says (a :class:`SwayingTka`)."""
    if sway is not None and sway.spec.peak_mm > 0:
        return SwayingTka(scene, kvp, sway)
    spectrum = tube_spectrum(kvp)
    return lambda view, t_s=0.0: scene.line_integrals(view, spectrum)


class SwayingTka(SwayingSubject):
    """The knee replacement while the patient sways: every part at its body's pose at the
    pulse's time."""

    def __init__(self, scene: TkaScene, kvp: float, sway: Sway) -> None:
        super().__init__(sway)
        self.scene, self._spectrum = scene, tube_spectrum(kvp)

    def __call__(self, view: View, t_s: float = 0.0) -> np.ndarray:
        return self.scene.line_integrals(view, self._spectrum, self.poses_at(t_s))


def tka_pivots(scene: TkaScene) -> SwayPivots:
    """Where the knee replacement's leg sways about: the ankle at the tibia's lower end, the
    knee at the femoral component's centre, the transepicondylar axis horizontal and across
    the line from the knee to the patella, the patella's and the insert's centres."""

    def outer(part: str) -> np.ndarray:
        return next(layer.vertices_mm for layer in scene.layers if layer.part == part)

    knee, patella = outer("femoral_component").mean(axis=0), outer("patella").mean(axis=0)
    forward = np.array([*(patella - knee)[:2], 0.0])
    tea = np.cross(forward, [0.0, 0.0, 1.0])
    tibia = outer("tibia")
    low = tibia[tibia[:, 2] <= tibia[:, 2].min() + ANKLE_SLAB_MM]
    return SwayPivots(
        ankle_mm=low.mean(axis=0),
        knee_mm=knee,
        tea=tea / np.linalg.norm(tea),
        patella_mm=patella,
        plateau_mm=outer("tibial_insert").mean(axis=0),
    )


def beam_behind_leg(kvp: float) -> Spectrum:
    """The tube's spectrum behind the leg's mean water path (the truth's)."""
    return tube_spectrum(kvp).hardened("water", LEG_FILTRATION_MM)


@dataclass(frozen=True)
class TkaTruth:
    """The scene on a grid.

    Attributes:
        grid: The grid.
        labels: Each voxel's part (the one that fills most of it; soft tissue inside the leg's
            cylinder, air outside), uint8 [z, y, x].
        mu: The parts' attenuations by the share each fills, float32 [z, y, x], 1/mm.
        metal_share: The share of each voxel that is metal, float32 [z, y, x].
    """

    grid: VolumeGrid
    labels: np.ndarray
    mu: np.ndarray
    metal_share: np.ndarray

    @cached_property
    def metal_zone(self) -> np.ndarray:
        """Voxels with any metal (a thin fin fills under half of its voxels), and those
        touching them: where neither bone nor tissue can be scored."""
        return ndimage.binary_dilation(self.metal_share > METAL_SHARE_SCORED)

    def near_metal_scores(self, labels: np.ndarray) -> dict[str, float]:
        """How a segmentation's bones match the truth's within :data:`NEAR_METAL_MM` of the
        metal (outside :attr:`metal_zone`).

        Args:
            labels: A segmentation (registration.labels.LABELS) on the grid, [z, y, x].

        Returns:
            The Dice of all bone together (``bone``) and of each bone by name.
        """
        distance = ndimage.distance_transform_edt(
            self.metal_share <= METAL_SHARE_SCORED, sampling=self.grid.spacing_mm[::-1]
        )
        near = (distance <= NEAR_METAL_MM) & ~self.metal_zone
        bones = {name: (LABELS[name],) for name in ("femur", "tibia", "fibula", "patella")}
        bones["bone"] = tuple(LABELS[name] for name in ("femur", "tibia", "fibula", "patella"))
        scores = {}
        for name, values in bones.items():
            ours, theirs = np.isin(labels, values) & near, np.isin(self.labels, values) & near
            total = int(ours.sum() + theirs.sum())
            scores[name] = 2.0 * float((ours & theirs).sum()) / total if total else float("nan")
        return scores

    def rmse_outside_metal(self, volume: np.ndarray) -> float:
        """The RMSE of a reconstruction against :attr:`mu` in the leg outside
        :attr:`metal_zone`, 1/mm."""
        inside = (self.labels != LABELS["air"]) & ~self.metal_zone
        return float(np.sqrt(np.mean((np.asarray(volume)[inside] - self.mu[inside]) ** 2)))


def tka_truth(scene: TkaScene, grid: VolumeGrid, kvp: float) -> TkaTruth:
    """The scene on ``grid`` (:class:`TkaTruth`), its attenuation as a scan at ``kvp`` shows
    it to first order."""
    beam = beam_behind_leg(kvp)
    x_mm, y_mm, _ = grid.axes_mm()
    y, x = np.meshgrid(y_mm, x_mm, indexing="ij")
    centre = scene.spec.center_mm
    leg = (x - centre[0]) ** 2 + (y - centre[1]) ** 2 <= scene.spec.leg_radius_mm**2
    leg = np.broadcast_to(leg, grid.shape)
    water = beam.mean_mu_per_mm("water")
    mu = np.where(leg, water, 0.0).astype(np.float32)
    labels = np.where(leg, LABELS["soft_tissue"], LABELS["air"]).astype(np.uint8)
    metal_share = np.zeros(grid.shape, dtype=np.float32)
    best = np.zeros(grid.shape, dtype=np.float32)
    for layer in scene.layers:
        surface = trimesh.Trimesh(layer.vertices_mm, layer.faces, process=False)
        fraction = inside_fraction(surface, grid)
        for material, amount in layer.materials.items():
            mu += (amount * fraction * beam.mean_mu_per_mm(material)).astype(np.float32)
        mu -= (layer.displaces * fraction * water).astype(np.float32)
        if layer.displaces == 0.0:
            continue
        metal = bool(set(layer.materials) & {"CoCr", "Ti6Al4V"})
        if metal:
            metal_share += fraction
        label = METAL_LABEL if metal else PART_LABELS[layer.part]
        wins = fraction > np.maximum(best, 0.5 - 1e-6)
        labels[wins] = label
        best = np.maximum(best, fraction)
    return TkaTruth(grid, labels, mu, metal_share)


NEAR_METAL_MM = 20.0
"""The bone scored next to the implant: within this of the metal, mm."""
METAL_SHARE_SCORED = 0.01
"""A voxel with more metal than this share is metal to the scores."""
