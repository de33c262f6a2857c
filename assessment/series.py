"""The 4D series: each bone's surface moved by its pose in every frame, exported as one mesh set
per frame (binary STL, world mm) and logged to rerun on a "frame" timeline."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import rerun as rr
import trimesh
from skimage.measure import marching_cubes

from recon.volume import Volume

MESH_STEP_VOXELS = 3
"""Marching-cubes step: coarser meshes keep a 30-frame series to tens of MB."""


def bone_mesh(labels: Volume, label_values: tuple[int, ...]) -> trimesh.Trimesh:
    """Surface mesh (world mm) of the voxels carrying any of ``label_values``."""
    mask = np.isin(labels.data, label_values)
    if not mask.any():
        raise ValueError(f"labels {list(label_values)} are missing from the label volume")
    spacing_zyx = labels.grid.spacing_mm[::-1]
    verts, faces, _, _ = marching_cubes(
        np.pad(mask, 1).astype(np.float32), 0.5, spacing=spacing_zyx, step_size=MESH_STEP_VOXELS
    )
    origin_zyx = np.array(labels.grid.origin_mm[::-1]) - np.array(spacing_zyx)
    return trimesh.Trimesh(vertices=(verts + origin_zyx)[:, ::-1], faces=faces[:, ::-1])


def export_series(
    meshes: dict[str, trimesh.Trimesh],
    frames: np.ndarray,
    poses: dict[str, np.ndarray],
    folder: Path,
) -> list[Path]:
    """Write ``folder/frame_<k>/<bone>.stl`` for every frame k (poses: bone -> (F, 4, 4))."""
    folder.mkdir(parents=True, exist_ok=False)
    written = []
    for i, frame in enumerate(frames):
        sub = folder / f"frame_{int(frame):04d}"
        sub.mkdir()
        for bone, mesh in meshes.items():
            moved = mesh.copy()
            moved.apply_transform(poses[bone][i])
            path = sub / f"{bone}.stl"
            moved.export(path)
            written.append(path)
    return written


def record_series(
    meshes: dict[str, trimesh.Trimesh],
    frames: np.ndarray,
    poses: dict[str, np.ndarray],
    path: Path,
    application_id: str = "dualarm-cbct",
) -> Path:
    """A rerun recording: each bone's mesh once, its pose per frame on the "frame" timeline."""
    if path.exists():
        raise FileExistsError(f"{path} exists: recordings are never written over")
    rec = rr.RecordingStream(application_id)
    rec.save(path)
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    for bone, mesh in meshes.items():
        rec.log(
            f"world/bones/{bone}",
            rr.Mesh3D(vertex_positions=mesh.vertices, triangle_indices=mesh.faces),
            static=True,
        )
    for i, frame in enumerate(frames):
        rec.set_time("frame", sequence=int(frame))
        for bone in meshes:
            T = poses[bone][i]
            rec.log(f"world/bones/{bone}", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
    rec.flush()
    rec.disconnect()
    return path
