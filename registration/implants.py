"""Implant components as tracked bodies: a CAD mesh of a known material, voxelised with
partial-volume fractions into the rigid model a bone is (:class:`registration.drr.BoneModel`).

A femoral component or a tibial tray is metal: near-opaque in a frame, streaking in a CBCT, and
its exact shape is known from its mesh. :func:`implant_model` turns the mesh into its
attenuation on a fine grid (the fraction of each voxel inside the mesh, exact along z and
sampled on ``supersample`` x ``supersample`` columns per voxel across, times the material's
attenuation), so the tracker renders, refines and reports it as it does a bone. Radiolucent
parts (a polyethylene insert) are not tracked alone.

Meshes come in STL, OBJ or PLY (trimesh), in the unit given; one whose size does not fit a knee
component in that unit is refused, and one that is not closed is repaired where only small
holes are missing (said in :attr:`MeshReport.repairs`) and refused otherwise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numba
import numpy as np
import trimesh

from recon.volume import VolumeGrid
from registration.drr import BoneModel, RigidVolume

MESH_UNITS_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4}
"""Length of one mesh unit, mm."""
COMPONENT_SIZE_MM = (20.0, 200.0)
"""The largest extent a knee implant component can have, mm (a patellar button to a long
stemmed tray)."""
VOXEL_MM = 0.25
"""Default voxel of an implant model, mm: a third of a 0.75 mm registration pixel at the
implant, its partial-volume edge placed to a few hundredths of a pixel."""


@dataclass(frozen=True)
class Material:
    """An implant material: density and mass attenuation at 60 and 80 keV.

    Attributes:
        name: as given on the command line.
        density_g_cm3: density, g/cm^3.
        mass_attenuation_cm2_g: (60 keV, 80 keV), cm^2/g, coherent scattering included.
        radiopaque: shows in a frame as itself (metal); a radiolucent part is not tracked
            alone.
    """

    name: str
    density_g_cm3: float
    mass_attenuation_cm2_g: tuple[float, float]
    radiopaque: bool

    def mu_per_mm(self, energy_kev: float) -> float:
        """Linear attenuation at ``energy_kev`` (50-100 keV, log-log through 60 and 80), 1/mm."""
        if not 50.0 <= energy_kev <= 100.0:
            raise ValueError(f"implant attenuation: energy {energy_kev} keV outside 50-100 keV")
        (m60, m80), t = self.mass_attenuation_cm2_g, math.log(energy_kev / 60.0) / math.log(80 / 60)
        mass = math.exp(math.log(m60) + t * (math.log(m80) - math.log(m60)))
        return mass * self.density_g_cm3 / 10.0


MATERIALS = {
    m.name: m
    for m in (
        Material("CoCr", 8.3, (1.30, 0.63), True),
        Material("Ti6Al4V", 4.43, (0.71, 0.40), True),
        Material("UHMWPE", 0.94, (0.19, 0.17), False),
    )
}
"""Knee implant materials: CoCrMo (ASTM F75: Co 63, Cr 28, Mo 6 %), Ti-6Al-4V and the
polyethylene of inserts; mass attenuation from the NIST tables of their elements, mixed by
weight (to about 10 %: the registration's similarity ignores a scale, and metal is near-opaque
in a frame whatever its exact value)."""


@dataclass(frozen=True)
class MeshReport:
    """What reading a mesh found: its file, unit, size (mm), faces and the repairs made."""

    path: str
    unit: str
    size_mm: tuple[float, float, float]
    faces: int
    repairs: tuple[str, ...] = ()


def read_mesh(path: str | Path, unit: str = "mm") -> tuple[trimesh.Trimesh, MeshReport]:
    """A component's closed mesh in mm, and what was found; raises ValueError naming the file
    and the problem (unknown unit, an implausible size, holes that cannot be closed).

    Args:
        path: an STL, OBJ or PLY file.
        unit: the mesh's unit (:data:`MESH_UNITS_MM`).
    """
    path = Path(path)
    if unit not in MESH_UNITS_MM:
        raise ValueError(f"{path}: mesh unit {unit!r}; one of {sorted(MESH_UNITS_MM)}")
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such mesh file")
    try:
        mesh = trimesh.load(path, force="mesh", process=True)
    except Exception as err:  # trimesh raises many kinds on a broken file
        raise ValueError(f"{path}: not a readable mesh ({type(err).__name__}: {err})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) < 4:
        raise ValueError(f"{path}: holds no surface mesh")
    mesh.apply_scale(MESH_UNITS_MM[unit])
    size = tuple(float(v) for v in mesh.extents)
    low, high = COMPONENT_SIZE_MM
    if not low <= max(size) <= high:
        raise ValueError(
            f"{path}: in {unit} the component is {max(size):.4g} mm across, outside a knee "
            f"implant's {low:g}-{high:g} mm: give its unit (--implant-unit)"
        )
    repairs = []
    if not mesh.is_watertight:
        holes = len(mesh.faces)
        trimesh.repair.fill_holes(mesh)
        trimesh.repair.fix_normals(mesh)
        if not mesh.is_watertight:
            raise ValueError(
                f"{path}: the mesh is not closed and its holes could not be filled: export it "
                "closed (a solid) from the CAD"
            )
        repairs.append(f"closed {len(mesh.faces) - holes} missing faces")
    if mesh.volume < 0:
        mesh.invert()
        repairs.append("turned its faces outwards")
    report = MeshReport(str(path), unit, size, len(mesh.faces), tuple(repairs))
    return mesh, report


def voxelize(
    mesh: trimesh.Trimesh, voxel_mm: float = VOXEL_MM, supersample: int = 4
) -> tuple[np.ndarray, VolumeGrid]:
    """The fraction of each voxel inside a closed mesh (mm), float32 [z, y, x], on a grid of
    ``voxel_mm`` cubes one voxel beyond its bounds.

    Exact along z (the crossings of each column's rays with the surface, integrated over the
    voxel), sampled on ``supersample`` x ``supersample`` rays per voxel across."""
    if not voxel_mm > 0 or supersample < 1:
        raise ValueError(
            f"voxel_mm must be > 0 and supersample >= 1, got {voxel_mm}, {supersample}"
        )
    low = mesh.bounds[0] - voxel_mm
    shape_xyz = np.ceil((mesh.bounds[1] - mesh.bounds[0]) / voxel_mm).astype(int) + 3
    grid = VolumeGrid(tuple(int(n) for n in shape_xyz[::-1]), (voxel_mm,) * 3, tuple(low))
    triangles = (np.asarray(mesh.triangles, dtype=np.float64) - low) / voxel_mm  # index coords
    nx, ny, nz = (int(n) for n in shape_xyz)
    steps = _crossings(triangles, nx, ny, nz, supersample)
    fraction = np.cumsum(steps, axis=0)[:nz] / supersample**2
    return np.clip(fraction, 0.0, 1.0).astype(np.float32), grid


@numba.njit(cache=True)
def _crossings(triangles, nx, ny, nz, s):  # pragma: no cover
    """The z-derivative of each voxel's inside fraction: every triangle adds, on the ``s x s``
    rays per voxel column it covers, +1 where a ray along +z enters the solid and -1 where it
    leaves, split between the voxel it crosses in and the next in proportion (nz + 1, ny, nx)."""
    out = np.zeros((nz + 1, ny, nx))
    for t in range(triangles.shape[0]):
        ax, ay, az = triangles[t, 0]
        bx, by, bz = triangles[t, 1]
        cx, cy, cz = triangles[t, 2]
        area = (bx - ax) * (cy - ay) - (cx - ax) * (by - ay)  # twice the signed area in xy
        if area == 0.0:
            continue
        sign = -1.0 if area > 0.0 else 1.0  # outward normal along -z: the ray enters
        g0 = max(0, math.ceil((min(ax, bx, cx) + 0.5) * s - 0.5))
        g1 = min(nx * s - 1, math.floor((max(ax, bx, cx) + 0.5) * s - 0.5))
        h0 = max(0, math.ceil((min(ay, by, cy) + 0.5) * s - 0.5))
        h1 = min(ny * s - 1, math.floor((max(ay, by, cy) + 0.5) * s - 0.5))
        for h in range(h0, h1 + 1):
            y = (h + 0.5) / s - 0.5
            for g in range(g0, g1 + 1):
                x = (g + 0.5) / s - 0.5
                wa = ((bx - x) * (cy - y) - (cx - x) * (by - y)) / area
                wb = ((cx - x) * (ay - y) - (ax - x) * (cy - y)) / area
                wc = 1.0 - wa - wb
                if wa < 0.0 or wb < 0.0 or wc < 0.0:
                    continue
                z = wa * az + wb * bz + wc * cz
                k = math.floor(z + 0.5)
                f = z + 0.5 - k
                ix, iy = g // s, h // s
                if k < 0:
                    out[0, iy, ix] += sign
                elif k < nz:
                    out[k, iy, ix] += sign * (1.0 - f)
                    out[k + 1, iy, ix] += sign * f
    return out


def implant_model(
    name: str,
    mesh: trimesh.Trimesh,
    material: Material,
    energy_kev: float = 70.0,
    voxel_mm: float = VOXEL_MM,
) -> BoneModel:
    """A component as a tracked body: its attenuation (the voxel fractions times the
    material's, 1/mm) in the mesh's own frame (``T_world_body`` maps mesh mm to world mm), its
    points (the centres of the voxels at least half inside, every other one along each axis)
    and their centroid."""
    if not material.radiopaque:
        raise ValueError(
            f"{name}: {material.name} is radiolucent: it does not show in a frame by itself "
            "and is not tracked alone"
        )
    fraction, grid = voxelize(mesh, voxel_mm)
    mu = material.mu_per_mm(energy_kev)
    kz, ky, kx = np.nonzero(fraction[::2, ::2, ::2] >= 0.5)
    x, y, z = grid.axes_mm()
    points = np.column_stack((x[::2][kx], y[::2][ky], z[::2][kz]))
    return BoneModel(name, RigidVolume.of(mu * fraction, grid), points, points.mean(axis=0))
