"""Dynamic single-plane (lateral) fluoroscopy of the knee phantom, with ground-truth bone poses.

A fluoroscopy sequence is one fixed lateral view (:func:`lateral_view`) watching the phantom
move (:mod:`sim.motion`). Rendering (:func:`simulate_fluoroscopy`):

1. The phantom is rasterised once, at its reference pose (the static scan), on a grid holding
   every part of the leg that any frame brings into the field of view (``voxel_mm``,
   2 x 2 x 2 sub-samples per voxel).
2. The scene is split into a soft-tissue volume, where the bones *displace* soft tissue (every
   bone voxel holds skeletal muscle: moving a bone leaves no bone-shaped hole), and per bone an
   excess volume ``mu - mu_muscle`` on the bone's voxels (its labelled voxels plus the
   partial-volume rim around them), cropped to the bone. Their sum is the reference
   attenuation, voxel for voxel, before the soft tissue is averaged onto its
   :data:`SOFT_TISSUE_MM` grid (with 0.5 mm voxels, the reference frame then differs from the
   projection of the reference attenuation by 0.004 rms, 0.06 at most at the skin's edge).
3. Frame k: each bone's excess volume is projected rigidly at its true pose ``T_b(k)``
   (moving a volume by T is moving the scanner by T^-1, :func:`move_view`), and the soft tissue
   is deformed non-rigidly: the pull-back of a point x is a blend ``(1 - w) T_tibia^-1 x +
   w T_femur^-1 x``, with ``w`` a sigmoid across the joint line (the plane through the midpoint
   of the knee centre and the tibial plateau centre, normal to the bisector of the femoral and
   tibial long axes; 10-90 % over :data:`JOINT_BLEND_WIDTH_MM`), resampled trilinearly (a
   numba kernel) on a :data:`SOFT_TISSUE_MM` grid, then projected.
4. ``realism="ideal"`` stops there: line integrals ``-ln(I/I0)``, float32. ``"independent"``
   (an image model the registration does not share) adds, in this order: beam hardening
   ``p -> p - beta p^2`` (:data:`BEAM_HARDENING_BETA`); scatter, a low-frequency background
   proportional to the fluence the object removes from the primary beam, Gaussian-blurred
   (:data:`SCATTER_SIGMA_MM` at the detector, :data:`SCATTER_PER_ATTENUATED`); detector blur
   (:data:`DETECTOR_BLUR_PX`); radial pincushion distortion (:func:`distort`,
   :data:`DISTORTION_MAX_MM` at the panel corners); Poisson quantum noise plus Gaussian
   readout noise (:func:`add_fluoro_noise`).

Cost: rasterising dominates (~20 s at 0.5 mm for a 90-degree squat, whose thigh sweeps
through the field); a 30-frame sequence takes ~30 s on 2 cores at 256^2 or 512^2 pixels.

The views follow recon.geometry: rows increase upward (``e_v = +z``), so display frames with
``origin="lower"``. The world frame is LPS, mm (docs/conventions.md).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numba
import numpy as np
from scipy import ndimage
from scipy.spatial.transform import Rotation

from calibration.dewarp_grid import DewarpGridSpec
from recon.config import ExposureSpec
from recon.geometry import DetectorSpec, Geometry, View
from recon.io import write_projections
from recon.project import forward_project
from recon.rtk_xml import write_rtk_geometry
from recon.volume import Volume, VolumeGrid
from registration.labels import BONE_LABELS, LABELS
from registration.poses import BodyPose, check_rigid, write_poses
from sim.motion import BONES, KneeMotion
from sim.phantoms.knee import (
    KneePhantomSpec,
    attenuation_per_mm,
    knee_bone_poses,
    knee_landmarks,
    knee_sdf,
    rasterize_knee,
)
from sim.scan import add_noise
from sim.scan import photons_per_pixel as exposure_photons_per_pixel

Realism = Literal["independent", "ideal"]
Projector = Callable[[np.ndarray, VolumeGrid, Geometry], np.ndarray]
"""Line integrals of a volume (values on a grid) through views, float32 (views, rows, cols):
recon.project.forward_project, or a peer's (recon.rtk_peer.rtk_forward_project)."""

FRAME_RATE_HZ = 15.0
"""Default frame rate of the fluoroscope, frames per second."""

FLUORO_EXPOSURE = ExposureSpec(tube_kv=70.0, tube_ma=80.0, pulse_ms=4.0)
"""Pulsed technique per frame (as in configs/protocols/knee_fluoroscopy_lateral.yaml):
~2.0e4 unattenuated photons per 0.3 mm pixel at SDD 1.2 m (sim.scan.photons_per_pixel)."""

BEAM_HARDENING_BETA = 0.015
"""``p -> p - beta p^2``: a knee's ~4 line-integral units lose ~6 % (polychromatic beam)."""

SCATTER_PER_ATTENUATED = 0.015
"""Scatter reaching the detector per unit of fluence removed from the primary (x I0), before
the blur: a scatter-to-primary ratio of ~0.3 behind the knee (line integrals > 3) and < 0.2 %
of I0 beside the leg."""

