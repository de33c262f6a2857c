"""A flat panel over GigE Vision, through Aravis (GObject introspection).

:class:`GigEPanel` satisfies :class:`scanner.hardware.Detector`. It reads the panel's whole
sensor (Width x Height at offset 0: a crop would move the image off the calibrated detector
frame) as Mono16, with ExposureTime as the integration window, triggered either by software
(``TriggerSoftware``, executed in :meth:`GigEPanel.arm`) or by the generator's exposure line
(``Line0``). Aravis is imported when the panel connects, so this module imports without it.

Every frame is checked before it is handed out: buffer status SUCCESS (else incomplete), block
(frame) id one past the previous frame's (a gap is that many lost frames; an id from before is a
late frame of a window that timed out), camera timestamp increasing, Mono16 rows x cols and
exactly rows * cols * 2 bytes. Each fault raises :class:`DeviceError` naming the ids, and is
counted in :attr:`GigEPanel.stats`.

Timing: the GVCP calls (connect, TriggerSoftware, AcquisitionStop) run on one worker thread
and the caller waits at most its timeout: Aravis retries an unanswered GVCP command 5 x 500 ms,
which a camera that is gone would otherwise cost every call. A read waits for the stream in
slices of :data:`POLL_S` and gives up at its timeout; Aravis's ``control-lost`` signal (the
heartbeat found the control privilege gone) fails the read at the next slice. A camera that
dies therefore fails the call in progress, or the next one, within that call's timeout (the
heartbeat itself needs seconds to notice). After a GVCP timeout or control-lost the panel is
gone: every call raises until it is closed and connected again.

Buffers: the stream holds :attr:`GigEPanel.n_buffers` buffers (8 by default). At most two
frames are in flight in the arm -> read cycle (one integrating or in transfer, one received and
not yet read), a read copies its frame out and returns the buffer at once, and a frame that
arrives late is drained at the next arm; the rest is margin for bursts of the hardware trigger.
A frame that finds no free buffer is an underrun in Aravis's statistics and, as it never
arrives, a block id gap here.
"""

from __future__ import annotations

import queue
import threading
import time
import traceback
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import asdict, dataclass
from typing import Any, Literal

import numpy as np

from scanner.hardware import DeviceError, DeviceTimeout, Frame

POLL_S = 0.05
"""The slice a read waits on the stream before it looks for a lost control, s."""
CLOSE_TIMEOUT_S = 0.5
"""How long close waits for AcquisitionStop and for the release of the camera, s (Aravis's own
timeout of one GVCP attempt)."""
MISSING_ARAVIS = (
    "Aravis through GObject introspection is not importable ({error}): install Debian's "
    "gir1.2-aravis-0.8 and python3-gi (apt-get), then `make` links Debian's gi into the venv "
    "(Makefile, the $(STAMP) rule: ln -sfn /usr/lib/python3/dist-packages/gi "
    ".venv/lib/python3.11/site-packages/gi)"
)
TRIGGER_SOURCES = {"software": "Software", "line0": "Line0"}
STREAM_COUNTERS = (
    "n_completed_buffers",
    "n_failures",
    "n_underruns",
    "n_missing_frames",
    "n_missing_packets",
    "n_resent_packets",
)
"""Aravis's GigE Vision stream counters that :meth:`GigEPanel.statistics` reports."""


def _aravis() -> Any:
    """The ``Aravis`` namespace of GObject introspection; raises DeviceError naming what to
    install when it is not there."""
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis
    except (ImportError, ValueError) as exc:
        raise DeviceError("GigE panel: " + MISSING_ARAVIS.format(error=exc)) from exc
    return Aravis


def block_id_step(previous: int, block_id: int) -> int:
    """How many frames ``block_id`` comes after ``previous`` (1: the next one; 0 or less: the
    same or an earlier one). 16-bit GVSP block ids run 1..65535 and wrap to 1."""
    if previous > 0xFFFF or block_id > 0xFFFF:
        return block_id - previous
    step = (block_id - previous) % 0xFFFF
    return step if step < 0x8000 else step - 0xFFFF


def block_id_after(previous: int, n: int) -> int:
    """The block id ``n`` frames after ``previous`` (16-bit ids wrap from 65535 to 1)."""
    return previous + n if previous > 0xFFFF else (previous + n - 1) % 0xFFFF + 1


