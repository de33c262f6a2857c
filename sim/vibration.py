"""Repeatable arm vibration: the geometry a vibrating scanner really acquires.

Each view's focal spot and panel centre are displaced and the panel tilted by smooth,
view-dependent offsets (a sum of a few sinusoids in the view index with seeded phases) whose
RMS amplitudes are configured. The same seed gives the same offsets for the same protocol:
the arms' vibration repeats from scan to scan, which is what lets a calibration scan correct
later patient scans.
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.spatial.transform import Rotation

from recon.geometry import Geometry, View

HARMONICS = 4


class VibrationSpec(BaseModel):
    """RMS amplitudes of the per-view offsets, and the seed of their pattern."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    source_mm: float = Field(0.5, ge=0.0, le=20.0)
    detector_mm: float = Field(0.5, ge=0.0, le=20.0)
    detector_deg: float = Field(0.2, ge=0.0, le=10.0)
    seed: int = 0


def _pattern(n_views: int, rng: np.random.Generator, rms: float) -> np.ndarray:
    """(n_views, 3) smooth offsets with the given RMS norm."""
    t = np.arange(n_views)[:, None]
    out = np.zeros((n_views, 3))
    for k in range(1, HARMONICS + 1):
        amplitude = rng.normal(size=3) / k
        phase = rng.uniform(0, 2 * np.pi, 3)
        out += amplitude * np.sin(2 * np.pi * k * t / max(n_views, 2) * 3.7 + phase)
    out += 0.3 * rng.normal(size=(n_views, 3)) / np.sqrt(3)  # a little view-to-view jitter
    norm = np.sqrt(np.mean(np.sum(out**2, axis=1)))
    return out * (rms / norm) if norm > 0 else out


def vibrate(geometry: Geometry, spec: VibrationSpec) -> Geometry:
    """The geometry perturbed by the vibration pattern ``spec`` (one offset set per view)."""
    rng = np.random.default_rng(spec.seed)
    n = len(geometry)
    ds = _pattern(n, rng, spec.source_mm)
    dc = _pattern(n, rng, spec.detector_mm)
    tilt = _pattern(n, rng, np.radians(spec.detector_deg))
    views = []
    for i, view in enumerate(geometry):
        R = Rotation.from_rotvec(tilt[i]).as_matrix()
        center = view.detector_center_mm + dc[i]
        e_u, e_v = R @ view.e_u, R @ view.e_v
        half_u = 0.5 * (view.cols - 1) * view.pitch_u_mm * e_u
        half_v = 0.5 * (view.rows - 1) * view.pitch_v_mm * e_v
        views.append(
            View(
                view.source_mm + ds[i],
                center - half_u - half_v,
                e_u,
                e_v,
                view.pitch_u_mm,
                view.pitch_v_mm,
                view.rows,
                view.cols,
            )
        )
    return Geometry(views)
