"""Implant components as tracked bodies: a CAD mesh of a known material (registration.meshes),
rendered ray by ray through the view (:class:`ImplantModel`), tracked, refined and reported as a
bone is.

A femoral component or a tibial tray is metal: near-opaque in a frame, streaking in a CBCT, and
its exact shape is known from its mesh. Radiolucent parts (a polyethylene insert) are not
tracked alone.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numba
import numpy as np
import trimesh
from scipy.ndimage import gaussian_filter

from recon.geometry import View
from registration.meshes import MATERIALS, Material, decimated, read_mesh, voxelize

OUTLINE_FACES = 4000
"""Faces a component's coarse mesh starts from, each part decimated to its share of these
(then more where its shape needs them: :data:`COARSE_SHAPE_SHARE`)."""

COARSE_SHAPE_SHARE = 1e-3
"""How far each part of a coarse mesh may depart from the part's volume and area (a share of
each). In one plane depth is read from the magnification, so a part that shrinks reads as
farther from the source: the simulated tray's metal, decimated to 2,196 faces, lost 3.1 % of
its volume and the tracker lost its depth in 6 frames of 90 (docs/implants.md)."""

FACE_CHUNKS = numba.config.NUMBA_NUM_THREADS
"""The shares a render's faces are summed in (one a thread of the process's): fixed, so a
render is the same to the bit whatever threads its caller runs on (registration.search.at_once)."""


@dataclass(frozen=True)
class ImplantModel:
    """An implant component as a tracked body: rendered from its mesh, ray by ray.

    Each sample's ray length ``L`` through the closed mesh is exact (the sum, over the faces it
    crosses, of the distance to where it leaves minus where it enters); the pixel's value is
    the share of the beam the component stops, ``1 - exp(-mu L)``, averaged over
    ``supersample`` x ``supersample`` rays: a metal component's shadow, flat inside as a real
    frame shows it (the detector chain saturates long before the metal's thickness varies),
    its edge placed to a fraction of a pixel. A component with parts attached (a tray and its
    insert) sums each part's ``mu L``: its faces carry their part's attenuation.

    Attributes:
        name: the body's name (registration.roles.COMPONENT_NAMES: femoral_component,
            tibial_tray; its role, the bone it replaces, follows from it or is given to the
            tracker).
        vertices_mm: the mesh's vertices in its own frame (V, 3), mm.
        faces: the mesh's triangles (T, 3), outward by their winding.
        face_mu: each face's attenuation, its part's material's, 1/mm (T,).
        points_mm: points filling the component (the centres of its 1 mm voxels at least half
            inside), in its frame: the TRE's and the principal axes' (N, 3).
        centroid_mm: their mean (rotations of the 6-DoF parameterisation are about it).
        supersample: rays per pixel along each axis.
        blur_mm: Gaussian sigma of the imaging chain (focal spot, panel, video) at the panel,
            mm, the render is blurred by (the tracker matches it to the frames).
    """

    name: str
    vertices_mm: np.ndarray
    faces: np.ndarray
    face_mu: np.ndarray
    points_mm: np.ndarray
    centroid_mm: np.ndarray
    supersample: int = 3
    blur_mm: float = 0.0

    def voxel_mm(self) -> float:
        """A mesh has no voxels to pool (its coarse mesh serves the pyramid's coarse levels:
        registration.scene)."""
        return 0.0

    def render(
        self,
        view: View,
        T_world_body: np.ndarray,
        coarse: bool = False,
        spans: np.ndarray | None = None,
        blurred: bool = True,
    ) -> np.ndarray:
        """The share of the beam the component at ``T_world_body`` stops.

        Args:
            view: The view rendered.
            T_world_body: Pose of the component, 4x4, mesh mm to world mm.
            coarse: Rendered from :attr:`coarse_mesh` (the pyramid's coarse levels), at a
                cost that does not grow with the mesh's faces.
            spans: Ignored: a voxel model's option (the whole view is rendered).
            blurred: Blurred by :attr:`blur_mm` (False: sharp, for a caller that filters
                it further anyway).

        Returns:
            The stopped share of the beam, in [0, 1], float32 (rows, cols).
        """
        vertices, faces, face_mu = (
            self.coarse_mesh if coarse else (self.vertices_mm, self.faces, self.face_mu)
        )
        uv, coef, A = _projected(view, vertices, faces, T_world_body)
        out = np.zeros((view.rows, view.cols), dtype=np.float32)
        _render(uv, coef, face_mu, A, self.supersample, True, out, FACE_CHUNKS)
        if blurred and self.blur_mm > 0.0:
            gaussian_filter(out, self.blur_mm / view.pitch_u_mm, output=out, mode="constant")
        return out

    @cached_property
    def coarse_mesh(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The mesh with each part (the faces of one attenuation) decimated to its share of
        :data:`OUTLINE_FACES` faces, or to as many more as keep its shape
        (:func:`shape_kept`): vertices (V, 3) mm, faces (T, 3) and each face's attenuation
        (T,) 1/mm; the mesh itself when it has no more faces."""
        if len(self.faces) <= OUTLINE_FACES:
            return self.vertices_mm, self.faces, self.face_mu
        parts, mus = [], []
        for mu in np.unique(self.face_mu):
            faces = self.faces[self.face_mu == mu]
            part = trimesh.Trimesh(self.vertices_mm, faces, process=False)
            part.remove_unreferenced_vertices()
            part = shape_kept(part, math.ceil(OUTLINE_FACES * len(faces) / len(self.faces)))
            parts.append(part)
            mus.append(np.full(len(part.faces), mu))
        whole = trimesh.util.concatenate(parts)
        return (
            np.asarray(whole.vertices, dtype=np.float64),
            np.asarray(whole.faces, dtype=np.int64),
            np.concatenate(mus),
        )

    def silhouette(self, view: View, T_world_body: np.ndarray, outline: bool = False) -> np.ndarray:
        """The pixels of ``view`` whose centre's ray meets the component at ``T_world_body``.

        Args:
            view: The view.
            T_world_body: Pose of the component, 4x4, mesh mm to world mm.
            outline: Drawn from :attr:`coarse_mesh` (pixels of a millimetre or more, as the
                automatic search's), at a cost that does not grow with the mesh's faces.

        Returns:
            The silhouette, bool (rows, cols).
        """
        vertices, faces = self.coarse_mesh[:2] if outline else (self.vertices_mm, self.faces)
        return ray_lengths(view, vertices, faces, T_world_body) > 0.0


def ray_lengths(
    view: View, vertices_mm: np.ndarray, faces: np.ndarray, T_world_body: np.ndarray
) -> np.ndarray:
    """Length (mm) of each pixel centre's ray through a closed mesh moved by ``T_world_body``,
    float32 (rows, cols): its silhouette is where it is > 0."""
    uv, coef, A = _projected(view, vertices_mm, faces, T_world_body)
    out = np.zeros((view.rows, view.cols), dtype=np.float32)
    _render(uv, coef, np.ones(len(faces)), A, 1, False, out, FACE_CHUNKS)
    return out


def shape_kept(mesh: trimesh.Trimesh, faces: int) -> trimesh.Trimesh:
    """``mesh`` decimated to ``faces`` faces, twice as many as often as its volume or its area
    departs from the mesh's by more than :data:`COARSE_SHAPE_SHARE` of it (``mesh`` itself at
    most)."""
    while True:
        coarse = decimated(mesh, faces)
        if faces >= len(mesh.faces) or all(
            abs(a - b) <= COARSE_SHAPE_SHARE * abs(b)
            for a, b in ((coarse.volume, mesh.volume), (coarse.area, mesh.area))
        ):
            return coarse
        faces *= 2


def _projected(
    view: View, vertices_mm: np.ndarray, faces: np.ndarray, T_world_body: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each face's corners in pixel coordinates (T, 3, 2); per face the ray's crossing
    ``t = coef[3] / (coef[:3] . (u, v, 1))`` (``t`` = 1 on the panel); and ``A``, a sample
    (u, v)'s ray direction ``A (u, v, 1)``."""
    A = np.column_stack(
        (
            view.pitch_u_mm * view.e_u,
            view.pitch_v_mm * view.e_v,
            view.detector_origin_mm - view.source_mm,
        )
    )
    M = np.ascontiguousarray(T_world_body[:3], dtype=np.float64)
    uv, coef = _project_faces(vertices_mm, faces, M, view.matrix, A, view.source_mm)
    return uv, coef, A


@numba.njit(parallel=True, cache=True, nogil=True)
def _project_faces(vertices, faces, M, P, A, source):  # pragma: no cover
    """The corners of each face moved by ``M`` (3 x 4) and projected by ``P``, and its
    crossing coefficients (:func:`_projected`)."""
    n = vertices.shape[0]
    X = np.empty((n, 3))
    uv_v = np.empty((n, 2))
    for i in numba.prange(n):
        for r in range(3):
            X[i, r] = M[r, 0] * vertices[i, 0] + M[r, 1] * vertices[i, 1] + M[r, 2] * vertices[i, 2]
            X[i, r] += M[r, 3]
        w = P[2, 0] * X[i, 0] + P[2, 1] * X[i, 1] + P[2, 2] * X[i, 2] + P[2, 3]
        for r in range(2):
            h = P[r, 0] * X[i, 0] + P[r, 1] * X[i, 1] + P[r, 2] * X[i, 2] + P[r, 3]
            uv_v[i, r] = h / w
    m = faces.shape[0]
    uv = np.empty((m, 3, 2))
    coef = np.empty((m, 4))
    for f in numba.prange(m):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        for k in range(3):
            corner = faces[f, k]
            uv[f, k, 0] = uv_v[corner, 0]
            uv[f, k, 1] = uv_v[corner, 1]
        e1x, e1y, e1z = X[b, 0] - X[a, 0], X[b, 1] - X[a, 1], X[b, 2] - X[a, 2]
        e2x, e2y, e2z = X[c, 0] - X[a, 0], X[c, 1] - X[a, 1], X[c, 2] - X[a, 2]
        nx = e1y * e2z - e1z * e2y
        ny = e1z * e2x - e1x * e2z
        nz = e1x * e2y - e1y * e2x
        for k in range(3):
            coef[f, k] = nx * A[0, k] + ny * A[1, k] + nz * A[2, k]
        coef[f, 3] = nx * (X[a, 0] - source[0]) + ny * (X[a, 1] - source[1])
        coef[f, 3] += nz * (X[a, 2] - source[2])
    return uv, coef


@numba.njit(parallel=True, cache=True, nogil=True)
def _render(uv, coef, weight, A, s, attenuate, out, chunks):  # pragma: no cover
    """Into ``out`` (rows, cols): with ``attenuate``, the mean over each pixel's ``s x s`` rays
    of ``1 - exp(-a)``; else ``a`` of its centre's ray (``s`` = 1). ``a``, a ray's weighted
    length through the closed mesh: over the faces it crosses, ``weight[f] |d| t`` where it
    leaves minus where it enters (the attenuation where the weights are each part's, the
    length where they are 1). Only the samples within the mesh's projected bounds are
    visited; the faces are shared out in ``chunks`` (one a thread), each summing into its own
    buffer."""
    rows, cols = out.shape
    u_lo, u_hi, v_lo, v_hi = _bounds(uv)
    g0 = max(0, math.ceil((u_lo + 0.5) * s - 0.5))
    g1 = min(cols * s - 1, math.floor((u_hi + 0.5) * s - 0.5))
    h0 = max(0, math.ceil((v_lo + 0.5) * s - 0.5))
    h1 = min(rows * s - 1, math.floor((v_hi + 0.5) * s - 0.5))
    if g1 < g0 or h1 < h0:
        return
    sums = np.empty((chunks, h1 - h0 + 1, g1 - g0 + 1))
    per = (uv.shape[0] + chunks - 1) // chunks
    for c in numba.prange(chunks):
        sums[c] = 0.0
        for f in range(c * per, min((c + 1) * per, uv.shape[0])):
            _add_face(uv[f], coef[f], weight[f], s, g0, g1, h0, h1, sums[c])
    share = 1.0 / (s * s)
    for r in numba.prange(h1 // s - h0 // s + 1):
        row = h0 // s + r
        for h in range(max(h0, row * s), min(h1, row * s + s - 1) + 1):
            v = (h + 0.5) / s - 0.5
            for g in range(g0, g1 + 1):
                total = 0.0
                for c in range(chunks):
                    total += sums[c, h - h0, g - g0]
                if total == 0.0:
                    continue
                u = (g + 0.5) / s - 0.5
                dx = A[0, 0] * u + A[0, 1] * v + A[0, 2]
                dy = A[1, 0] * u + A[1, 1] * v + A[1, 2]
                dz = A[2, 0] * u + A[2, 1] * v + A[2, 2]
                length = max(total, 0.0) * math.sqrt(dx * dx + dy * dy + dz * dz)
                if attenuate:
                    out[row, g // s] += share * (1.0 - math.exp(-length))
                else:
                    out[row, g // s] += length


@numba.njit(cache=True, inline="always")
def _bounds(uv):  # pragma: no cover
    """The least and greatest u and v of the faces' corners (T, 3, 2), in one serial pass: a
    render's two parallel loops are its only parallel regions (with sleeping OpenMP threads,
    each region costs a wake-up, 0.1-0.2 ms on a 2-core VM, as much as this pass)."""
    u_lo, u_hi = math.inf, -math.inf
    v_lo, v_hi = math.inf, -math.inf
    for f in range(uv.shape[0]):
        for k in range(3):
            u_lo = min(u_lo, uv[f, k, 0])
            u_hi = max(u_hi, uv[f, k, 0])
            v_lo = min(v_lo, uv[f, k, 1])
            v_hi = max(v_hi, uv[f, k, 1])
    return u_lo, u_hi, v_lo, v_hi


@numba.njit(cache=True, inline="always")
def _add_face(uv, coef, weight, s, g0, g1, h0, h1, sums):  # pragma: no cover
    """Add one face's crossing times ``weight``, ``t`` where rays leave minus where they enter
    (``t`` = 1 on the panel), to the samples it covers: row by row, over the span of samples
    that every edge keeps on the face's side. A sample on an edge shared by two faces counts
    for exactly one of them (a ray along a mesh edge crosses the surface once): where an edge
    crosses a row is computed from its endpoints in one order whichever face asks, the face
    to its right keeps the sample, and a row along an edge belongs to the face below it."""
    au, bu, cu = uv[0, 0], uv[1, 0], uv[2, 0]
    av, bv, cv = uv[0, 1], uv[1, 1], uv[2, 1]
    area = (bu - au) * (cv - av) - (cu - au) * (bv - av)
    if area == 0.0:
        return
    side = 1.0 if area > 0.0 else -1.0
    b0 = max(h0, math.ceil((min(av, bv, cv) + 0.5) * s - 0.5))
    b1 = min(h1, math.floor((max(av, bv, cv) + 0.5) * s - 0.5))
    a0 = max(g0, math.ceil((min(au, bu, cu) + 0.5) * s - 0.5))
    a1 = min(g1, math.floor((max(au, bu, cu) + 0.5) * s - 0.5))
    ku, kv, k1, num = coef[0], coef[1], coef[2], weight * coef[3]
    for h in range(b0, b1 + 1):
        v = (h + 0.5) / s - 0.5
        lo, hi, empty = -math.inf, math.inf, False  # samples lo <= u < hi
        for e in range(3):  # edge from corner e to the next; inside: side * cross(edge, p) > 0
            pu, pv = uv[e, 0], uv[e, 1]
            qu, qv = uv[(e + 1) % 3, 0], uv[(e + 1) % 3, 1]
            if pv == qv:  # along the rows: inside below it (or above), the row itself below
                below = side * (qu - pu) > 0.0
                if (v < pv) if below else (v > pv):
                    empty = True
                elif v == pv and not below:
                    empty = True
                continue
            if (pv, pu) < (qv, qu):  # the same crossing from both faces of the edge
                cross = pu + (v - pv) * ((qu - pu) / (qv - pv))
            else:
                cross = qu + (v - qv) * ((pu - qu) / (pv - qv))
            if -side * (qv - pv) > 0.0:  # inside to the crossing's right
                lo = max(lo, cross)
            else:
                hi = min(hi, cross)
        if empty or hi <= lo:
            continue
        first = max(a0, math.ceil((lo + 0.5) * s - 0.5) - 1)
        while first <= a1 and (first + 0.5) / s - 0.5 < lo:
            first += 1
        last = min(a1, math.floor((hi + 0.5) * s - 0.5) + 1)
        while last >= first and (last + 0.5) / s - 0.5 >= hi:
            last -= 1
        row = sums[h - h0]
        base = kv * v + k1
        for g in range(first, last + 1):
            u = (g + 0.5) / s - 0.5
            denominator = ku * u + base
            if denominator > 0.0:
                row[g - g0] += num / denominator
            elif denominator < 0.0:
                row[g - g0] -= num / denominator


def implant_body(
    name: str, path: str | Path, material: str = "CoCr", unit: str = "mm"
) -> ImplantModel:
    """A component as a tracked body, from its mesh file (registration.meshes.read_mesh, then
    :func:`implant_model`).

    Args:
        name: The body's name (registration.roles: ``femoral_component``, ``tibial_tray`` and
            ``patellar_component`` play the bone they replace; any other name needs its role
            given to the tracker).
        path: The component's mesh, an STL, OBJ or PLY file.
        material: Its material, one of registration.meshes.MATERIALS.
        unit: The mesh's unit (registration.meshes.MESH_UNITS_MM).

    Examples:
        A 60 x 10 x 40 mm block of cobalt-chrome, written as an STL and read back as a body:

        >>> import tempfile
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     mesh = Path(folder) / "block.stl"
        ...     _ = trimesh.creation.box(extents=(60.0, 10.0, 40.0)).export(mesh)
        ...     body = implant_body("femoral_component", mesh)
        >>> body.name, body.centroid_mm.round(3).tolist()  # the mesh's frame is the body's
        ('femoral_component', [0.0, 0.0, 0.0])
    """
    if material not in MATERIALS:
        raise ValueError(f"{path}: material {material!r}; one of {sorted(MATERIALS)}")
    return implant_model(name, read_mesh(path, unit)[0], MATERIALS[material])


def implant_model(
    name: str,
    mesh: trimesh.Trimesh,
    material: Material,
    energy_kev: float = 70.0,
    supersample: int = 3,
    attached: Sequence[tuple[trimesh.Trimesh, Material]] = (),
) -> ImplantModel:
    """A component as a tracked body in the mesh's own frame.

    ``T_world_body`` maps mesh mm to world mm; the body's points are the centres of its 1 mm
    voxels at least half inside. ValueError for a radiolucent material.

    Args:
        name: The body's name (:func:`implant_body`'s).
        mesh: The closed component mesh (mm).
        material: Its material; must be radiopaque.
        energy_kev: Effective energy (keV) of the attenuation coefficient.
        supersample: Rays per pixel along each axis when rendering.
        attached: Parts fixed to it and moving with it, each a closed mesh in its frame and
            a material (a tray's polyethylene insert, the bone it is fixed to): rendered with
            it, not in its points.
    """
    if not material.radiopaque:
        raise ValueError(
            f"{name}: {material.name} is radiolucent: it does not show in a frame by itself "
            "and is not tracked alone"
        )
    fraction, grid = voxelize(mesh, 1.0)
    kz, ky, kx = np.nonzero(fraction >= 0.5)
    x, y, z = grid.axes_mm()
    points = np.column_stack((x[kx], y[ky], z[kz]))
    parts = [(mesh, material), *attached]
    whole = trimesh.util.concatenate([part for part, _ in parts])
    face_mu = np.concatenate(
        [np.full(len(part.faces), m.mu_per_mm(energy_kev)) for part, m in parts]
    )
    return ImplantModel(
        name,
        np.asarray(whole.vertices, dtype=np.float64),
        np.asarray(whole.faces, dtype=np.int64),
        face_mu,
        points,
        points.mean(axis=0),
        supersample,
    )
