"""A fake GigE Vision flat panel that serves our own images: Aravis's fake camera on the wire,
each frame's pixels from a "sensor" over a unix-domain socket.

The panel is a process of its own (``python -m sim.gige_panel --interface 127.0.0.2 --serial
SIM-PANEL-0001 --rows 512 --cols 512 --feed /path/to/unix.sock``): an ``Aravis.GvFakeCamera``
(GVCP control, GenICam, GVSP streaming, heartbeat: the real protocol stack) whose fill pattern,
at each trigger, sends the sensor a request carrying the integration window and copies the
rows x cols uint16 frame it answers into the outgoing buffer. The sensor is
:func:`serve_sensor` in the parent process; :func:`start_fake_panel` starts the panel and waits
until it answers on GVCP.

The fill pattern is installed through ctypes, not GObject introspection: the introspection data
of ``arv_fake_camera_set_fill_pattern`` declares the callback ``scope call``, so PyGObject frees
its closure when the call returns and the camera thread later calls freed memory. ctypes hands
over a C function pointer we keep alive, and its ``ArvBuffer *`` argument goes straight to
``arv_buffer_get_data``, whose memory is the buffer the camera thread then sends
(``Buffer.get_data`` through introspection returns a copy).

Aravis's fake camera binds its GVCP port (UDP 3956) to an interface's own address, so one panel
per address, and the address must be on an interface (127.0.0.1 is; 127.0.0.2 needs
``ip addr add 127.0.0.2/32 dev lo``). In software-trigger mode the fake checks for a trigger
every millisecond (its trigger frequency, set to 1 kHz here); with a ``Line0`` trigger it
never sends a frame (Aravis's fake has no trigger line). One thread of the fake answers GVCP
and sends frames, so a sensor that takes long to answer delays the control answers as much.
Without a sensor (no ``--feed``, or it does not answer) each frame is :func:`test_pattern`. The
panel process ends with the thread that started it (PR_SET_PDEATHSIG).

Sensor protocol (little-endian): request ``<QIId`` (block id, rows, cols, window in s); answer
``<Q`` byte count, then that many bytes: the frame, rows x cols uint16 [row, col] (a count of 0:
the sensor failed; the panel sends the test pattern).
"""

from __future__ import annotations

import argparse
import ctypes
import errno
import os
import re
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

GVCP_PORT = 3956
REQUEST = struct.Struct("<QIId")
"""Panel -> sensor: block id, rows, cols, integration window (s)."""
ANSWER = struct.Struct("<Q")
"""Sensor -> panel: the frame's byte count (0: no frame), then the frame."""
TRIGGER_POLL_HZ = 1000.0
"""The fake camera's trigger frequency: how often it checks for a software trigger, Hz."""
SENSOR_TIMEOUT_S = 10.0
"""How long the panel waits for the sensor's answer beyond the window, s."""


class FakePanelError(RuntimeError):
    """The fake panel could not be started (the message says why, and what to do)."""


class FakePanelAddressError(FakePanelError):
    """The panel's address is on no interface (Aravis's fake camera cannot serve on it)."""


NO_ADDRESS_EXIT = 3
"""The panel process's exit status when its address is on no interface."""


def aravis_missing() -> str | None:
    """Why the fake panel cannot run here (Aravis through GObject introspection, or its C
    library, is not importable), or None when it can."""
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis  # noqa: F401

        ctypes.CDLL("libaravis-0.8.so.0")
    except (ImportError, ValueError, OSError) as exc:
        return (
            f"Aravis through GObject introspection is not importable ({exc}): install "
            "gir1.2-aravis-0.8 python3-gi aravis-tools; `make` links Debian's gi into the venv"
        )
    return None


def test_pattern(rows: int, cols: int, block_id: int) -> np.ndarray:
    """The frame the panel sends without a sensor: a ramp shifted by the block id, uint16."""
    r, c = np.ogrid[:rows, :cols]
    return ((7 * r + 3 * c + block_id) % 4096).astype(np.uint16)


def _recv_exact(sock: socket.socket, n: int) -> bytes:
    """Exactly ``n`` bytes from ``sock``; raises ConnectionError when it closes first."""
    chunks, got = [], 0
    while got < n:
        chunk = sock.recv(min(n - got, 1 << 20))
        if not chunk:
            raise ConnectionError(f"closed after {got} of {n} bytes")
        chunks.append(chunk)
        got += len(chunk)
    return b"".join(chunks)


