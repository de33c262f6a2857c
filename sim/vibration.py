"""Repeatable arm vibration: the geometry a vibrating scanner really acquires.

Each view's focal spot and panel centre are displaced and the panel tilted by smooth offsets
(a sum of a few sinusoids with seeded phases) whose RMS amplitudes are configured: in the view
index for a whole geometry (:func:`vibrate`), or in the rotary angle for the mock arms
(:func:`vibrate_at`: the structure flexes the same way wherever the orbit passes the same
angle). The encoders do not see it. The same seed gives the same offsets for the same
protocol: the vibration repeats from scan to scan, which is what lets a calibration scan
correct later patient scans.
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


def _displaced(view: View, ds: np.ndarray, dc: np.ndarray, tilt_rad: np.ndarray) -> View:
    """``view`` with the focal spot moved by ``ds``, the panel centre by ``dc`` (mm) and the
    panel tilted by the rotation vector ``tilt_rad`` about its centre."""
    R = Rotation.from_rotvec(tilt_rad).as_matrix()
    center = view.detector_center_mm + dc
    e_u, e_v = R @ view.e_u, R @ view.e_v
    half_u = 0.5 * (view.cols - 1) * view.pitch_u_mm * e_u
    half_v = 0.5 * (view.rows - 1) * view.pitch_v_mm * e_v
    return View(
        view.source_mm + ds,
        center - half_u - half_v,
        e_u,
        e_v,
        view.pitch_u_mm,
        view.pitch_v_mm,
        view.rows,
        view.cols,
    )


def vibrate(geometry: Geometry, spec: VibrationSpec) -> Geometry:
    """The geometry perturbed by the vibration pattern ``spec`` (one offset set per view)."""
    rng = np.random.default_rng(spec.seed)
    n = len(geometry)
    ds = _pattern(n, rng, spec.source_mm)
    dc = _pattern(n, rng, spec.detector_mm)
    tilt = _pattern(n, rng, np.radians(spec.detector_deg))
    return Geometry([_displaced(view, ds[i], dc[i], tilt[i]) for i, view in enumerate(geometry)])


def _angular(rng: np.random.Generator, rms: float, theta_rad: float) -> np.ndarray:
    """A smooth 3-vector function of the rotary angle with RMS norm ``rms`` over a turn."""
    k = np.arange(1, HARMONICS + 1)[:, None]
    amplitude = rng.normal(size=(HARMONICS, 3)) / k
    phase = rng.uniform(0, 2 * np.pi, (HARMONICS, 3))
    norm = np.sqrt(0.5 * np.sum(amplitude**2))  # RMS of distinct-frequency sinusoids
    value = np.sum(amplitude * np.sin(3 * k * theta_rad + phase), axis=0)
    return value * (rms / norm)


def vibrate_at(view: View, spec: VibrationSpec, rotary_deg: float) -> View:
    """``view`` as the flexing structure really realises it at rotary angle ``rotary_deg``."""
    rng = np.random.default_rng(spec.seed)
    theta = np.radians(rotary_deg)
    ds = _angular(rng, spec.source_mm, theta)
    dc = _angular(rng, spec.detector_mm, theta)
    tilt = _angular(rng, np.radians(spec.detector_deg), theta)
    return _displaced(view, ds, dc, tilt)