SCATTER_SIGMA_MM = 30.0
"""Gaussian width of the scatter background at the detector, mm."""

DETECTOR_BLUR_PX = 0.6
"""Gaussian detector blur (scintillator spread), pixels (sigma)."""

DISTORTION_MAX_MM = 0.6
"""Radial pincushion displacement at the panel corners, mm (a property of the panel: 1 pixel
of a 512^2 read-out of the 307 mm panel, 2 pixels at its native 0.3 mm pitch)."""

JOINT_BLEND_WIDTH_MM = 30.0
"""Soft tissue follows the tibia below and the femur above the joint line; the weight of the
femur's motion rises from 10 % to 90 % over this distance across the joint line, mm."""

SOFT_TISSUE_MM = 1.0
"""Grid spacing on which the soft tissue is deformed each frame, mm (voxel_mm if coarser)."""

_COARSE_MM = 5.0  # spacing of the points that find which part of the leg the frames see
_MARGIN_MM = 10.0  # around that part, and around the deformed soft tissue in the field
_FIELD_MARGIN_PX = 4.0  # a point counts as in the field this far outside the panel


@dataclass(frozen=True)
class FluoroSequence:
    """A simulated fluoroscopy sequence and its ground truth.

    Attributes:
        frames: line integrals -ln(I/I0), float32 (F, rows, cols), indexed [frame, v, u].
        counts: detected photons per pixel, float32 (F, rows, cols); None for ``"ideal"``.
        view: the (fixed) fluoroscopy view.
        times_s: acquisition time of each frame, s (F,).
        poses: bone -> ``T_world_body`` (F, 4, 4) from the reference pose, mm ("femur",
            "tibia", "fibula", "patella", "tibia_fibula").
        flexion_deg: true knee flexion per frame, degrees (F,).
        attenuation: the reference phantom the frames were rendered from, 1/mm.
        labels: its labels (registration.labels.LABELS) on the same grid.
        photons_per_pixel: mean unattenuated photons per pixel per frame (0 when ideal).
        realism: "ideal" or "independent" (see the module docstring).
    """

    frames: np.ndarray
    counts: np.ndarray | None
    view: View
    times_s: np.ndarray
    poses: dict[str, np.ndarray]
    flexion_deg: np.ndarray
    attenuation: Volume
    labels: Volume
    photons_per_pixel: float
    realism: Realism


# -- geometry ------------------------------------------------------------------------------------


def move_view(view: View, T: np.ndarray) -> View:
    """The view moved rigidly by ``T`` (4x4, checked rigid): source, panel and axes move.

    A world point x seen at pixel (u, v) by ``view`` is seen at the same pixel by the moved
    view at ``T x``. So projecting a volume moved by T through ``view`` equals projecting the
    unmoved volume through ``move_view(view, T^-1)`` (recon.geometry.View.transformed).
    """
    return view.transformed(check_rigid(T, "move_view"))


def turned_view(view: View, point_mm: np.ndarray, angle_deg: float) -> View:
    """``view`` (source and panel) turned by ``angle_deg`` about the vertical (world z) through
    ``point_mm``, counter-clockwise seen from above.

    Args:
        view: The view.
        point_mm: A point of the vertical turned about (3,), world mm.
        angle_deg: The turn, degrees.
    """
    point = np.asarray(point_mm, dtype=np.float64)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", angle_deg, degrees=True).as_matrix()
    T[:3, 3] = point - T[:3, :3] @ point
    return move_view(view, T)


def lateral_view(
    spec: KneePhantomSpec,
    detector: DetectorSpec,
    sid_mm: float = 800.0,
    sdd_mm: float = 1200.0,
    target_mm: np.ndarray | None = None,
) -> View:
    """Lateral fluoroscopy view of the knee: source medial, panel lateral, rows upward.

    The central ray (source to panel centre) is horizontal along the world x axis through
    ``target_mm``, by default the tibial plateau centre of the reference pose (the knee centre
    at the joint line, world z = ``spec.joint_line_height_mm``). ``e_v = +z``; ``e_u`` points
    posterior for a right knee (anterior for a left one), so ``e_u x e_v`` points back at the
    source. This is ``OrbitSpec(kind="static", start_deg=90)`` (right) or ``-90`` (left) with
    ``isocenter_mm = target_mm``.

    Args:
        spec: the phantom (side and joint line).
        detector: the panel.
        sid_mm: source to ``target_mm`` distance, mm.
        sdd_mm: source to panel distance, mm (> sid_mm).
        target_mm: world point on the central ray at ``sid_mm`` from the source, mm (3,).
    """
    if not (0.0 < sid_mm < sdd_mm and math.isfinite(sdd_mm)):
        raise ValueError(f"need 0 < sid_mm < sdd_mm, got sid {sid_mm!r}, sdd {sdd_mm!r} mm")
    if target_mm is None:
        target = knee_landmarks(spec)["tibial_plateau_center"]
    else:
        target = np.asarray(target_mm, dtype=np.float64).reshape(3)
    medial = np.array([1.0 if spec.side == "right" else -1.0, 0.0, 0.0])
    e_v = np.array([0.0, 0.0, 1.0])
    return View.from_center(
        source_mm=target + sid_mm * medial,
        detector_center_mm=target - (sdd_mm - sid_mm) * medial,
        e_u=np.cross(e_v, medial),
        e_v=e_v,
        detector=detector,
    )