class SensorServer:
    """Answers the fake panel's frame requests with ``integrate(window_s)``, in a thread.

    Attributes:
        path: the unix-domain socket it listens on.
        requests: requests answered so far.
        errors: what went wrong with a request (the panel then sent its test pattern).
    """

    def __init__(self, integrate: Callable[[float], np.ndarray], path: str | Path) -> None:
        self.path = Path(path)
        self._integrate = integrate
        self.requests = 0
        self.errors: list[str] = []
        self.path.unlink(missing_ok=True)
        self._listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self._listener.bind(str(self.path))
        self._listener.listen(1)
        self._closing = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="gige-sensor", daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while not self._closing.is_set():
            try:
                conn, _ = self._listener.accept()
            except OSError:
                return
            with conn:
                self._answer(conn)

    def _answer(self, conn: socket.socket) -> None:
        while not self._closing.is_set():
            try:
                block_id, rows, cols, window_s = REQUEST.unpack(_recv_exact(conn, REQUEST.size))
            except (ConnectionError, OSError):
                return
            try:
                frame = np.asarray(self._integrate(window_s))
                if frame.shape != (rows, cols) or frame.dtype != np.uint16:
                    raise ValueError(
                        f"integrate gave {frame.dtype} {frame.shape}, the panel reads out "
                        f"uint16 ({rows}, {cols})"
                    )
                data = np.ascontiguousarray(frame, dtype="<u2").tobytes()
            except Exception as exc:  # reported to the caller through .errors
                self.errors.append(f"block {block_id}: {exc!r}")
                data = b""
            self.requests += 1
            try:
                conn.sendall(ANSWER.pack(len(data)) + data)
            except OSError:
                return

    def close(self) -> None:
        """Stop answering and remove the socket; safe to call twice."""
        if self._closing.is_set():
            return
        self._closing.set()
        try:
            self._listener.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self._listener.close()
        self._thread.join(timeout=SENSOR_TIMEOUT_S)
        self.path.unlink(missing_ok=True)

    def __enter__(self) -> SensorServer:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()


def serve_sensor(integrate: Callable[[float], np.ndarray], path: str | Path) -> SensorServer:
    """The sensor of a fake panel: a thread answering each request with ``integrate(window_s)``
    (a rows x cols uint16 array, the counts integrated over the window of ``window_s`` s that
    opened when the request was sent). Start it before the panel, which connects to ``path``."""
    return SensorServer(integrate, path)


def gvcp_discover(address: str, timeout_s: float = 0.2) -> str | None:
    """The serial number of the GigE Vision device answering a unicast GVCP discovery at
    ``address``, or None when none answers within ``timeout_s``."""
    request_id = 1
    # GVCP command header: key 0x42, flags (ack required), DISCOVERY_CMD, length 0, request id
    command = struct.pack(">BBHHH", 0x42, 0x01, 0x0002, 0, request_id)
    deadline = time.monotonic() + timeout_s
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.connect((address, GVCP_PORT))  # the kernel drops datagrams from anyone else
        sock.send(command)
        while (left := deadline - time.monotonic()) > 0:
            sock.settimeout(left)
            try:
                ack = sock.recv(1024)
            except (TimeoutError, ConnectionRefusedError):
                return None
            # ack header: status, answer (DISCOVERY_ACK), length, request id; then the
            # bootstrap registers 0x0000..0x00f7, the serial at 0x00d8
            if len(ack) >= 8 + 0xE8 and struct.unpack(">2xH2xH", ack[:8]) == (0x0003, request_id):
                serial = ack[8 + 0xD8 : 8 + 0xD8 + 16]
                return serial.split(b"\0", 1)[0].decode("ascii", "replace")
    return None


