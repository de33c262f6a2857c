"""The soft tissue around the tracked bones, deformed by their poses in the frame being
registered (registration.drr.SoftTissue), and the static scan's cuts through it as the panel
sees them."""

from __future__ import annotations

import math

import numpy as np
from scipy.ndimage import distance_transform_edt

from recon.geometry import View
from recon.project import JosephProjector
from registration.drr import SoftTissue

EDGE_ON_DEG = 45.0
"""A face of the static scan's box cuts the leg with a step in the DRR where the rays graze it
within this angle (registration.drr.cut_outlines); seen more face-on, what it leaves out
thins out to nothing at its outline."""

DEFORMATION_REUSE_MM = 1.0
DEFORMATION_CARRY_MM = 5.0
DEFORMATION_REUSE_REACH_MM = 60.0
"""The soft tissue deformed by a pair of femur and tibia poses is reused for poses that move
no corner of the cube of this half-width about the joint centre by more than
DEFORMATION_REUSE_MM (its lattice is ~2 mm), or DEFORMATION_CARRY_MM for the body registered,
which carries its share of the tissue from its pose in the deformation (to first order)."""

Split = tuple[JosephProjector, tuple[JosephProjector, np.ndarray] | None]
"""What stays when a body moves (a projector), and what it carries (a projector and the
body's pose in the deformation, 4x4 mm) or None."""


class DeformedTissue:
    """The soft tissue deformed by the femur's and the tibia's poses, kept for the frame being
    registered and reused for poses nearby.

    Args:
        soft_tissue: the static scan's soft tissue.
        view: the fluoroscopy view at full resolution.
    """

    def __init__(self, soft_tissue: SoftTissue, view: View) -> None:
        self.soft_tissue, self.view = soft_tissue, view
        self._knees: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        """The frame's (femur, tibia) pose pairs the soft tissue was deformed by."""
        self._deformed: dict[int, tuple] = {}
        """Per pose pair of :attr:`_knees`: the deformed soft tissue."""
        self._split: dict[tuple[int, str], Split] = {}
        """Per pose pair and body: what stays, what the body carries."""
        reach = DEFORMATION_REUSE_REACH_MM * np.array([-1.0, 1.0])
        self._knee_corners = soft_tissue.joint_mm + np.array(
            [[x, y, z] for x in reach for y in reach for z in reach]
        )

    def clear(self) -> None:
        """Forget the deformations (a new frame)."""
        self._knees.clear()
        self._deformed.clear()
        self._split.clear()

    def split(self, name: str, poses: dict[str, np.ndarray]) -> Split:
        """The soft tissue deformed by ``poses``: what stays when body ``name`` moves, and
        what it carries (registration.drr.SoftTissue.split, averaged over pairs of slices
        along the rays: rendered every evaluation) with the body's pose in the deformation;
        reused for poses nearby (:meth:`_near`)."""
        knee = next((k for k, pair in self._knees.items() if self._near(name, pair, poses)), None)
        if knee is None:
            knee = len(self._knees)
            self._knees[knee] = (poses["femur"], poses["tibia_fibula"])
            self._deformed[knee] = self.soft_tissue.deformed(*self._knees[knee], self.view)
        if (knee, name) not in self._split:
            axis = int(np.argmax(np.abs(self.view.normal)))  # the rays' main axis
            stays, carried = self.soft_tissue.split(self._deformed[knee], name, axis)
            if carried is not None:  # with the bone's pose in the deformation
                carried = (carried, self._knees[knee][name != "femur"])
            self._split[knee, name] = (stays, carried)
        return self._split[knee, name]

    def _near(self, name: str, knee: tuple[np.ndarray, np.ndarray], poses) -> bool:
        """Whether the (femur, tibia) poses ``knee`` and those in ``poses`` move no corner of
        the knee's cube (:data:`DEFORMATION_REUSE_REACH_MM`) further apart than
        :data:`DEFORMATION_REUSE_MM` (:data:`DEFORMATION_CARRY_MM` for body ``name``, which
        carries its share of the tissue)."""
        corners = self._knee_corners
        return all(
            np.abs(corners @ (A[:3, :3] - B[:3, :3]).T + (A[:3, 3] - B[:3, 3])).max()
            <= (DEFORMATION_CARRY_MM if bone == name else DEFORMATION_REUSE_MM)
            for bone, A, B in zip(
                ("femur", "tibia_fibula"),
                knee,
                (poses["femur"], poses["tibia_fibula"]),
                strict=True,
            )
        )


def truncation_mask(
    soft_tissue: SoftTissue,
    view: View,
    band_mm: float,
    name: str,
    poses: dict[str, np.ndarray],
    reach: tuple[np.ndarray, ...],
) -> np.ndarray | None:
    """The pixels of ``view`` within ``band_mm`` of the static scan's cuts
    (registration.drr.SoftTissue.cuts) seen within :data:`EDGE_ON_DEG` of edge-on, carried by
    the femur and the tibia at ``poses`` (body ``name``'s also at ``reach``); None when
    nothing is cut nearby."""
    pad = math.ceil(band_mm / view.pitch_u_mm)  # cuts just off the panel reach onto it
    hit = np.zeros((view.rows + 2 * pad, view.cols + 2 * pad), dtype=bool)
    for carrier, (points, normals) in soft_tissue.cuts.items():
        for T in (poses[carrier], *(reach if carrier == name else ())):
            moved = points @ T[:3, :3].T + T[:3, 3]
            rays = moved - view.source_mm
            facing = np.abs(np.sum(rays * (normals @ T[:3, :3].T), axis=1))
            edge_on = facing < math.sin(math.radians(EDGE_ON_DEG)) * np.linalg.norm(rays, axis=1)
            u, v = np.rint(view.project(moved[edge_on]) + pad).T
            on = (u >= 0) & (u < hit.shape[1]) & (v >= 0) & (v < hit.shape[0])
            hit[v[on].astype(int), u[on].astype(int)] = True
    if not hit.any():
        return None
    near = distance_transform_edt(~hit, sampling=(view.pitch_v_mm, view.pitch_u_mm))
    return (near <= band_mm)[pad:-pad, pad:-pad]
