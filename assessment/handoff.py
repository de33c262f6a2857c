"""The tracked motion for other tools: ITK transforms, Autoscoper ``.tra`` files and a 3D Slicer
scene.

Every file states the same poses as ``poses.csv`` (registration.poses): ``T_world_body`` moves a
bone from where the static scan saw it to where it is in a frame, in world mm, and the world
frame is DICOM/ITK's LPS patient frame (docs/conventions.md). What each format adds:

- ITK (``itk/<bone>/frame_<k>.tfm``): an ``AffineTransform_double_3_3`` in LPS mm holding ITK's
  resampling direction, the inverse of the pose: it maps a point of the frame to the point of
  the static scan it came from, so ``sitk.Resample(static, transform)`` shows the static volume
  with the bone where the frame has it, and 3D Slicer (which reads ITK files as the
  "from parent" transform) moves a model placed under it to the frame.
- Autoscoper (``autoscoper/<bone>.tra``): see :func:`write_tra`.
- 3D Slicer (``scene.mrml``): see :mod:`assessment.slicer_scene`.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import SimpleITK as sitk
import trimesh

from assessment.slicer_scene import add_stl_header, write_scene, write_sequence
from recon.io import check_image_file
from registration.poses import BodyPose, check_rigid, poses_by_frame


@dataclass(frozen=True)
class Motion:
    """Each bone's pose in every frame.

    Attributes:
        frames: frame numbers (F,), increasing.
        poses: bone -> (F, 4, 4) ``T_world_body`` (LPS mm).
    """

    frames: np.ndarray
    poses: dict[str, np.ndarray]

    @classmethod
    def of(cls, poses: list[BodyPose]) -> Motion:
        """The motion of every bone in ``poses`` (every frame must hold every bone)."""
        bones = tuple(sorted({p.body for p in poses}))
        frames, stacks = poses_by_frame(poses, bones)
        return cls(frames, stacks)


def itk_transform(T_world_body: np.ndarray) -> sitk.AffineTransform:
    """The ITK (resampling) transform of a pose: frame point -> static-scan point, LPS mm."""
    inverse = np.linalg.inv(check_rigid(T_world_body, "pose"))
    transform = sitk.AffineTransform(3)
    transform.SetMatrix(inverse[:3, :3].ravel().tolist())
    transform.SetTranslation(inverse[:3, 3].tolist())
    return transform


def pose_of_itk(transform: sitk.Transform) -> np.ndarray:
    """The pose ``T_world_body`` an ITK transform file written by :func:`write_itk` holds."""
    affine = sitk.AffineTransform(transform)
    inverse = np.eye(4)
    inverse[:3, :3] = np.reshape(affine.GetMatrix(), (3, 3))
    centre = np.array(affine.GetCenter())
    inverse[:3, 3] = np.array(affine.GetTranslation()) + centre - inverse[:3, :3] @ centre
    return np.linalg.inv(inverse)


def write_itk(folder: Path, motion: Motion) -> list[Path]:
    """``folder/<bone>/frame_<k>.tfm`` for every bone and frame."""
    written = []
    for bone, stack in motion.poses.items():
        (folder / bone).mkdir(parents=True)
        for frame, T in zip(motion.frames, stack, strict=True):
            path = folder / bone / f"frame_{int(frame):04d}.tfm"
            sitk.WriteTransform(itk_transform(T), str(path))
            written.append(path)
    return written


def write_models(folder: Path, meshes: dict[str, trimesh.Trimesh]) -> dict[str, Path]:
    """Each bone's surface in the static scan's pose, binary STL in LPS mm."""
    folder.mkdir(parents=True)
    paths = {}
    for bone, mesh in meshes.items():
        paths[bone] = folder / f"{bone}.stl"
        mesh.export(paths[bone])
    return paths


def write_tra(path: Path, frames: np.ndarray, poses: np.ndarray) -> Path:
    """Autoscoper's tracking file of one bone (its "volume"), as Autoscoper saves it by default
    (matrix, comma, row-major, mm): line i is frame i, from frame 0 to the last; each line is
    the pose's 16 numbers row by row (R00, R01, R02, tx, ..., 0, 0, 0, 1), mapping the static
    scan's world coordinates (LPS mm) to the frame's; frames without a pose are rows of NaN,
    as Autoscoper marks untracked frames."""
    if len(frames) and int(frames.min()) < 0:
        raise ValueError(f"{path}: frame numbers must be >= 0, got {int(frames.min())}")
    rows = np.full((int(frames.max()) + 1 if len(frames) else 0, 16), np.nan)
    for frame, T in zip(frames, poses, strict=True):
        rows[int(frame)] = check_rigid(T, f"{path}: frame {int(frame)}").ravel()
    text = "".join(",".join(_tra_number(x) for x in row) + "\n" for row in rows)
    path.write_text(text, encoding="ascii")
    return path


def read_tra(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Frame numbers and poses (F, 4, 4) of the tracked (non-NaN) rows of a ``.tra`` file."""
    rows = np.loadtxt(path, delimiter=",", ndmin=2)
    if rows.shape[1] != 16:
        raise ValueError(f"{path}: {rows.shape[1]} numbers per line, expected 16")
    tracked = ~np.isnan(rows).any(axis=1)
    return np.flatnonzero(tracked), rows[tracked].reshape(-1, 4, 4)