def biplane_views(
    spec: KneePhantomSpec,
    detector: DetectorSpec,
    angle_deg: float = 90.0,
    sid_mm: float = 800.0,
    sdd_mm: float = 1200.0,
) -> tuple[View, View]:
    """Two fluoroscopy views of the knee ``angle_deg`` apart: the :func:`lateral_view`, and
    the same source and panel turned about the vertical line through the tibial plateau
    centre (toward anterior; 90 degrees: the anterior-posterior view, source in front).

    Args:
        spec: the phantom (side and joint line).
        detector: both panels.
        angle_deg: the angle between the central rays, degrees in [20, 160] (nearly parallel
            views resolve depth no better than one).
        sid_mm: source to the plateau centre, mm.
        sdd_mm: source to panel, mm (> sid_mm).
    """
    if not 20.0 <= angle_deg <= 160.0:
        raise ValueError(f"angle_deg must be in [20, 160] degrees, got {angle_deg!r}")
    lateral = lateral_view(spec, detector, sid_mm, sdd_mm)
    target = knee_landmarks(spec)["tibial_plateau_center"]
    turn = -1.0 if spec.side == "right" else 1.0  # the medial source swings to the front
    return lateral, turned_view(lateral, target, turn * angle_deg)


def default_photons_per_pixel(view: View) -> float:
    """Unattenuated photons per pixel of ``view`` per frame at :data:`FLUORO_EXPOSURE`."""
    panel = DetectorSpec(rows=view.rows, cols=view.cols, pixel_pitch_mm=view.pitch_u_mm)
    area_ratio = view.pitch_v_mm / view.pitch_u_mm  # non-square pixels scale with their area
    return exposure_photons_per_pixel(FLUORO_EXPOSURE, panel, view.sdd_mm) * area_ratio


# -- image model -----------------------------------------------------------------------------------


