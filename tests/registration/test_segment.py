"""Tests of registration.segment: bones of a simulated, reconstructed knee CBCT scan. The
scan's noise follows the ``seed`` option; accuracy figures go through ``measured``."""

from __future__ import annotations

from functools import cache
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

from recon.config import load_protocol
from recon.fdk import fdk_reconstruct
from recon.volume import Volume, VolumeGrid
from registration.segment import (
    BONE_UNITS,
    LABELS,
    _edge_threshold,
    _fill_bone,
    bone_points,
    bone_surfaces,
    segment_bones,
    segment_bones_with_metal,
)
from sim.phantoms.knee import KneePhantomSpec, attenuation_per_mm, rasterize_knee
from sim.phantoms.tka import TkaPhantomSpec
from sim.scan import simulate_knee_scan
from sim.tka_ct import METAL_LABEL, tka_scene, tka_truth

PROTOCOL = Path(__file__).resolve().parents[2] / "configs" / "protocols" / "demo_knee.yaml"
RECON_VOXEL_MM = 1.0
DICE_TARGETS = {"femur": 0.95, "tibia_fibula": 0.95, "patella": 0.90}
"""The issue's targets per registration unit."""


@cache
def _knee(side: str, seed: int) -> tuple[Volume, Volume, Volume]:
    """Demo-protocol scan (noise on, seeded by ``seed``) of a knee, its FDK reconstruction on a
    1 mm grid over the phantom, the phantom's labels on that grid and the segmentation."""
    spec = KneePhantomSpec(side=side)
    scan = simulate_knee_scan(load_protocol(PROTOCOL), spec, voxel_mm=1.0, noise=True, seed=seed)
    sim_grid = scan.attenuation.grid
    extent = np.array(sim_grid.size_xyz) * np.array(sim_grid.spacing_mm)
    grid = VolumeGrid.centered(
        tuple(int(n) for n in np.floor(extent / RECON_VOXEL_MM)),
        RECON_VOXEL_MM,
        sim_grid.center_mm,
    )
    recon = fdk_reconstruct(scan.projections, scan.geometry, grid).volume
    truth = Volume(rasterize_knee(spec, grid, supersample=3)[0], grid, "label")
    return recon, truth, segment_bones(recon)


def _dice(a: np.ndarray, b: np.ndarray) -> float:
    return 2.0 * float(np.sum(a & b)) / float(np.sum(a) + np.sum(b))


def _crop_z(volume: Volume, z_max_mm: float) -> Volume:
    """The slices of ``volume`` below world z = ``z_max_mm``."""
    n = int(np.sum(volume.grid.axes_mm()[2] < z_max_mm))
    grid = VolumeGrid((n, *volume.grid.shape[1:]), volume.grid.spacing_mm, volume.grid.origin_mm)
    return Volume(volume.data[:n], grid, volume.unit)


def test_labels_follow_the_phantom() -> None:
    assert set(BONE_UNITS) == {"femur", "tibia_fibula", "patella"}


@pytest.mark.parametrize("side", ["right", "left"])
def test_segmentation_matches_the_phantom(side: str, seed, measured) -> None:
    recon, truth, seg = _knee(side, seed)
    assert seg.unit == "label" and seg.grid == recon.grid and seg.data.dtype == np.uint8
    for unit, values in BONE_UNITS.items():
        dice = _dice(np.isin(seg.data, values), np.isin(truth.data, values))
        measured(f"dice_shortfall_{unit}", 1.0 - dice, below=1.0 - DICE_TARGETS[unit])
    # the fibula is its own bone (0.94 at 1 mm: the 1.5 mm tibiofibular gap is not resolved)
    fibula = _dice(seg.data == LABELS["fibula"], truth.data == LABELS["fibula"])
    measured("dice_shortfall_fibula", 1.0 - fibula, below=0.15)
    measured("dice_shortfall_bone", 1.0 - _dice(seg.data > 0, truth.data > 0), below=0.02)


