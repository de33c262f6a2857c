"""Meshes of implant components and the materials they are made of: reading a CAD mesh in its
unit, checking its size, repairing small holes, and its partial volumes on a voxel grid.

Meshes come in STL, OBJ or PLY (trimesh), in the unit given; one whose size does not fit a knee
component in that unit is refused, and one that is not closed is repaired where only small
holes are missing (said in :attr:`MeshReport.repairs`) and refused otherwise. :func:`voxelize`
gives a mesh's partial volumes on a grid (a component's points in registration.implants; a
phantom's implants in the simulator).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numba
import numpy as np
import trimesh

from recon.volume import VolumeGrid

MESH_UNITS_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4}
"""Length of one mesh unit, mm."""
COMPONENT_SIZE_MM = (20.0, 200.0)
"""The largest extent a knee implant component can have, mm (a patellar button to a long
stemmed tray)."""
BONE_SIZE_MM = (20.0, 600.0)
"""The largest extent a knee's bone mesh can have, mm (a patella to a whole femur)."""


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
BONE = Material("bone", 1.45, (0.22, 0.19), False)
"""A whole bone's mean: cortex and cancellous bone with marrow (mass attenuation of cortical
bone at 60 and 80 keV; the density a knee's bones average over their volume)."""
ATTACHABLE = {**MATERIALS, BONE.name: BONE}
"""What a part fixed to a tracked component can be made of: an implant material (an insert's
polyethylene) or bone (the bone the component is fixed to)."""


def size_range_mm(material: str) -> tuple[float, float]:
    """The plausible range of the largest extent (mm) of a knee's part made of ``material``
    (a name in :data:`ATTACHABLE`): a bone's, or an implant component's."""
    return BONE_SIZE_MM if material == BONE.name else COMPONENT_SIZE_MM


@dataclass(frozen=True)
class MeshReport:
    """What reading a mesh found: its file, unit, size (mm), faces and the repairs made."""

    path: str
    unit: str
    size_mm: tuple[float, float, float]
    faces: int
    repairs: tuple[str, ...] = ()


def capped_loops(mesh: trimesh.Trimesh) -> tuple[trimesh.Trimesh | None, list[int]]:
    """The mesh with each hole (a loop of edges that bound one face) capped by a fan of
    triangles about the loop's mean vertex (flat where the hole is), and each loop's edge
    count; None where the open edges do not form separate loops or the result is not closed."""
    boundary = trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1)
    following: dict[int, int] = {}
    for a, b in mesh.edges[boundary]:  # each as its face runs it
        if int(a) in following:
            return None, []  # two loops touch at a vertex
        following[int(a)] = int(b)
    vertices, faces, loops = list(mesh.vertices), list(mesh.faces), []
    left = set(following)
    while left:
        loop = [left.pop()]
        while following.get(loop[-1]) in left:
            loop.append(following[loop[-1]])
            left.discard(loop[-1])
        if following.get(loop[-1]) != loop[0]:
            return None, []
        centre = len(vertices)
        vertices.append(mesh.vertices[loop].mean(axis=0))
        faces += [(b, a, centre) for a, b in zip(loop, loop[1:] + loop[:1], strict=True)]
        loops.append(len(loop))
    capped = trimesh.Trimesh(np.asarray(vertices), np.asarray(faces), process=True)
    return (capped, loops) if loops and capped.is_watertight else (None, [])


