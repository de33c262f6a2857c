"""Implant components placed on the metal of a static scan (registration.placement)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from recon.volume import VolumeGrid
from registration.meshes import inside_fraction
from registration.placement import place_components
from sim.phantoms.tka import TkaPhantomSpec
from sim.tka import load_tka
from sim.tka_ct import tka_scene

DATA = Path(__file__).resolve().parents[3] / "shared" / "data" / "grand-challenge-tka"
pytestmark = pytest.mark.skipif(not DATA.is_dir(), reason=f"no grand-challenge data at {DATA}")
PARTS = {"femur": "femoral_component", "tibia": "tibial_tray"}


@pytest.fixture(scope="module")
def scanned():
    spec = TkaPhantomSpec(data=str(DATA), supersample=1)
    scene = tka_scene(spec)
    # the box cuts the tray's stem, as the recon box does: metal it does not see is not fitted
    grid = VolumeGrid.centered((140, 140, 200), 0.8, tuple(spec.center_mm - [0, 0, 40]))
    metal = sum(  # the truth's metal (sim.tka_ct.tka_truth), of the metal layers alone
        inside_fraction(trimesh.Trimesh(layer.vertices_mm, layer.faces), grid)
        for layer in scene.layers
        if "CoCr" in layer.materials
    )
    return scene, load_tka(DATA), metal >= 0.5, grid


def test_both_components_land_where_the_scan_has_them(scanned) -> None:
    """On the truth's metal at 0.8 mm, the surface fit averages thousands of points: within a
    quarter of a voxel and half a degree of the scene's poses (a 70 mm tray tilted by 0.5 deg
    moves its rim by 0.3 mm, under half a voxel)."""
    scene, knee, metal, grid = scanned
    meshes = {body: (knee.meshes[part], f"{part}.stl") for body, part in PARTS.items()}
    placed = place_components(meshes, metal, grid)
    for body, part in PARTS.items():
        T, truth = placed[body].T_world_body, scene.poses[part]
        angle = Rotation.from_matrix(T[:3, :3] @ truth[:3, :3].T).magnitude()
        c = knee.meshes[part].centroid
        moved = (T[:3, :3] @ c + T[:3, 3]) - (truth[:3, :3] @ c + truth[:3, 3])
        assert np.degrees(angle) < 0.5 and np.linalg.norm(moved) < 0.2, body
        assert placed[body].surface_distance_mm < 0.75 and 0.8 < placed[body].volume_ratio < 1.2


def test_a_component_of_another_size_is_refused(scanned) -> None:
    _, knee, metal, grid = scanned
    larger = knee.meshes["femoral_component"].copy().apply_scale(1.1)
    with pytest.raises(ValueError, match=r"FEM\.stl \(femur\) does not fit the scan's metal"):
        place_components({"femur": (larger, "FEM.stl")}, metal, grid)


def test_more_components_than_metal_is_refused(scanned) -> None:
    _, knee, metal, grid = scanned
    meshes = {body: (knee.meshes["tibial_tray"], "T.stl") for body in ("femur", "tibia", "x")}
    with pytest.raises(ValueError, match=r"2 separate region\(s\) for 3 component"):
        place_components(meshes, metal, grid)


def test_a_component_of_the_other_side_is_refused(scanned) -> None:
    """The femoral component mirrored (a left one for this right knee) fits the metal within
    the distance check, but its mirror image, the right one, fits it clearly better."""
    _, knee, metal, grid = scanned
    mirrored = knee.meshes["femoral_component"].copy()
    mirrored.apply_transform(np.diag([-1.0, 1.0, 1.0, 1.0]))  # trimesh keeps it outward
    assert mirrored.volume > 0
    with pytest.raises(ValueError, match=r"LEFT\.stl \(femur\) fits the scan's metal better mirr"):
        place_components({"femur": (mirrored, "LEFT.stl")}, metal, grid)