def test_side_is_inferred_from_the_fibula_or_enforced(seed) -> None:
    recon, _, seg = _knee("left", seed)
    x = recon.grid.axes_mm()[0]
    centre_x = {
        name: x[np.nonzero(seg.data == LABELS[name])[2]].mean() for name in ("tibia", "fibula")
    }
    assert centre_x["fibula"] > centre_x["tibia"] + 20.0  # lateral is +x for a left knee
    assert np.array_equal(segment_bones(recon, side="left").data, seg.data)
    with pytest.raises(ValueError, match="no fibula found"):
        segment_bones(recon, side="right")


def test_given_soft_tissue_level_gives_the_same_bones(seed, measured) -> None:
    recon, truth, _ = _knee("right", seed)
    muscle = attenuation_per_mm(KneePhantomSpec().effective_energy_kev)["muscle"]
    seg = segment_bones(recon, soft_tissue_per_mm=muscle)
    for unit, values in BONE_UNITS.items():
        dice = _dice(np.isin(seg.data, values), np.isin(truth.data, values))
        measured(f"dice_shortfall_{unit}", 1.0 - dice, below=1.0 - DICE_TARGETS[unit])


def test_volume_without_bone_is_refused(make_cylinder, seed) -> None:
    grid = VolumeGrid.centered((100, 100, 60), 1.0, (0.0, 0.0, 480.0))
    leg = make_cylinder(grid, (0.0, 0.0, 480.0), 45.0, 100.0, value=0.0202)
    leg += np.random.default_rng(1 + seed).normal(0.0, 0.001, leg.shape).astype(np.float32)
    with pytest.raises(ValueError, match="a volume without bone"):
        segment_bones(Volume(leg, grid, "1/mm"))


def test_volume_without_the_femur_is_refused(seed) -> None:
    recon, _, _ = _knee("right", seed)
    below_joint = _crop_z(recon, KneePhantomSpec().joint_line_height_mm)
    with pytest.raises(ValueError, match="no bone found above or below"):
        segment_bones(below_joint)
    with pytest.raises(ValueError, match="linear attenuation"):
        segment_bones(Volume(recon.data, recon.grid, "HU"))


def test_surfaces_are_closed_and_hold_the_label_volume(seed, measured) -> None:
    _, _, seg = _knee("right", seed)
    meshes = bone_surfaces(seg)
    assert set(meshes) == set(BONE_UNITS)
    lo, hi = seg.grid.corners_mm().min(axis=0), seg.grid.corners_mm().max(axis=0)
    volume_error = []
    for unit, mesh in meshes.items():
        label_mm3 = np.isin(seg.data, BONE_UNITS[unit]).sum() * seg.grid.voxel_volume_mm3
        assert mesh.is_watertight, unit
        volume_error.append(abs(mesh.volume - label_mm3) / label_mm3)
        assert np.all(mesh.bounds[0] >= lo - 1e-6) and np.all(mesh.bounds[1] <= hi + 1e-6)
    measured("mesh_volume_rel_error", max(volume_error), below=0.05)


def test_bone_points_are_the_labelled_voxels(seed) -> None:
    recon, _, seg = _knee("right", seed)
    clouds = bone_points(seg, recon)
    assert set(clouds) == set(BONE_UNITS)
    for unit, (points, mu) in clouds.items():
        mask = np.isin(seg.data, BONE_UNITS[unit])
        assert points.shape == (mask.sum(), 3) and mu.shape == (mask.sum(),)
        index = np.rint(seg.grid.world_to_index(points)).astype(int)
        assert np.all(mask[index[:, 2], index[:, 1], index[:, 0]])
        assert np.allclose(mu, recon.data[index[:, 2], index[:, 1], index[:, 0]])
    femur, tibia = clouds["femur"][0], clouds["tibia_fibula"][0]
    assert femur[:, 2].mean() > tibia[:, 2].mean()
    with pytest.raises(ValueError, match="differs"):
        bone_points(seg, _crop_z(recon, recon.grid.axes_mm()[2][-1]))
    with pytest.raises(ValueError, match="no patella"):
        bone_points(Volume(np.where(seg.data == 5, 1, seg.data), seg.grid, "label"), recon)


