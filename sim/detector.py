"""The simulated flat panel: each exposure rendered from the geometry of its instant.

:meth:`SimDetector.arm` opens an integration window. When the generator delivers a pulse in it
(:meth:`SimDetector.exposed`, the mock generator's exposure callback) the panel takes the TRUE
view of that instant (the arms' true joints through the scanner's kinematics, then the
structure's vibration, which no encoder sees) and the technique; :meth:`SimDetector.read_frame`
renders the subject through that view, draws the photons' Poisson noise (sim.scan's photon
model) and reads them out through the panel's sensor (:class:`sim.panel.PanelSensor`: offset,
gain, defects, lag, read-out noise; raw uint16 counts). A window without a pulse reads a dark
frame. Quantum noise is seeded by the seed and the true view of the pulse: the same motion
gives the same photons, also when a scan is resumed in a new session.
"""

from __future__ import annotations

import threading
import zlib
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from recon.config import ExposureSpec
from recon.geometry import DetectorSpec, View
from sim.panel import PanelSensor, SimPanelSpec
from sim.scan import photons_per_pixel

REFERENCE_TECHNIQUE = ExposureSpec(tube_kv=110.0, tube_ma=51.0, pulse_ms=15.0)
"""The technique at which an unattenuated pixel reads the panel's ``flood_adu`` (every read-out
mode's conversion gain is set from it at the nominal source-detector distance)."""


class SimFrame(NamedTuple):
    """One read-out (the fields of scanner.hardware.Frame)."""

    counts: np.ndarray
    t_s: float


Subject = Callable[[View, float], np.ndarray]
"""Line integrals (rows, cols) of the imaged object through a view at a clock time, s."""


class FrameTimeout(TimeoutError):
    """No frame arrived (the panel was not armed, or a dropped frame)."""


class SimDetector:
    """A panel that renders ``subject`` through the view ``true_view()`` at each exposure.

    Args:
        panel: rows, columns and pixel pitch as read out.
        true_view: the view the scanner really realises now.
        subject: line integrals of the imaged object through a view at a time (the clock's,
            s), (rows, cols).
        now: the clock (frame time stamps).
        sdd_mm: nominal source-detector distance, mm (the conversion gain's reference).
        seed: noise seed (also the panel's defects).
        sensor: the panel's imperfections (default: :class:`sim.panel.SimPanelSpec`'s).
        drop_frame_at: exposure number (0-based) whose frame never arrives (fault injection).
        log: event log callback (device, event).

    ``true_views`` and ``true_times_s`` keep the view and the clock of every pulse (ground
    truth).
    """

    def __init__(
        self,
        panel: DetectorSpec,
        true_view: Callable[[], View],
        subject: Subject,
        now: Callable[[], float],
        *,
        sdd_mm: float,
        seed: int = 0,
        sensor: SimPanelSpec | None = None,
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
        self._pending: tuple[View, float, ExposureSpec, int] | None = None
        self._armed = False
        self._pulsed = threading.Event()
        self.exposures = 0
        self.true_views: list[View] = []
        self.true_times_s: list[float] = []
        self.connected = False
        spec = sensor or SimPanelSpec()
        reference = photons_per_pixel(REFERENCE_TECHNIQUE, panel, sdd_mm)
        self.sensor = PanelSensor(spec, panel.rows, panel.cols, spec.flood_adu / reference, seed)
        self.serial = spec.serial
        self.mode = f"{panel.cols}x{panel.rows} Mono16"
        self._darks = 0

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
        view, t_s = self._true_view(), self._now()
        with self._lock:
            number = self.exposures
            self.exposures += 1
            self.true_views.append(view)
            self.true_times_s.append(t_s)
            if self._armed:
                technique = ExposureSpec(tube_kv=kv, tube_ma=ma, pulse_ms=ms)
                self._pending = (view, t_s, technique, number)
                self._armed = False
                self._pulsed.set()
        self._log("detector", f"integrated exposure {number}")

    def integrate(self, window_s: float) -> np.ndarray:
        """The sensor behind a read-out of its own (the fake GigE Vision panel's): the frame of
        the first pulse that arrives within ``window_s`` s, else a dark frame, raw uint16. The
        sensor stays armed between calls: the trigger that asks for a frame travels through
        the camera while the generator may already be firing, and that pulse is the frame's."""
        if not self._pulsed.wait(window_s):
            with self._lock:
                self._armed = True  # a dark frame
        try:
            return np.asarray(self.read_frame(window_s).counts)
        finally:
            with self._lock:
                self._pulsed.clear()
                self._armed = True

    def read_frame(self, timeout_s: float) -> SimFrame:
        with self._lock:
            pending, self._pending = self._pending, None
            armed, self._armed = self._armed, False
        if pending is None:
            if not armed:
                raise FrameTimeout(f"detector: not armed, no frame within {timeout_s} s")
            self._darks += 1
            rng = np.random.default_rng([self.seed, 1, self._darks])
            return SimFrame(self.sensor.read(None, rng), self._now())
        view, t_s, technique, number = pending
        if number == self.drop_frame_at:
            self._log("detector", f"dropped frame {number}")
            raise FrameTimeout(f"detector: frame of exposure {number} lost (injected fault)")
        line_integrals = np.asarray(self._subject(view, t_s), dtype=np.float64)
        photons = photons_per_pixel(technique, self.panel, view.sdd_mm)
        rng = np.random.default_rng([self.seed, zlib.crc32(view.matrix.tobytes())])
        detected = rng.poisson(photons * np.exp(-line_integrals))
        return SimFrame(self.sensor.read(detected, rng), self._now())

    def close(self) -> None:
        self.connected = False