class FakePanel:
    """A running fake panel process (from :func:`start_fake_panel`).

    Attributes:
        interface, serial, rows, cols: as started.
        process: the panel's process.
        killed_at: ``time.monotonic()`` just before :meth:`kill` signalled it, or None.
    """

    def __init__(
        self, process: subprocess.Popen, interface: str, serial: str, rows: int, cols: int
    ) -> None:
        self.process = process
        self.interface, self.serial, self.rows, self.cols = interface, serial, rows, cols
        self.killed_at: float | None = None

    @property
    def device_id(self) -> str:
        """Aravis's device id of the panel (its vendor and model are "Aravis" and "Fake")."""
        return f"Aravis-Fake-{self.serial}"

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop the panel (SIGTERM, then SIGKILL after ``timeout_s``); safe to call twice."""
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()

    def kill(self) -> float:
        """The camera-gone fault: SIGKILL now, no goodbye on the wire; returns the
        ``time.monotonic()`` of the signal."""
        self.killed_at = time.monotonic()
        self.process.kill()
        self.process.wait()
        return self.killed_at

    def __enter__(self) -> FakePanel:
        return self

    def __exit__(self, *_: object) -> None:
        self.stop()


def start_fake_panel(
    interface: str,
    serial: str,
    rows: int,
    cols: int,
    feed_path: str | Path | None = None,
    *,
    pixel_formats: Sequence[str] | None = None,
    skip_block_id_after: int | None = None,
    gvsp_lost_ratio: float = 0.0,
    timeout_s: float = 10.0,
) -> FakePanel:
    """Start a fake panel process and return once it answers GVCP discovery at ``interface``.

    Args:
        interface: the IPv4 address it serves on (an interface's own address, free of cameras).
        serial: its serial number (at most 15 characters).
        rows, cols: its sensor's size (SensorHeight/SensorWidth, the Height/Width maxima).
        feed_path: the sensor's socket (:func:`serve_sensor`); None: the test pattern.
        pixel_formats: the PixelFormat entries it offers (the first is selected); None: all of
            Aravis's fake camera's, with Mono16 selected.
        skip_block_id_after: after this many frames, skip one block id (a lost frame as the
            host sees it); None: never.
        gvsp_lost_ratio: the fraction of stream packets it drops (Aravis's fake does not
            resend them).
        timeout_s: how long to wait for it, s.

    Raises:
        FakePanelError: a camera already answers at ``interface``, or the panel exited or did
            not answer in time (the message carries its stderr).
    """
    found = gvcp_discover(interface)
    if found is not None:
        raise FakePanelError(f"a GigE Vision device ({found}) already answers at {interface}")
    args = [sys.executable, "-m", "sim.gige_panel", "--interface", interface, "--serial", serial]
    args += ["--parent-pid", str(os.getpid())]
    args += ["--rows", str(rows), "--cols", str(cols), "--gvsp-lost-ratio", str(gvsp_lost_ratio)]
    if feed_path is not None:
        args += ["--feed", str(feed_path)]
    if pixel_formats is not None:
        args += ["--pixel-formats", ",".join(pixel_formats)]
    if skip_block_id_after is not None:
        args += ["--skip-block-id-after", str(skip_block_id_after)]
    stderr = tempfile.TemporaryFile()
    root = Path(__file__).resolve().parent.parent
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join(filter(None, [str(root), os.environ.get("PYTHONPATH")])),
    }
    process = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=stderr, env=env)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if process.poll() is not None:
            break
        if gvcp_discover(interface, 0.05) == serial:
            return FakePanel(process, interface, serial, rows, cols)
        time.sleep(0.02)
    if process.poll() is None:
        process.kill()
        process.wait()
        reason = f"did not answer GVCP within {timeout_s} s"
    else:
        reason = f"exited with {process.returncode}"
    stderr.seek(0)
    error = FakePanelAddressError if process.returncode == NO_ADDRESS_EXIT else FakePanelError
    raise error(
        f"fake panel {serial} at {interface} {reason}: "
        f"{stderr.read().decode(errors='replace').strip()}"
    )


@contextmanager
def fake_panel_with_sensor(
    interface: str,
    serial: str,
    rows: int,
    cols: int,
    integrate: Callable[[float], np.ndarray],
    **options: Any,
) -> Iterator[tuple[FakePanel, SensorServer]]:
    """A fake panel fed by ``integrate`` (:func:`serve_sensor` on a socket in a temporary
    folder, then :func:`start_fake_panel` with ``options``); both stopped on exit."""
    with tempfile.TemporaryDirectory(prefix="gige-") as folder:
        path = Path(folder) / "sensor.sock"
        with (
            serve_sensor(integrate, path) as sensor,
            start_fake_panel(interface, serial, rows, cols, path, **options) as panel,
        ):
            yield panel, sensor


# --- the panel process ---------------------------------------------------------------------

_FILL = ctypes.CFUNCTYPE(None, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_uint32,
                         ctypes.c_uint32, ctypes.c_uint32)  # fmt: skip
"""ArvFakeCameraFillPattern: (ArvBuffer *, user data, exposure µs, gain, pixel format)."""


def _libaravis() -> ctypes.CDLL:
    lib = ctypes.CDLL("libaravis-0.8.so.0")
    lib.arv_buffer_get_data.restype = ctypes.c_void_p
    lib.arv_buffer_get_data.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_size_t)]
    for name in ("arv_buffer_get_image_width", "arv_buffer_get_image_height"):
        getattr(lib, name).restype = ctypes.c_int
        getattr(lib, name).argtypes = [ctypes.c_void_p]
    lib.arv_buffer_get_frame_id.restype = ctypes.c_uint64
    lib.arv_buffer_get_frame_id.argtypes = [ctypes.c_void_p]
    lib.arv_buffer_set_frame_id.argtypes = [ctypes.c_void_p, ctypes.c_uint64]
    # 0.8 takes (camera, callback, data), 0.9 adds a destroy notifier: a NULL fourth argument
    # suits both
    lib.arv_fake_camera_set_fill_pattern.argtypes = [
        ctypes.c_void_p, _FILL, ctypes.c_void_p, ctypes.c_void_p
    ]  # fmt: skip
    return lib


def _gpointer(obj: object) -> int:
    """The C pointer of a PyGObject wrapper (its ``__gpointer__`` capsule)."""
    get = ctypes.pythonapi.PyCapsule_GetPointer
    get.restype, get.argtypes = ctypes.c_void_p, [ctypes.py_object, ctypes.c_char_p]
    return get(obj.__gpointer__, None)


class _Feed:
    """The panel's side of the sensor socket: one request per frame, reconnecting when lost."""

    def __init__(self, path: str | None) -> None:
        self.path = path
        self._sock: socket.socket | None = None

    def frame(self, block_id: int, rows: int, cols: int, window_s: float) -> bytes | None:
        """The sensor's frame for this window, or None (no sensor, or it failed)."""
        if self.path is None:
            return None
        try:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
                self._sock.settimeout(window_s + SENSOR_TIMEOUT_S)
                self._sock.connect(self.path)
            self._sock.sendall(REQUEST.pack(block_id, rows, cols, window_s))
            (n,) = ANSWER.unpack(_recv_exact(self._sock, ANSWER.size))
            data = _recv_exact(self._sock, n)
        except OSError as exc:
            if self._sock is not None:
                self._sock.close()
                self._sock = None
            if not (isinstance(exc, FileNotFoundError | ConnectionRefusedError)):
                print(f"gige_panel: sensor at {self.path}: {exc!r}", file=sys.stderr, flush=True)
            return None
        return data if len(data) == rows * cols * 2 else None


def _genicam_offering(xml: str, pixel_formats: Sequence[str]) -> tuple[str, int]:
    """The fake camera's GenICam XML with only ``pixel_formats`` in its PixelFormat
    enumeration, and the first one's value."""
    enum = re.search(r'<Enumeration Name="PixelFormat".*?</Enumeration>', xml, re.S)
    if enum is None:
        raise FakePanelError("the fake camera's GenICam has no PixelFormat enumeration")
    entries = dict(
        (m.group(1), (m.group(0), int(m.group(2), 0)))
        for m in re.finditer(r'<EnumEntry Name="(\w+)".*?<Value>(\w+)</Value>\s*</EnumEntry>',
                             enum.group(0), re.S)
    )  # fmt: skip
    unknown = [f for f in pixel_formats if f not in entries]
    if unknown or not pixel_formats:
        raise FakePanelError(f"pixel formats {unknown} unknown; the fake offers {list(entries)}")
    body = enum.group(0)
    for name, (text, _) in entries.items():
        if name not in pixel_formats:
            body = body.replace(text, "")
    return xml.replace(enum.group(0), body), entries[pixel_formats[0]][1]


def _run_panel(args: argparse.Namespace) -> int:
    """The panel process: serve until SIGTERM/SIGINT."""
    import gi

    gi.require_version("Aravis", "0.8")
    from gi.repository import Aravis

    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM, signal.SIGINT})
    # go with the process that started us (PR_SET_PDEATHSIG: SIGTERM when its thread exits)
    ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM, 0, 0, 0)
    if os.getppid() != args.parent_pid:
        return 0
    if len(args.serial) > 15:
        raise SystemExit(f"serial {args.serial!r}: at most 15 characters (GVBS field)")
    xml, _ = Aravis.FakeCamera.new("probe").get_genicam_xml()
    genicam = None
    if args.pixel_formats:
        xml, pixel_format = _genicam_offering(xml, args.pixel_formats.split(","))
        genicam = tempfile.NamedTemporaryFile("w", suffix=".xml", prefix="gige-panel-")
        genicam.write(xml)
        genicam.flush()
    else:
        pixel_format = Aravis.PIXEL_FORMAT_MONO_16
    gv = Aravis.GvFakeCamera(
        interface_name=args.interface,
        serial_number=args.serial,
        genicam_filename=genicam and genicam.name,
        gvsp_lost_ratio=args.gvsp_lost_ratio,
    )
    if not gv.is_running():
        print(
            f"Aravis's fake camera did not start on {args.interface}: it binds to an "
            f"interface's own address (add it, e.g. `ip addr add {args.interface}/32 dev lo`)",
            file=sys.stderr,
        )
        return NO_ADDRESS_EXIT
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:  # the fake's GVCP socket holds the port, or it failed to bind it
        probe.bind((args.interface, GVCP_PORT))
        raise SystemExit(f"Aravis's fake camera could not bind {args.interface}:{GVCP_PORT}")
    except OSError as exc:
        if exc.errno != errno.EADDRINUSE:
            raise
    finally:
        probe.close()

    camera = gv.get_fake_camera()
    for register, value in (
        (Aravis.FAKE_CAMERA_REGISTER_SENSOR_WIDTH, args.cols),
        (Aravis.FAKE_CAMERA_REGISTER_SENSOR_HEIGHT, args.rows),
        (Aravis.FAKE_CAMERA_REGISTER_WIDTH, args.cols),
        (Aravis.FAKE_CAMERA_REGISTER_HEIGHT, args.rows),
        (Aravis.FAKE_CAMERA_REGISTER_PIXEL_FORMAT, pixel_format),
    ):
        camera.write_register(register, value)
    camera.set_trigger_frequency(TRIGGER_POLL_HZ)

    lib = _libaravis()
    feed = _Feed(args.feed)
    sent = [0]

    def fill(buffer: int, _data: int, exposure_us: int, _gain: int, pixel_format: int) -> None:
        block_id = lib.arv_buffer_get_frame_id(buffer)
        if args.skip_block_id_after is not None and sent[0] >= args.skip_block_id_after:
            block_id = block_id % 0xFFFF + 1  # 16-bit block ids run 1..65535
            lib.arv_buffer_set_frame_id(buffer, block_id)
        sent[0] += 1
        if pixel_format != Aravis.PIXEL_FORMAT_MONO_16:
            return
        cols = lib.arv_buffer_get_image_width(buffer)
        rows = lib.arv_buffer_get_image_height(buffer)
        data = feed.frame(block_id, rows, cols, exposure_us * 1e-6)
        if data is None:
            data = test_pattern(rows, cols, block_id).tobytes()
        size = ctypes.c_size_t()
        ctypes.memmove(lib.arv_buffer_get_data(buffer, ctypes.byref(size)), data, len(data))

    callback = _FILL(fill)  # kept alive until the fill pattern is reset
    lib.arv_fake_camera_set_fill_pattern(_gpointer(camera), callback, None, None)
    signal.sigwait({signal.SIGTERM, signal.SIGINT})
    # back to Aravis's own pattern (this waits for a fill in progress), then go
    lib.arv_fake_camera_set_fill_pattern(_gpointer(camera), _FILL(), None, None)
    if genicam is not None:
        genicam.close()  # os._exit skips the finalisers that would delete it
    os._exit(0)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--interface", default="127.0.0.1", help="IPv4 address to serve on")
    parser.add_argument("--serial", default="SIM-PANEL-0001", help="serial number")
    parser.add_argument("--rows", type=int, default=512, help="sensor rows (Height maximum)")
    parser.add_argument("--cols", type=int, default=512, help="sensor columns (Width maximum)")
    parser.add_argument("--feed", help="the sensor's unix socket (default: test pattern)")
    parser.add_argument("--pixel-formats", help="offer only these, comma-separated")
    parser.add_argument("--skip-block-id-after", type=int, help="frames before a lost one")
    parser.add_argument("--gvsp-lost-ratio", type=float, default=0.0, help="packets dropped")
    parser.add_argument("--parent-pid", type=int, default=os.getppid(), help=argparse.SUPPRESS)
    return _run_panel(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