def add_fluoro_noise(
    line_integrals: np.ndarray, photons: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Detector counts and the noisy line integrals measured from them.

    The scan's detector model (sim.scan.add_noise): counts are Poisson(photons exp(-p)) plus
    Gaussian readout noise (sim.scan.ELECTRONIC_NOISE_PHOTONS), clipped to >= 1 photon.

    Args:
        line_integrals: noise-free -ln(I/I0), any shape.
        photons: mean unattenuated photons per pixel, > 0.
        rng: random generator.

    Returns:
        counts (float32) and line integrals -ln(counts / photons) (float32), both of the
        input's shape.
    """
    if not (math.isfinite(photons) and photons > 0.0):
        raise ValueError(f"photons must be a finite count > 0, got {photons!r}")
    return add_noise(np.asarray(line_integrals), photons, rng)


def distort(images: np.ndarray, max_px: float) -> np.ndarray:
    """Radial pincushion distortion about the panel centre, applied by resampling.

    A point at radius r pixels from the panel centre (((cols - 1) / 2, (rows - 1) / 2)) is
    imaged at radius ``r + max_px (r / R)^3``, R the half diagonal: the displacement is 0 at
    the centre, ``max_px`` at the corners and ``max_px / 2^1.5`` at the middle of the edges
    of a square panel. Negative ``max_px`` gives barrel distortion. Bilinear resampling,
    edges extended.

    Args:
        images: (rows, cols) or (F, rows, cols) images.
        max_px: displacement at the corners, pixels.

    Returns:
        float32 images of the input's shape.
    """
    arr = np.asarray(images, dtype=np.float32)
    if arr.ndim not in (2, 3):
        raise ValueError(f"images must be (rows, cols) or (F, rows, cols), got {arr.shape}")
    rows, cols = arr.shape[-2:]
    cv, cu = 0.5 * (rows - 1), 0.5 * (cols - 1)
    k = max_px / max(math.hypot(cu, cv), 1.0) ** 3
    dv, du = np.meshgrid(np.arange(rows) - cv, np.arange(cols) - cu, indexing="ij")
    r_out = np.hypot(du, dv)
    r_in = r_out.copy()  # solve r_in + k r_in^3 = r_out (Newton)
    for _ in range(4):
        r_in -= (r_in + k * r_in**3 - r_out) / (1.0 + 3.0 * k * r_in**2)
    scale = np.divide(r_in, r_out, out=np.ones_like(r_out), where=r_out > 0.0)
    coords = np.stack((cv + dv * scale, cu + du * scale))
    flat = arr.reshape(-1, rows, cols)
    out = np.stack([ndimage.map_coordinates(img, coords, order=1, mode="nearest") for img in flat])
    return out.reshape(arr.shape)


def _blur_large(images: np.ndarray, sigma_px: float) -> np.ndarray:
    """Gaussian blur (F, rows, cols) of a wide sigma by FFT, edges reflected."""
    pad = min(math.ceil(3.0 * sigma_px), 4 * max(images.shape[1:]))
    padded = np.pad(images.astype(np.float64), ((0, 0), (pad, pad), (pad, pad)), mode="reflect")
    spectrum = ndimage.fourier_gaussian(
        np.fft.rfft2(padded), (0.0, sigma_px, sigma_px), n=padded.shape[-1]
    )
    blurred = np.fft.irfft2(spectrum, s=padded.shape[1:])
    return blurred[:, pad:-pad, pad:-pad] if pad else blurred


def _realistic(
    ideal: np.ndarray, view: View, photons: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Counts and measured line integrals of ideal ones (F, rows, cols): beam hardening,
    scatter, detector blur, distortion, quantum and readout noise (module docstring)."""
    p = ideal.astype(np.float64)
    primary = np.exp(-(p - BEAM_HARDENING_BETA * p * p))
    sigma_px = SCATTER_SIGMA_MM / view.pitch_u_mm
    scatter = SCATTER_PER_ATTENUATED * np.maximum(_blur_large(1.0 - primary, sigma_px), 0.0)
    detected = ndimage.gaussian_filter(
        primary + scatter, (0.0, DETECTOR_BLUR_PX, DETECTOR_BLUR_PX), mode="nearest"
    )
    detected = distort(detected, DISTORTION_MAX_MM / view.pitch_u_mm)
    return add_fluoro_noise(-np.log(detected), photons, rng)


# -- scene -----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Scene:
    """The reference phantom split for rendering (module docstring, step 2)."""

    attenuation: Volume
    labels: Volume
    soft: Volume  # soft tissue, bones displaced, on a SOFT_TISSUE_MM lattice
    excess: dict[str, Volume]  # bone -> mu - mu_muscle on the bone, cropped
    soft_out: VolumeGrid  # where the deformed soft tissue is sampled, same lattice as soft


def _leg_points(spec: KneePhantomSpec) -> np.ndarray:
    """Points (N, 3) mm on a coarse lattice inside the skin at the reference pose."""
    marks = knee_landmarks(spec)
    ankle, knee = marks["ankle_center"], marks["knee_center"]
    thigh_top = knee + 500.0 * spec.scale * marks["femoral_anatomical_axis"]
    ends = np.stack((ankle * [1.0, 1.0, 0.0], ankle, knee, thigh_top))
    reach = 1.5 * spec.soft_tissue_radius_mm + _COARSE_MM
    lo = np.maximum(ends.min(axis=0) - reach, [-np.inf, -np.inf, 0.0])
    hi = ends.max(axis=0) + reach
    axes = [np.arange(a, b + _COARSE_MM, _COARSE_MM) for a, b in zip(lo, hi, strict=True)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    return pts[knee_sdf(spec, "skin", pts) < 0.0]


def _in_field(matrices: np.ndarray, points_h: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """(N, F) True where homogeneous points (N, 4) project through each 3x4 matrix (F, 3, 4)
    in front of the source onto a ``rows x cols`` panel (within a small margin)."""
    h = (points_h @ matrices.reshape(-1, 4).T).reshape(len(points_h), -1, 3)
    u, v, w = h[..., 0], h[..., 1], h[..., 2]
    m = _FIELD_MARGIN_PX
    return (
        (w > 0.0)
        & (u >= -m * w)
        & (u <= (cols - 1 + m) * w)
        & (v >= -m * w)
        & (v <= (rows - 1 + m) * w)
    )


def _field_boxes(
    spec: KneePhantomSpec, poses: dict[str, np.ndarray], view: View
) -> tuple[np.ndarray, np.ndarray]:
    """Reference box (2, 3) holding every leg point any bone's motion brings into the field
    at some frame, and frame box (2, 3) holding those points moved by the femur and tibia."""
    pts = _leg_points(spec).astype(np.float32)
    pts_h = np.hstack((pts, np.ones((len(pts), 1), dtype=np.float32)))
    needed = np.zeros(len(pts), dtype=bool)
    moved_lo, moved_hi = np.full(3, np.inf), np.full(3, -np.inf)
    for bone in BONES:
        seen = _in_field(
            (view.matrix @ poses[bone]).astype(np.float32), pts_h, view.rows, view.cols
        )
        needed |= seen.any(axis=1)
        if bone not in ("femur", "tibia"):
            continue
        for T, seen_k in zip(poses[bone], seen.T, strict=True):
            if seen_k.any():
                moved = pts[seen_k] @ T[:3, :3].T + T[:3, 3]
                moved_lo = np.minimum(moved_lo, moved.min(axis=0))
                moved_hi = np.maximum(moved_hi, moved.max(axis=0))
    if not needed.any():
        raise ValueError("the leg never enters the field of view: aim the view at the knee")
    margin = _MARGIN_MM + _COARSE_MM
    reference = np.stack((pts[needed].min(axis=0) - margin, pts[needed].max(axis=0) + margin))
    return reference.astype(np.float64), np.stack((moved_lo - margin, moved_hi + margin))


def _grid_over(box: np.ndarray, spacing_mm: float) -> VolumeGrid:
    n = np.ceil((box[1] - box[0]) / spacing_mm).astype(int) + 1
    return VolumeGrid(shape=(n[2], n[1], n[0]), spacing_mm=(spacing_mm,) * 3, origin_mm=box[0])


def _lattice_grid(lattice: VolumeGrid, box: np.ndarray) -> VolumeGrid:
    """Grid on ``lattice``'s voxel centres covering ``box`` (2, 3) mm."""
    spacing = np.asarray(lattice.spacing_mm)
    first = np.floor((box[0] - lattice.origin_mm) / spacing)
    last = np.ceil((box[1] - lattice.origin_mm) / spacing)
    n = (last - first).astype(int) + 1
    origin = np.asarray(lattice.origin_mm) + first * spacing
    return VolumeGrid(shape=(n[2], n[1], n[0]), spacing_mm=lattice.spacing_mm, origin_mm=origin)


def _block_mean(volume: np.ndarray, grid: VolumeGrid, factor: int) -> Volume:
    """Mean over factor^3 blocks (trailing voxels that fill no block are dropped)."""
    if factor == 1:
        return Volume(volume, grid)
    nz, ny, nx = (n // factor for n in volume.shape)
    cut = volume[: nz * factor, : ny * factor, : nx * factor]
    data = cut.reshape(nz, factor, ny, factor, nx, factor).mean(axis=(1, 3, 5), dtype=np.float64)
    spacing = tuple(s * factor for s in grid.spacing_mm)
    origin = tuple(
        o + 0.5 * (factor - 1) * s for o, s in zip(grid.origin_mm, grid.spacing_mm, strict=True)
    )
    return Volume(data.astype(np.float32), VolumeGrid(data.shape, spacing, origin))


def _bounding_slices(mask: np.ndarray, pad: int) -> tuple[slice, ...]:
    """Index slices [z, y, x] of the bounding box of a non-empty mask, grown by ``pad``."""
    out = []
    for axis, n in enumerate(mask.shape):
        hit = np.flatnonzero(mask.any(axis=tuple(a for a in range(3) if a != axis)))
        out.append(slice(max(int(hit[0]) - pad, 0), min(int(hit[-1]) + pad + 1, n)))
    return tuple(out)


def _bone_excess(
    labels: np.ndarray, mu: np.ndarray, grid: VolumeGrid, mu_muscle: float
) -> tuple[dict[str, Volume], np.ndarray]:
    """Per bone, mu - mu_muscle on its voxels (labels dilated by one voxel into soft tissue:
    the partial-volume rim), cropped with 2 zero voxels around; and the union mask."""
    taken = labels >= LABELS["femur"]  # voxels already given to a bone
    union = np.zeros(labels.shape, dtype=bool)
    excess = {}
    for bone in BONES:
        own = labels == LABELS[bone]
        if not own.any():
            continue
        box = _bounding_slices(own, pad=2)
        rim = ndimage.binary_dilation(own[box], np.ones((3, 3, 3), dtype=bool)) & ~taken[box]
        mask = own[box] | rim
        taken[box] |= rim
        union[box] |= mask
        data = np.where(mask, mu[box] - np.float32(mu_muscle), np.float32(0.0))
        first_xyz = np.array([sl.start for sl in box[::-1]])
        origin = np.asarray(grid.origin_mm) + first_xyz * grid.spacing_mm
        excess[bone] = Volume(
            data.astype(np.float32), VolumeGrid(data.shape, grid.spacing_mm, origin)
        )
    return excess, union


def _build_scene(
    spec: KneePhantomSpec, motion: KneeMotion, view: View, voxel_mm: float, say
) -> _Scene:
    reference_box, frame_box = _field_boxes(spec, motion.poses, view)
    grid = _grid_over(reference_box, voxel_mm)
    say(f"rasterising the reference knee on {grid.size_xyz} voxels of {voxel_mm} mm")
    labels, mu = rasterize_knee(spec, grid, supersample=2)
    mu_muscle = attenuation_per_mm(spec.effective_energy_kev)["muscle"]
    excess, bone_voxels = _bone_excess(labels, mu, grid, mu_muscle)
    soft_full = np.where(bone_voxels, np.float32(mu_muscle), mu)
    factor = max(1, round(SOFT_TISSUE_MM / voxel_mm))
    soft = _block_mean(soft_full, grid, factor)
    return _Scene(
        attenuation=Volume(mu, grid),
        labels=Volume(labels, grid, "label"),
        soft=soft,
        excess=excess,
        soft_out=_lattice_grid(soft.grid, frame_box),
    )


# -- rendering -------------------------------------------------------------------------------------


def _render_bones(
    scene: _Scene, poses: dict[str, np.ndarray], view: View, projector: Projector
) -> np.ndarray:
    """Sum over bones of each excess volume projected at its pose, (F, rows, cols)."""
    total = np.zeros((len(poses["femur"]), view.rows, view.cols), dtype=np.float32)
    for bone, volume in scene.excess.items():
        views = Geometry([move_view(view, np.linalg.inv(T)) for T in poses[bone]])
        total += projector(volume.data, volume.grid, views)
    return total


def _deformed_soft_tissue(
    scene: _Scene, T_femur: np.ndarray, T_tibia: np.ndarray, axes: dict[str, np.ndarray]
) -> np.ndarray:
    """The soft tissue at one frame on ``scene.soft_out`` (module docstring, step 3).

    ``axes`` holds the reference long axes and origins of the femur and tibia (world mm).
    """
    f_axis = T_femur[:3, :3] @ axes["femur_z"]
    t_axis = T_tibia[:3, :3] @ axes["tibia_z"]
    normal = (f_axis + t_axis) / np.linalg.norm(f_axis + t_axis)
    center = 0.5 * (
        T_femur[:3, :3] @ axes["femur_o"]
        + T_femur[:3, 3]
        + T_tibia[:3, :3] @ axes["tibia_o"]
        + T_tibia[:3, 3]
    )
    tau = JOINT_BLEND_WIDTH_MM / (2.0 * math.log(9.0))
    to_index = np.diag(1.0 / np.asarray(scene.soft.grid.spacing_mm))
    origin = np.asarray(scene.soft.grid.origin_mm)
    A = np.empty((2, 3, 3))  # world -> reference voxel index (x, y, z): tibia, femur
    b = np.empty((2, 3))
    for k, T in enumerate((T_tibia, T_femur)):
        inv = np.linalg.inv(T)
        A[k], b[k] = to_index @ inv[:3, :3], to_index @ (inv[:3, 3] - origin)
    out = scene.soft_out
    result = np.empty(out.shape, dtype=np.float32)
    _pull_back_kernel(
        scene.soft.data,
        np.asarray(out.origin_mm),
        np.asarray(out.spacing_mm),
        A,
        b,
        normal / tau,
        center,
        result,
    )
    return result


@numba.njit(parallel=True, fastmath=True, cache=True, error_model="numpy")
def _pull_back_kernel(soft, origin, spacing, A, b, slope, center, out):  # pragma: no cover
    """out[voxel] = soft trilinearly sampled (zero outside) at the blended pull-back of the
    voxel centre: ``q_t + w (q_f - q_t)``, ``q = A x + b`` per bone, ``w`` the sigmoid of
    ``slope . (x - center)``."""
    nz, ny, nx = out.shape
    sz, sy, sx = soft.shape
    for job in numba.prange(nz * ny):
        iz = job // ny
        iy = job - iz * ny
        z = origin[2] + iz * spacing[2]
        y = origin[1] + iy * spacing[1]
        for ix in range(nx):
            x = origin[0] + ix * spacing[0]
            s = slope[0] * (x - center[0]) + slope[1] * (y - center[1]) + slope[2] * (z - center[2])
            w = 1.0 / (1.0 + math.exp(-s))
            qt = A[0, 0, 0] * x + A[0, 0, 1] * y + A[0, 0, 2] * z + b[0, 0]
            qf = A[1, 0, 0] * x + A[1, 0, 1] * y + A[1, 0, 2] * z + b[1, 0]
            fx = qt + w * (qf - qt)
            qt = A[0, 1, 0] * x + A[0, 1, 1] * y + A[0, 1, 2] * z + b[0, 1]
            qf = A[1, 1, 0] * x + A[1, 1, 1] * y + A[1, 1, 2] * z + b[1, 1]
            fy = qt + w * (qf - qt)
            qt = A[0, 2, 0] * x + A[0, 2, 1] * y + A[0, 2, 2] * z + b[0, 2]
            qf = A[1, 2, 0] * x + A[1, 2, 1] * y + A[1, 2, 2] * z + b[1, 2]
            fz = qt + w * (qf - qt)
            i0 = math.floor(fx)
            j0 = math.floor(fy)
            k0 = math.floor(fz)
            total = 0.0
            for dk in range(2):
                k = k0 + dk
                if k < 0 or k >= sz:
                    continue
                wk = 1.0 - abs(fz - k)
                for dj in range(2):
                    j = j0 + dj
                    if j < 0 or j >= sy:
                        continue
                    wj = wk * (1.0 - abs(fy - j))
                    for di in range(2):
                        i = i0 + di
                        if 0 <= i < sx:
                            total += wj * (1.0 - abs(fx - i)) * soft[k, j, i]
            out[iz, iy, ix] = total


def _render_soft(
    scene: _Scene,
    poses: dict[str, np.ndarray],
    view: View,
    spec: KneePhantomSpec,
    projector: Projector,
) -> np.ndarray:
    """The deformed soft tissue projected frame by frame, (F, rows, cols)."""
    reference = knee_bone_poses(spec)
    axes = {
        "femur_z": reference["femur"][:3, 2],
        "tibia_z": reference["tibia"][:3, 2],
        "femur_o": reference["femur"][:3, 3],
        "tibia_o": reference["tibia"][:3, 3],
    }
    geometry = Geometry([view])
    frames = [
        projector(
            _deformed_soft_tissue(scene, T_f, T_t, axes),
            scene.soft_out,
            geometry,
        )[0]
        for T_f, T_t in zip(poses["femur"], poses["tibia"], strict=True)
    ]
    return np.stack(frames)


def simulate_fluoroscopy(
    spec: KneePhantomSpec,
    motion: KneeMotion,
    view: View,
    *,
    voxel_mm: float = 0.5,
    photons_per_pixel: float | None = None,
    realism: Realism = "independent",
    frame_rate_hz: float = FRAME_RATE_HZ,
    seed: int = 0,
    status: Callable[[str], None] | None = None,
    projector: Projector = forward_project,
) -> FluoroSequence:
    """Render a fluoroscopy sequence of the phantom moving through ``motion``.

    Args:
        spec: the phantom at its reference pose (the static scan the poses start from).
        motion: per-frame poses of "femur", "tibia", "fibula" and "patella" (sim.motion).
        view: the fixed fluoroscopy view (e.g. :func:`lateral_view`).
        voxel_mm: rasterisation voxel, mm (2 x 2 x 2 sub-samples per voxel).
        photons_per_pixel: unattenuated photons per pixel per frame; default
            :func:`default_photons_per_pixel` (the :data:`FLUORO_EXPOSURE` technique).
        realism: "ideal" (noise-free line integrals) or "independent" (module docstring).
        frame_rate_hz: frames per second, for ``times_s``.
        seed: noise seed.
        status: optional callback receiving a line per stage.
        projector: renders the bones and the soft tissue (our Joseph projector; a peer's
            renders frames the registration's own renderer did not make).

    Returns:
        The frames and their ground truth.
    """
    say = status or (lambda _msg: None)
    missing = [b for b in BONES if b not in motion.poses]
    if missing:
        raise ValueError(f"motion has no poses for {missing}; needs {list(BONES)}")
    if realism not in ("independent", "ideal"):
        raise ValueError(f"realism must be 'independent' or 'ideal', got {realism!r}")
    if not (math.isfinite(voxel_mm) and voxel_mm > 0.0):
        raise ValueError(f"voxel_mm must be > 0 mm, got {voxel_mm!r}")
    if not (math.isfinite(frame_rate_hz) and frame_rate_hz > 0.0):
        raise ValueError(f"frame_rate_hz must be > 0, got {frame_rate_hz!r}")
    scene = _build_scene(spec, motion, view, voxel_mm, say)
    n = len(motion.flexion_deg)
    say(f"projecting {len(scene.excess)} bones over {n} frames of {view.rows} x {view.cols}")
    ideal = _render_bones(scene, motion.poses, view, projector)
    say(f"deforming and projecting the soft tissue on {scene.soft_out.size_xyz} voxels")
    ideal += _render_soft(scene, motion.poses, view, spec, projector)
    counts, photons = None, 0.0
    frames = ideal.astype(np.float32)
    if realism == "independent":
        photons = (
            default_photons_per_pixel(view) if photons_per_pixel is None else photons_per_pixel
        )
        say(f"beam hardening, scatter, blur, distortion, noise at {photons:.3g} photons/pixel")
        counts, frames = _realistic(ideal, view, photons, np.random.default_rng(seed))
    return FluoroSequence(
        frames=frames,
        counts=counts,
        view=view,
        times_s=np.arange(n) / frame_rate_hz,
        poses={b: p.copy() for b, p in motion.poses.items()},
        flexion_deg=np.asarray(motion.flexion_deg, dtype=np.float64).copy(),
        attenuation=scene.attenuation,
        labels=scene.labels,
        photons_per_pixel=float(photons),
        realism=realism,
    )


def simulate_dewarp_grid(
    grid: DewarpGridSpec,
    view: View,
    *,
    photons_per_pixel: float | None = None,
    realism: Realism = "independent",
    seed: int = 0,
    supersample: int = 3,
) -> np.ndarray:
    """One exposure of the dewarp grid alone (calibration.dewarp_grid) through ``view``:
    line integrals (rows, cols), float32, through the same image model as the frames of
    :func:`simulate_fluoroscopy` (``realism``, including its distortion).

    The plate is a slab (its chord through each pixel's ray); each ball's chord is exact,
    averaged over ``supersample`` x ``supersample`` rays per pixel around its shadow."""
    if supersample < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    rows, cols = view.rows, view.cols
    v, u = np.mgrid[0:rows, 0:cols]
    rays = view.pixel_to_world(u, v) - view.source_mm
    cosine = np.abs(rays @ view.normal) / np.linalg.norm(rays, axis=-1)
    ideal = grid.plate_mu_per_mm * grid.plate_thickness_mm / cosine
    radius_mm = 0.5 * grid.ball_diameter_mm
    reach = math.ceil(grid.ball_radius_px(view) + 2)
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    balls = grid.balls_mm(view)
    for centre, (bu, bv) in zip(balls, view.project(balls), strict=True):
        r0, c0 = max(0, round(bv) - reach), max(0, round(bu) - reach)
        r1, c1 = min(rows, round(bv) + reach + 1), min(cols, round(bu) + reach + 1)
        pv, pu = np.mgrid[r0:r1, c0:c1]
        su = (pu[..., None, None] + offsets[None, :]).reshape(*pu.shape, -1)
        sv = (pv[..., None, None] + offsets[:, None]).reshape(*pv.shape, -1)
        direction = view.pixel_to_world(su, sv) - view.source_mm
        direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
        to_centre = centre - view.source_mm
        along = direction @ to_centre
        miss = to_centre @ to_centre - along**2
        chord = 2.0 * np.sqrt(np.maximum(radius_mm**2 - miss, 0.0))
        ideal[r0:r1, c0:c1] += grid.ball_mu_per_mm * chord.mean(axis=-1)
    if realism == "ideal":
        return ideal.astype(np.float32)
    if realism != "independent":
        raise ValueError(f"realism must be 'independent' or 'ideal', got {realism!r}")
    photons = default_photons_per_pixel(view) if photons_per_pixel is None else photons_per_pixel
    return _realistic(ideal[None], view, photons, np.random.default_rng(seed))[1][0]


# -- files -----------------------------------------------------------------------------------------


def bone_centroids(labels: Volume, bones: tuple[str, ...]) -> dict[str, np.ndarray]:
    """Reference centroid (world mm) of each bone's labelled voxels ("tibia_fibula": both)."""
    axes = labels.grid.axes_mm()
    out = {}
    for bone in bones:
        if bone not in BONE_LABELS:
            raise ValueError(f"unknown bone {bone!r}; known: {', '.join(BONE_LABELS)}")
        kz, ky, kx = np.nonzero(np.isin(labels.data, BONE_LABELS[bone]))
        if kz.size == 0:
            raise ValueError(f"bone {bone!r} has no voxels in the label volume")
        out[bone] = np.array([axes[0][kx].mean(), axes[1][ky].mean(), axes[2][kz].mean()])
    return out


def save_sequence(seq: FluoroSequence, folder: str | Path) -> dict[str, Path]:
    """Write a sequence for registration benchmarks (a study's ``fluoro/`` folder).

    Files: ``frames.mha`` (line integrals, an RTK projection stack, centred panel origin),
    ``counts.mha`` (when noisy), ``view.xml`` (RTK geometry, one identical view per frame),
    ``poses.csv`` (ground truth, registration.poses format with each bone's reference
    centroid) and ``sequence.json`` (times, flexion, realism, photons; units in the keys).

    Args:
        seq: the sequence.
        folder: output folder, created if needed; existing sequence files are never
            overwritten (FileExistsError).

    Returns:
        Name -> path of each file written.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    names = ("frames.mha", "counts.mha", "view.xml", "poses.csv", "sequence.json")
    clash = [n for n in names if (folder / n).exists()]
    if clash:
        raise FileExistsError(f"{folder}: {', '.join(clash)} exist; sequences are not overwritten")
    view = seq.view
    if not math.isclose(view.pitch_u_mm, view.pitch_v_mm, rel_tol=1e-9):
        raise ValueError(f"pixels must be square, got {view.pitch_u_mm} x {view.pitch_v_mm} mm")
    n = len(seq.frames)
    paths = {"frames": write_projections(folder / "frames.mha", seq.frames, view.pitch_u_mm)}
    if seq.counts is not None:
        paths["counts"] = write_projections(folder / "counts.mha", seq.counts, view.pitch_u_mm)
    paths["view"] = write_rtk_geometry(folder / "view.xml", Geometry([view] * n))
    bones = tuple(seq.poses)
    poses = [BodyPose(k, b, seq.poses[b][k]) for k in range(n) for b in bones]
    paths["poses"] = write_poses(folder / "poses.csv", poses, bone_centroids(seq.labels, bones))
    meta = {
        "frames": n,
        "rows": view.rows,
        "cols": view.cols,
        "pixel_pitch_mm": view.pitch_u_mm,
        "times_s": seq.times_s.tolist(),
        "flexion_deg": seq.flexion_deg.tolist(),
        "realism": seq.realism,
        "photons_per_pixel": seq.photons_per_pixel,
        "bones": list(bones),
        "values": "line integrals -ln(I/I0), float32",
    }
    paths["sequence"] = folder / "sequence.json"
    paths["sequence"].write_text(json.dumps(meta, indent=2), encoding="utf-8")
    return paths