@dataclass
class GigEStats:
    """What a panel delivered and the faults it saw since connect.

    Attributes:
        frames: frames handed out by read_frame.
        frames_lost: frames that never arrived (block id gaps; includes Aravis's underruns).
        frames_late: frames that arrived after their window's read had timed out.
        frames_incomplete: frames with a status other than SUCCESS (missing packets, timeout).
        timeouts: reads that timed out.
        last_block_id: the block id of the last frame received, or None.
    """

    frames: int = 0
    frames_lost: int = 0
    frames_late: int = 0
    frames_incomplete: int = 0
    timeouts: int = 0
    last_block_id: int | None = None


class _Worker:
    """A daemon thread that makes blocking calls in order, so that the caller can stop
    waiting for one (and the thread can drop the last reference to a dead camera)."""

    def __init__(self, name: str) -> None:
        self._jobs: queue.SimpleQueue = queue.SimpleQueue()
        threading.Thread(target=self._run, name=name, daemon=True).start()

    def _run(self) -> None:
        while (job := self._jobs.get()) is not None:
            fn, future = job
            del job
            try:
                future.set_result(fn())
            except BaseException as exc:  # handed to the caller
                future.set_exception(exc)
            del fn, future

    def submit(self, fn: Callable[[], Any]) -> Future:
        future: Future = Future()
        self._jobs.put((fn, future))
        return future

    def stop(self) -> None:
        self._jobs.put(None)


