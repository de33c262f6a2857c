"""The simulated flat panel: each exposure rendered from the geometry of its instant.

When the generator delivers a pulse (:meth:`SimDetector.exposed`, the mock generator's
exposure callback) the panel takes the TRUE view of that instant (the arms' true joints through
the scanner's kinematics, then the structure's vibration, which no encoder sees) and the
technique; :meth:`SimDetector.read_frame` renders the subject through that view and turns it
into counts with Poisson quantum noise and Gaussian readout noise (sim.scan's photon model).
Noise is seeded by the seed and the true view of the pulse: the same motion gives the same
frames, also when a scan is resumed in a new session.
"""

from __future__ import annotations

import threading
import zlib
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from recon.config import ExposureSpec
from recon.geometry import DetectorSpec, View
from sim.scan import detected_counts, photons_per_pixel


class SimFrame(NamedTuple):
    """One read-out (the fields of scanner.hardware.Frame)."""

    counts: np.ndarray
    t_s: float


class FrameTimeout(TimeoutError):
    """No frame arrived (nothing exposed, or a dropped frame)."""


class SimDetector:
    """A panel that renders ``subject`` through the view ``true_view()`` at each exposure.

    Args:
        panel: rows, columns and pixel pitch as read out.
        true_view: the view the scanner really realises now.
        subject: line integrals of the imaged object through a view, (rows, cols).
        now: the clock (frame time stamps).
        sdd_mm: nominal source-detector distance of the flood calibration.
        seed: noise seed.

    ``true_views`` keeps the view of every pulse (ground truth).
        drop_frame_at: exposure number (0-based) whose frame never arrives (fault injection).
        log: event log callback (device, event).
    """

    def __init__(
        self,
        panel: DetectorSpec,
        true_view: Callable[[], View],
        subject: Callable[[View], np.ndarray],
        now: Callable[[], float],
        *,
        sdd_mm: float,
        seed: int = 0,
        drop_frame_at: int | None = None,
        log: Callable[[str, str], None] | None = None,
    ) -> None:
        self.rows, self.cols, self.pixel_pitch_mm = panel.rows, panel.cols, panel.pixel_pitch_mm
        self.panel = panel
        self._true_view = true_view
        self._subject = subject
        self._now = now
        self.sdd_mm = sdd_mm
        self.seed = seed
        self.drop_frame_at = drop_frame_at
        self._log = log or (lambda _who, _what: None)
        self._lock = threading.Lock()
        self._pending: tuple[View, ExposureSpec, int] | None = None
        self._armed = False
        self.exposures = 0
        self.true_views: list[View] = []
        self.connected = False

    def connect(self, timeout_s: float) -> None:
        self.connected = True

    def arm(self, timeout_s: float) -> None:
        if not self.connected:
            raise RuntimeError("detector.arm: not connected")
        with self._lock:
            self._pending = None
            self._armed = True

    def exposed(self, kv: float, ma: float, ms: float, *_: object) -> None:
        """A pulse was delivered now: capture the true view and the technique."""
        view = self._true_view()
        with self._lock:
            number = self.exposures
            self.exposures += 1
            self.true_views.append(view)
            if self._armed:
                technique = ExposureSpec(tube_kv=kv, tube_ma=ma, pulse_ms=ms)
                self._pending = (view, technique, number)
                self._armed = False
        self._log("detector", f"integrated exposure {number}")

    def read_frame(self, timeout_s: float) -> SimFrame:
        with self._lock:
            pending, self._pending = self._pending, None
        if pending is None:
            raise FrameTimeout(f"detector: no exposure integrated within {timeout_s} s")
        view, technique, number = pending
        if number == self.drop_frame_at:
            self._log("detector", f"dropped frame {number}")
            raise FrameTimeout(f"detector: frame of exposure {number} lost (injected fault)")
        line_integrals = self._subject(view)
        photons = photons_per_pixel(technique, self.panel, view.sdd_mm)
        rng = np.random.default_rng([self.seed, zlib.crc32(view.matrix.tobytes())])
        counts = detected_counts(np.asarray(line_integrals), photons, rng)
        return SimFrame(counts, self._now())

    def flood_counts(self, technique) -> np.ndarray:
        """Mean unattenuated counts per pixel at ``technique`` (kv, ma, ms attributes)."""
        spec = ExposureSpec(tube_kv=technique.kv, tube_ma=technique.ma, pulse_ms=technique.ms)
        value = photons_per_pixel(spec, self.panel, self.sdd_mm)
        return np.full((self.rows, self.cols), value, dtype=np.float32)

    def close(self) -> None:
        self.connected = False