def test_a_shell_open_in_some_axial_slices_is_still_filled(measured) -> None:
    """A hollow ball (shell 2 voxels thick) slit open across 4 axial slices: those slices'
    rings are open, but the slices across them (coronal, sagittal) are closed rings."""
    z, y, x = np.mgrid[:41, :41, :41] - 20
    r = np.sqrt(x**2 + y**2 + z**2)
    shell = (r <= 15) & (r > 13)
    shell[18:22, :, 20] = False  # a 1-voxel slit through the +x and -x walls in 4 slices
    shell[18:22, 20, :] = False  # and through the +y and -y walls: no axial ring is closed
    bone, interior = _fill_bone(shell)
    inside = r <= 13
    measured("interior_unfilled_fraction", 1.0 - interior[inside].mean(), below=0.01)
    assert not bone[r > 15.5].any()  # nothing grows outside the ball


def test_bright_specks_inside_the_bone_do_not_move_its_edge() -> None:
    """A ball of cortex (1.8 x soft tissue, 3 voxels thick) around cancellous bone (1.2 x),
    blurred by 0.8 voxel: specks of 4 x soft tissue inside it (a sparse-view TV volume's
    streak remnants, 3 voxels across) leave the edge isovalue where it was. The specks' steep
    flanks are a small band at ~1.85 whose mean gradient beats the bone surface's; counted
    among the candidates they took the edge there, above the whole cortex."""
    z, y, x = np.mgrid[-32:32, -32:32, -32:32]
    r = np.sqrt(x**2 + y**2 + z**2)
    ball = np.where(r < 20, np.where(r > 17, 1.8, 1.2), 1.0)
    specks = np.zeros(ball.shape, dtype=bool)
    seeds = np.random.default_rng(0).choice(np.argwhere((r > 6) & (r < 14)), 10, replace=False)
    specks[tuple(seeds.T)] = True
    specked = np.where(ndimage.binary_dilation(specks), 4.0, ball)
    clean = _edge_threshold(ndimage.gaussian_filter(ball, 0.8), np.ones(3))
    assert 1.3 <= clean <= 1.6  # between soft tissue (1) and the blurred cortex's crest
    assert _edge_threshold(ndimage.gaussian_filter(specked, 0.8), np.ones(3)) == clean


GC_DATA = Path(__file__).resolve().parents[3] / "shared" / "data" / "grand-challenge-tka"


@pytest.mark.skipif(not GC_DATA.is_dir(), reason=f"no grand-challenge data at {GC_DATA}")
def test_bone_an_implant_caps_stays_with_its_own_bone(measured) -> None:
    """The knee replacement's attenuation itself (sim.tka_ct's truth on 1 mm voxels about the
    joint, no scan): next to the tray, the tibia's cortex that no interior of its own encloses
    goes to the tray and so to the tibia, not to the fibula's interior nearby. Dice within
    20 mm of the metal: 0.919 for the fibula, 0.975 for the tibia (0.753 and 0.954 when that
    cortex went to the fibula); the bound lies between."""
    spec = TkaPhantomSpec(data=str(GC_DATA), supersample=1)
    grid = VolumeGrid.centered((140, 140, 160), 1.0, tuple(spec.center_mm))
    truth = tka_truth(tka_scene(spec), grid, 110.0)
    metal = truth.labels == METAL_LABEL
    volume = Volume(truth.mu.astype(np.float32), grid, "1/mm")
    labels = segment_bones_with_metal(volume, metal, METAL_LABEL, side="right")
    scores = truth.near_metal_scores(labels.data)
    for bone in ("tibia", "fibula"):
        measured(f"{bone}_dice_near_metal", scores[bone], above=0.85)