class GigEPanel:
    """A flat panel on GigE Vision, read through Aravis (see the module docstring).

    Args:
        device: Aravis's device id (e.g. ``"Aravis-Fake-SIM-PANEL-0001"``) or the IPv4 address.
        rows, cols: the panel's read-out size, pixels: must be the camera's whole sensor
            (its Height and Width maxima).
        pixel_pitch_mm: the pixel pitch as read out, mm.
        window_ms: the integration window (ExposureTime), ms.
        trigger: ``"software"`` (arm executes TriggerSoftware) or ``"line0"`` (the generator's
            exposure line opens the window; arm only drains late frames).
        n_buffers: the stream's buffer pool (at least 2 frames in flight, see the module).
        clock: the time base of :attr:`Frame.t_s`, s.
        frame_timeout_s: the longest an arm or a read waits, s, whatever timeout its caller
            gives (None: the caller's): a dead camera is found within it, so set it to a
            few frame periods (more than the window and the frame's transfer).
        warmup_frames: frames triggered and discarded when it connects (software trigger),
            with the connect's timeout: the first frame after the stream starts comes late
            (24-73 ms against 6 on loopback), which a frame timeout of a few frame periods
            would take for a dead camera.

    Attributes:
        serial: the camera's serial number (DeviceSerialNumber, or DeviceID where that is
            missing), after connect.
        mode: the read-out mode, e.g. ``"512x512 Mono16"``.
        stats: frames delivered and faults seen (:class:`GigEStats`).
    """

    def __init__(
        self,
        device: str,
        rows: int,
        cols: int,
        pixel_pitch_mm: float,
        *,
        window_ms: float,
        trigger: Literal["software", "line0"] = "software",
        n_buffers: int = 8,
        clock: Callable[[], float] = time.monotonic,
        frame_timeout_s: float | None = None,
        warmup_frames: int = 0,
    ) -> None:
        if trigger not in TRIGGER_SOURCES:
            raise ValueError(f"trigger must be one of {sorted(TRIGGER_SOURCES)}, got {trigger!r}")
        if n_buffers < 2:
            raise ValueError(f"n_buffers must be at least 2 (frames in flight), got {n_buffers}")
        self.device = device
        self.rows, self.cols, self.pixel_pitch_mm = rows, cols, pixel_pitch_mm
        self.window_ms = window_ms
        self.trigger = trigger
        self.n_buffers = n_buffers
        if frame_timeout_s is not None and frame_timeout_s <= window_ms * 1e-3:
            raise ValueError(
                f"frame_timeout_s {frame_timeout_s} s must exceed the window, {window_ms} ms"
            )
        self.frame_timeout_s = frame_timeout_s
        self.warmup_frames = warmup_frames
        self._clock = clock
        self.serial = ""
        self.mode = f"{cols}x{rows} Mono16"
        self.stats = GigEStats()
        self._aravis: Any = None
        self._camera: Any = None
        self._stream: Any = None
        self._device: Any = None
        self._handler = 0
        self._worker: _Worker | None = None
        self._gone: str | None = None
        self._control_lost = threading.Event()
        self._last_timestamp_ns: int | None = None
        # block ids gone by unseen since the last one seen: software windows whose read timed
        # out, incomplete frames without an id
        self._unanswered = 0

    # --- Detector -------------------------------------------------------------------------

    def connect(self, timeout_s: float) -> None:
        """Open the camera, configure it (Mono16, whole sensor, window, trigger), start the
        stream and the acquisition; raises DeviceError naming the field it refuses."""
        if self._camera is not None:
            return
        self._aravis = _aravis()
        self._worker = _Worker(f"gige-{self.device}")
        self._gone = None
        self._control_lost.clear()
        self.stats = GigEStats()
        self._last_timestamp_ns, self._unanswered = None, 0
        try:
            opened = self._call("connect", self._open, timeout_s)
        except DeviceError:
            self._release()
            raise
        self._camera, self._device, self._stream, self._handler, self.serial = opened
        if self.trigger == "software":
            cap, self.frame_timeout_s = self.frame_timeout_s, None
            try:
                for _ in range(self.warmup_frames):
                    self.arm(timeout_s)
                    self.read_frame(timeout_s)
            finally:
                self.frame_timeout_s = cap

    def arm(self, timeout_s: float) -> None:
        """Open the integration window of the next frame: drain late frames, then (software
        trigger) execute TriggerSoftware; the window lasts ``window_ms``."""
        self._usable("arm")
        timeout_s = self._capped(timeout_s)
        self._drain()
        if self.trigger == "software":
            self._call("TriggerSoftware", self._camera.software_trigger, timeout_s)

    def read_frame(self, timeout_s: float) -> Frame:
        """The window's frame, counts uint16 [row, col]; raises DeviceTimeout when none
        arrives within ``timeout_s``, DeviceError when it is lost, late or incomplete."""
        self._usable("read_frame")
        timeout_s = self._capped(timeout_s)
        deadline = time.monotonic() + timeout_s
        while (buffer := self._stream.timeout_pop_buffer(self._slice_us(deadline))) is None:
            if self._control_lost.is_set():
                raise DeviceError(f"{self._name()}: read_frame: control lost ({self._gone})")
            if time.monotonic() >= deadline:
                self.stats.timeouts += 1
                self._unanswered += self.trigger == "software"
                raise DeviceTimeout(
                    f"{self._name()}: read_frame: no frame within {timeout_s} s (last block id "
                    f"{self.stats.last_block_id}; camera gone, or no trigger)"
                )
        try:
            counts = self._checked(buffer)
        finally:
            self._stream.push_buffer(buffer)
        self.stats.frames += 1
        return Frame(counts, self._clock())

    def close(self) -> None:
        """Stop the acquisition and release the camera; safe to call twice. With the camera
        gone it does not wait for it (Aravis's release retries in the worker thread)."""
        if self._camera is not None and self._gone is None:
            try:
                self._call("AcquisitionStop", self._camera.stop_acquisition, CLOSE_TIMEOUT_S)
            except DeviceError:
                pass
        self._release()

    # --- statistics -----------------------------------------------------------------------

    @property
    def frames_lost(self) -> int:
        """Frames that never arrived since connect."""
        return self.stats.frames_lost

    def statistics(self) -> dict[str, int | None]:
        """:attr:`stats` and Aravis's stream counters (:data:`STREAM_COUNTERS`, as
        ``stream_*``), for the bench and the event log."""
        out: dict[str, int | None] = asdict(self.stats)
        if self._stream is not None:
            for name in STREAM_COUNTERS:
                out[f"stream_{name[2:]}"] = self._stream.get_info_uint64_by_name(name)
        return out

    # --- the camera -----------------------------------------------------------------------

    def _open(self) -> tuple[Any, Any, Any, int, str]:
        """Open and configure the camera (runs on the worker); a refusal releases it here."""
        camera = self._aravis.Camera.new(self.device)
        try:
            return self._configure(camera)
        except BaseException as exc:
            camera = None  # the traceback keeps the frames: release the camera now
            traceback.clear_frames(exc.__traceback__)
            raise

    def _configure(self, camera: Any) -> tuple[Any, Any, Any, int, str]:
        aravis, rows, cols = self._aravis, self.rows, self.cols
        self.serial = camera.get_device_serial_number()
        if not camera.is_gv_device():
            raise DeviceError(f"{self._name()}: not a GigE Vision device")
        device = camera.get_device()
        if not device.is_controller():
            raise DeviceError(f"{self._name()}: another host controls the camera")
        formats = camera.dup_available_pixel_formats_as_strings()
        if "Mono16" not in formats:
            raise DeviceError(
                f"{self._name()}: PixelFormat: no Mono16; the camera offers {', '.join(formats)}"
            )
        camera.set_pixel_format_from_string("Mono16")
        if camera.is_region_offset_available():  # the maxima may shrink with the offsets
            camera.set_integer("OffsetX", 0)
            camera.set_integer("OffsetY", 0)
        for field, want, (_, most), unit in (
            ("Width", cols, camera.get_width_bounds(), "columns"),
            ("Height", rows, camera.get_height_bounds(), "rows"),
        ):
            if most != want:
                raise DeviceError(
                    f"{self._name()}: {field}: the camera reads out {most} {unit} (its {field} "
                    f"maximum), the panel is configured with {want}"
                )
        camera.set_region(0, 0, cols, rows)
        region = tuple(camera.get_region())
        if region != (0, 0, cols, rows):
            raise DeviceError(f"{self._name()}: region (x, y, Width, Height) reads {region}")
        window_us = self.window_ms * 1e3
        low, high = camera.get_exposure_time_bounds()
        if not low <= window_us <= high:
            raise DeviceError(
                f"{self._name()}: ExposureTime: window {self.window_ms} ms outside the camera's "
                f"{low / 1e3:g}..{high / 1e3:g} ms"
            )
        camera.set_exposure_time(window_us)
        if abs(camera.get_exposure_time() - window_us) > max(1.0, 1e-3 * window_us):
            raise DeviceError(
                f"{self._name()}: ExposureTime: set {window_us:g} µs, reads "
                f"{camera.get_exposure_time():g} µs"
            )
        source = TRIGGER_SOURCES[self.trigger]
        sources = camera.dup_available_trigger_sources()
        if source not in sources:
            raise DeviceError(
                f"{self._name()}: TriggerSource: no {source}; the camera offers "
                f"{', '.join(sources)}"
            )
        camera.set_trigger(source)
        if camera.get_trigger_source() != source:
            raise DeviceError(f"{self._name()}: TriggerSource reads {camera.get_trigger_source()}")
        camera.set_acquisition_mode(aravis.AcquisitionMode.CONTINUOUS)
        payload = camera.get_payload()
        if payload != rows * cols * 2:
            raise DeviceError(
                f"{self._name()}: PayloadSize: {payload} bytes, Mono16 {cols}x{rows} is "
                f"{rows * cols * 2}"
            )
        stream = camera.create_stream(None, None)
        for _ in range(self.n_buffers):
            stream.push_buffer(aravis.Buffer.new_allocate(payload))
        handler = device.connect("control-lost", self._on_control_lost)
        camera.start_acquisition()
        return camera, device, stream, handler, self.serial

    def _on_control_lost(self, _device: Any) -> None:
        """Aravis's heartbeat found the control privilege gone (its thread calls this)."""
        self._gone = "Aravis's heartbeat lost the control of the camera"
        self._control_lost.set()

    def _checked(self, buffer: Any) -> np.ndarray:
        """The buffer's counts, after the checks of the module docstring."""
        aravis, name = self._aravis, self._name()
        block_id, timestamp_ns = buffer.get_frame_id(), buffer.get_timestamp()
        status = buffer.get_status()
        if status != aravis.BufferStatus.SUCCESS:
            self.stats.frames_incomplete += 1
            if block_id:
                self.stats.last_block_id, self._unanswered = block_id, 0
            else:  # its leader was lost: one block id went by unseen
                self._unanswered += 1
            raise DeviceError(f"{name}: frame {block_id} incomplete: status {status.value_nick}")
        previous, self.stats.last_block_id = self.stats.last_block_id, block_id
        if previous is not None:
            step, expected = block_id_step(previous, block_id), 1 + self._unanswered
            if step < expected:
                self.stats.frames_late += 1
                self._unanswered = max(expected - max(step, 0) - 1, 0)
                raise DeviceError(
                    f"{name}: late frame: block id {block_id} after {previous} belongs to a "
                    f"window whose read timed out"
                )
            self._unanswered = 0
            if step > expected:
                self.stats.frames_lost += step - expected
                raise DeviceError(
                    f"{name}: {step - expected} frame(s) lost: block id {block_id} follows "
                    f"{previous}, expected {block_id_after(previous, expected)}"
                )
        last_ns, self._last_timestamp_ns = self._last_timestamp_ns, timestamp_ns
        if last_ns is not None and timestamp_ns <= last_ns:
            raise DeviceError(
                f"{name}: frame {block_id}: timestamp {timestamp_ns} ns not after {last_ns} ns"
            )
        shape = (buffer.get_image_height(), buffer.get_image_width())
        pixel_format = buffer.get_image_pixel_format()
        data = buffer.get_image_data()
        size = 0 if data is None else len(data)
        if (
            shape != (self.rows, self.cols)
            or pixel_format != aravis.PIXEL_FORMAT_MONO_16
            or size != self.rows * self.cols * 2
        ):
            raise DeviceError(
                f"{name}: frame {block_id}: {shape[1]}x{shape[0]} pixel format "
                f"{pixel_format:#010x}, {size} bytes; expected {self.mode}, "
                f"{self.rows * self.cols * 2} bytes"
            )
        return np.frombuffer(data, dtype="<u2").reshape(self.rows, self.cols).astype(np.uint16)

    def _drain(self) -> None:
        """Take the frames that arrived outside a read (late ones) off the stream."""
        while (buffer := self._stream.try_pop_buffer()) is not None:
            self.stats.frames_late += 1
            self._unanswered = max(self._unanswered - 1, 0)
            self.stats.last_block_id = buffer.get_frame_id()
            self._last_timestamp_ns = buffer.get_timestamp()
            self._stream.push_buffer(buffer)

    # --- plumbing -------------------------------------------------------------------------

    def _name(self) -> str:
        return f"GigE panel {self.serial or self.device}"

    def _capped(self, timeout_s: float) -> float:
        """The caller's timeout, capped at :attr:`frame_timeout_s`."""
        cap = self.frame_timeout_s
        return timeout_s if cap is None else min(timeout_s, cap)

    def _usable(self, call: str) -> None:
        if self._camera is None:
            raise DeviceError(f"{self._name()}: {call}: not connected")
        if self._gone is not None:
            raise DeviceError(f"{self._name()}: {call}: the camera is gone ({self._gone})")

    @staticmethod
    def _slice_us(deadline: float) -> int:
        return int(min(max(deadline - time.monotonic(), 0.0), POLL_S) * 1e6)

    def _call(self, what: str, fn: Callable[[], Any], timeout_s: float) -> Any:
        """``fn()`` on the worker, waiting at most ``timeout_s``; Aravis's errors become
        DeviceError, no answer in time DeviceTimeout (and the camera is gone)."""
        assert self._worker is not None
        future = self._worker.submit(fn)
        try:
            return future.result(timeout_s)
        except TimeoutError:
            self._gone = f"{what} unanswered within {timeout_s} s"
            raise DeviceTimeout(f"{self._name()}: {what}: no answer within {timeout_s} s") from None
        except DeviceError:
            raise
        except Exception as exc:  # GLib.Error from Aravis
            raise DeviceError(f"{self._name()}: {what}: {getattr(exc, 'message', exc)}") from exc

    def _release(self) -> None:
        """Drop the camera on the worker (a dead camera's release retries GVCP for seconds)."""
        objects = [self._camera, self._device, self._stream]
        if self._device is not None and self._handler:
            self._device.disconnect(self._handler)
        self._camera = self._device = self._stream = None
        self._handler = 0
        worker, self._worker = self._worker, None
        if worker is None:
            return
        released = worker.submit(objects.clear)
        del objects
        worker.stop()
        if self._gone is None:
            try:
                released.result(CLOSE_TIMEOUT_S)
            except TimeoutError:
                pass
