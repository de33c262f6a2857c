"""QA a user can see: every frame with each tracked body's outline at its registered pose.

``overlays/frame_NNNN.png``: the frame as fluoroscopy shows it (attenuation dark), each body's
silhouette outline drawn over it in its colour (femur orange, tibia cyan, patella magenta), a
failed registration's dashed. A component's silhouette is exact (the pixels whose ray meets its
mesh); a bone's is its DRR's support (the objective's silhouette threshold).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import SimpleITK as sitk
from scipy.ndimage import binary_erosion

from recon.geometry import View
from registration.implants import ImplantModel
from registration.roles import KNOWN_ROLES

COLOURS = {
    "femur": (255, 150, 30),
    "tibia": (40, 210, 255),
    "patella": (240, 60, 240),
}
"""Outline colour of the body playing each role (RGB; registration.roles)."""
BONE_SILHOUETTE = 0.02
"""A bone's DRR above this (line integral) is its silhouette (as the objective's)."""


def silhouette(model, view: View, T_world_body: np.ndarray) -> np.ndarray:
    """The pixels of ``view`` the body at ``T_world_body`` covers, bool (rows, cols)."""
    if isinstance(model, ImplantModel):
        return model.silhouette(view, T_world_body)
    return model.render(view, T_world_body) > BONE_SILHOUETTE


def outline(mask: np.ndarray) -> np.ndarray:
    """The boundary pixels of a silhouette (inside, next to outside)."""
    return mask & ~binary_erosion(mask, border_value=0)


def overlay(frame: np.ndarray, outlines: dict[str, tuple[np.ndarray, bool]]) -> np.ndarray:
    """An RGB image (rows, cols, 3) uint8: ``frame`` (0..1 attenuation stand-in) shown dark
    where it attenuates, each body's outline in its colour (dashed where ``failed``)."""
    grey = np.clip(1.0 - frame, 0.0, 1.0)
    rgb = np.repeat((255.0 * grey).astype(np.uint8)[..., None], 3, axis=2)
    rows, cols = np.indices(frame.shape)
    for name, (line, failed) in outlines.items():
        draw = line & ((rows + cols) % 6 < 3) if failed else line
        rgb[draw] = COLOURS.get(KNOWN_ROLES.get(name), (255, 255, 0))
    return rgb


def write_overlays(
    folder: Path, frames: np.ndarray, view: View, models: dict, results: Sequence
) -> list[Path]:
    """One PNG per frame into the new ``folder``: ``frames[k]`` with ``results[k]``
    (registration.results.FrameResult; named by its frame number). Where the view's rows go
    up in the world (+z, the scanner's up), the image is flipped so that up is at its top, as
    a reader expects; other views' images keep the frames' row order (a JointTrack frame's
    row 0 is its top)."""
    folder.mkdir(parents=True)
    upright = view.e_v[2] > 0.5
    written = []
    for image, result in zip(frames, results, strict=True):
        outlines = {
            name: (outline(silhouette(models[name], view, bone.T_world_body)), bone.failed)
            for name, bone in result.bodies.items()
        }
        path = folder / f"frame_{result.frame:04d}.png"
        rgb = overlay(image, outlines)
        sitk.WriteImage(sitk.GetImageFromArray(rgb[::-1] if upright else rgb, True), path)
        written.append(path)
    return written


def write_side_by_side(folder: Path, views: Sequence[Path], gap: int = 4) -> list[Path]:
    """One PNG per frame into the new ``folder``: each camera's overlay of the frame (the
    ``frame_NNNN.png`` of each folder of ``views``, in order) side by side, top-aligned, ``gap``
    black pixels apart; the frames of the first camera's folder."""
    folder.mkdir(parents=True)
    written = []
    for first in sorted(Path(views[0]).glob("frame_*.png")):
        images = [sitk.GetArrayFromImage(sitk.ReadImage(str(v / first.name))) for v in views]
        height = max(image.shape[0] for image in images)
        parts = []
        for image in images:
            padded = np.zeros((height, image.shape[1] + gap, 3), dtype=image.dtype)
            padded[: image.shape[0], : image.shape[1]] = image
            parts.append(padded)
        path = folder / first.name
        sitk.WriteImage(sitk.GetImageFromArray(np.hstack(parts)[:, :-gap], True), path)
        written.append(path)
    return written