def _tra_number(x: float) -> str:
    return "NaN" if np.isnan(x) else f"{x:.16f}"


def write_handoff(
    folder: Path,
    motion: Motion,
    meshes: dict[str, trimesh.Trimesh],
    volume: Path | None = None,
) -> list[Path]:
    """Write the hand-off into the new folder ``folder``: ``itk/``, ``autoscoper/``,
    ``models/``, ``motion/``, the static volume (copied; a DICOM folder becomes
    ``static.nii.gz``) and ``scene.mrml``. Returns every file written."""
    missing = sorted(set(motion.poses) - set(meshes))
    if missing:
        raise ValueError(f"{folder}: no bone model for the tracked bone(s) {missing}")
    kind = None if volume is None else check_static_volume(volume)
    folder.mkdir(parents=True, exist_ok=False)
    written = write_itk(folder / "itk", motion)
    (folder / "autoscoper").mkdir()
    for bone, stack in motion.poses.items():
        written.append(write_tra(folder / "autoscoper" / f"{bone}.tra", motion.frames, stack))
    models = write_models(folder / "models", {b: meshes[b] for b in motion.poses})
    for path in models.values():
        add_stl_header(path)
    (folder / "motion").mkdir()
    sequences = {
        bone: write_sequence(folder / "motion" / f"{bone}.seq.mha", bone, motion.frames, stack)
        for bone, stack in motion.poses.items()
    }
    static = None if volume is None else _static_volume(volume, kind, folder)
    scene = write_scene(
        folder / "scene.mrml",
        None if static is None else static.name,
        {b: p.relative_to(folder).as_posix() for b, p in models.items()},
        {b: p.relative_to(folder).as_posix() for b, p in sequences.items()},
        motion.frames,
    )
    extra = [] if static is None else [static]
    return [*written, *models.values(), *sequences.values(), *extra, scene]


def _static_volume(volume: Path, suffix: str, folder: Path) -> Path:
    """The static scan beside the scene: a copy of a volume file (a MetaImage header and its
    data as one .mha), a DICOM series folder written as NIfTI (its HU and LPS placement kept by
    SimpleITK). A copy, not a link: the scene's volume cannot change the study's. ``suffix``:
    :func:`check_static_volume`'s."""
    if suffix == "dicom":
        reader = sitk.ImageSeriesReader()
        ids = reader.GetGDCMSeriesIDs(str(volume))
        reader.SetFileNames(reader.GetGDCMSeriesFileNames(str(volume), ids[0]))
        image, target = reader.Execute(), folder / "static.nii.gz"
    elif suffix == ".mhd":
        image, target = sitk.ReadImage(str(volume)), folder / "static.mha"
    else:
        return Path(shutil.copyfile(volume, folder / f"static{suffix}"))
    sitk.WriteImage(image, str(target), True)
    return target


STATIC_SUFFIXES = (".nii.gz", ".nii", ".mha", ".mhd", ".nrrd")
"""File name endings of a static volume for the hand-off (or a DICOM series folder)."""


def check_static_volume(volume: Path) -> str:
    """Check the static volume for the hand-off by reading its header (a DICOM folder: that it
    holds one series); return its suffix, or "dicom" for a folder. Errors name the path.

    Args:
        volume: A volume file or a DICOM series folder.
    """
    if volume.is_dir():
        ids = sitk.ImageSeriesReader.GetGDCMSeriesIDs(str(volume))
        if len(ids) != 1:
            raise ValueError(
                f"{volume}: the static volume's folder holds {len(ids)} DICOM series; give a "
                "folder with one"
            )
        return "dicom"
    if not volume.is_file():
        raise FileNotFoundError(f"{volume}: no such volume file or DICOM folder")
    name = volume.name.lower()
    suffix = next((s for s in STATIC_SUFFIXES if name.endswith(s)), None)
    if suffix is None:
        raise ValueError(
            f"{volume}: the static volume must be one file ({', '.join(STATIC_SUFFIXES)}) or "
            "a DICOM series folder"
        )
    check_image_file(volume)
    return suffix