def read_mesh(
    path: str | Path, unit: str = "mm", size_mm: tuple[float, float] = COMPONENT_SIZE_MM
) -> tuple[trimesh.Trimesh, MeshReport]:
    """A component's closed mesh in mm, and what was found; raises ValueError naming the file
    and the problem (unknown unit, an implausible size, open edges that form no holes).

    Args:
        path: an STL, OBJ or PLY file.
        unit: the mesh's unit (:data:`MESH_UNITS_MM`).
        size_mm: the plausible range of its largest extent, mm (a knee implant's by
            default; a whole bone is longer).
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
    low, high = size_mm
    if not low <= max(size) <= high:
        what = "a knee implant's" if size_mm == COMPONENT_SIZE_MM else "the plausible"
        raise ValueError(
            f"{path}: in {unit} the component is {max(size):.4g} mm across, outside {what} "
            f"{low:g}-{high:g} mm: give its unit (--implant-unit)"
        )
    repairs = []
    if not mesh.is_watertight:  # zero-volume slivers stuck to closed shells: drop them
        pieces = mesh.split(only_watertight=False)
        with np.errstate(invalid="ignore", divide="ignore"):  # a sliver's centre of mass
            kept = [p for p in pieces if abs(p.volume) > 1e-6 * abs(mesh.volume)]
        if len(kept) < len(pieces) and all(p.is_watertight for p in kept):
            mesh = trimesh.util.concatenate(kept)
            repairs.append(f"removed {len(pieces) - len(kept)} piece(s) of no volume")
    if not mesh.is_watertight:
        holes = len(mesh.faces)
        trimesh.repair.fill_holes(mesh)
        trimesh.repair.fix_normals(mesh)
        if len(mesh.faces) > holes:
            repairs.append(f"closed {len(mesh.faces) - holes} missing faces")
    if not mesh.is_watertight:
        capped, loops = capped_loops(mesh)
        if capped is None:
            raise ValueError(
                f"{path}: the mesh is not closed and its open edges form no loops to close: "
                "export it closed (a solid) from the CAD"
            )
        mesh = capped
        trimesh.repair.fix_normals(mesh)
        repairs.append(f"capped {len(loops)} hole(s) of {', '.join(str(n) for n in loops)} edges")
    if mesh.volume < 0:
        mesh.invert()
        repairs.append("turned its faces outwards")
    report = MeshReport(str(path), unit, size, len(mesh.faces), tuple(repairs))
    return mesh, report


def decimated(mesh: trimesh.Trimesh, max_faces: int) -> trimesh.Trimesh:
    """``mesh`` brought down to ``max_faces`` faces by quadric decimation (``mesh`` itself when
    it has no more). The decimation may stop above ``max_faces`` where removing more faces
    would change the surface's topology.

    Args:
        mesh: A surface mesh.
        max_faces: The faces aimed at.

    Returns:
        The decimated mesh.
    """
    if len(mesh.faces) <= max_faces:
        return mesh
    return mesh.simplify_quadric_decimation(face_count=max_faces)


def voxelize(
    mesh: trimesh.Trimesh, voxel_mm: float, supersample: int = 4
) -> tuple[np.ndarray, VolumeGrid]:
    """The fraction of each voxel inside a closed mesh (mm), float32 [z, y, x], on a grid of
    ``voxel_mm`` cubes one voxel beyond its bounds (:func:`inside_fraction`)."""
    if not voxel_mm > 0:
        raise ValueError(f"voxel_mm must be > 0, got {voxel_mm}")
    low = mesh.bounds[0] - voxel_mm
    shape_xyz = np.ceil((mesh.bounds[1] - mesh.bounds[0]) / voxel_mm).astype(int) + 3
    grid = VolumeGrid(tuple(int(n) for n in shape_xyz[::-1]), (voxel_mm,) * 3, tuple(low))
    return inside_fraction(mesh, grid, supersample), grid


def inside_fraction(mesh: trimesh.Trimesh, grid: VolumeGrid, supersample: int = 4) -> np.ndarray:
    """The fraction of each voxel of ``grid`` (cubic voxels) inside a closed mesh (mm),
    float32 [z, y, x].

    Exact along z (the crossings of each column's rays with the surface, integrated over the
    voxel), sampled on ``supersample`` x ``supersample`` rays per voxel across."""
    if supersample < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    if len(set(grid.spacing_mm)) != 1:
        raise ValueError(f"inside_fraction needs cubic voxels, got {grid.spacing_mm} mm")
    low, pitch = np.asarray(grid.origin_mm), grid.spacing_mm[0]
    triangles = (np.asarray(mesh.triangles, dtype=np.float64) - low) / pitch  # index coords
    nz, ny, nx = grid.shape
    steps = _crossings(triangles, nx, ny, nz, supersample)
    return np.clip(np.cumsum(steps, axis=0)[:nz] / supersample**2, 0.0, 1.0).astype(np.float32)


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
