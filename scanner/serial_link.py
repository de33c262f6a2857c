"""The serial command set of the X-ray generator and the lift/rotary stage, and its link.

This docstring is the protocol's specification; ``scanner.generator`` and ``scanner.stage`` are
its host drivers, ``sim.generator`` and ``sim.stage`` independent mock devices over a pty.

Framing
-------
Every message, in both directions, is one line of printable ASCII (at most 256 bytes)::

    <body>*<XX>\\r\\n

``XX`` is the checksum of ``<body>``: the sum of its bytes modulo 256 as two upper-case hex
digits (``ID?*CC``, ``KV 110.0*B1``). ``<body>`` is words separated by single spaces, numbers in
plain decimal (``110``, ``12.5``, ``-3.25``). A device answers a request whose checksum is wrong
with ``ERR <CMD> CHECKSUM ...`` (``?`` for an unreadable command word) and does nothing.

Request and reply
-----------------
The host sends one request and waits, up to that request's timeout, for exactly one reply::

    OK <CMD> [<value> ...]
    ERR <CMD> <CODE> <message>

``<CMD>`` repeats the request's command word (``OK STATUS? ...``). The host raises
``DeviceTimeout`` when no complete line arrives in time, and ``DeviceError`` for a bad checksum,
a line that is neither ``OK`` nor ``ERR``, or a reply naming another command; every message names
the device, the request and what came back. Unread input is discarded before each request (the
late reply of a timed-out request). Devices answer in the order of the requests.

``ABORT`` is the exception: the host may send it while another request is outstanding (it
is written at once, not queued behind the other request) and takes the ``OK ABORT`` whenever
it comes, skipping other replies; it is idempotent, so a lost confirmation is fixed by resending.

Error codes: ``SYNTAX`` (wrong arguments), ``CHECKSUM``, ``UNKNOWN`` (command), ``RANGE`` (value
outside the device's limit; the message names value and limit, e.g. ``ERR KV RANGE kV 160
above limit 150``), ``NOTECH`` (no technique set), ``NOTREADY``, ``INTERLOCK`` (the message names
the open interlock), ``FAULT`` (latched fault), ``BUSY`` (a pulse is running), ``ABORTED``,
``PSTOP`` (protective stop).

Generator
---------
``ID?`` -> ``OK ID? <model> <version>``
    Identification.
``KV <kvp>`` -> ``OK KV <kvp>``; ``MA <ma>`` -> ``OK MA <ma>``; ``MS <ms>`` -> ``OK MS <ms>``
    Tube voltage (kVp), tube current (mA), pulse width (ms); ``RANGE`` outside the generator's
    limits. Changing the technique keeps READY.
``PREP`` -> ``OK PREP <warmup_s>``
    Start the warm-up; answered at once with the seconds left; ``STATUS?`` shows ``READY=1``
    once warm (``NOTECH``, ``FAULT``).
``EXP`` -> ``OK EXP <kv> <ma> <ms> <seq>``
    Fire one pulse; answered after the pulse with the technique delivered and its sequence
    number (pulses since power-up). Refused, nothing fired: ``NOTREADY``, ``INTERLOCK``,
    ``NOTECH``, ``FAULT``, ``BUSY``. Cut short by ``ABORT`` or an opening interlock:
    ``ERR EXP ABORTED ...`` (not counted).
``ABORT`` -> ``OK ABORT``
    X-ray off now. Always honoured, in any state, also during a pulse (whose ``EXP`` is
    answered first); answered once the tube is off; drops READY (``PREP`` again before ``EXP``).
``STATUS?`` -> ``OK STATUS? <KEY>=<value> ...``
    In this order: ``READY=<0|1> XRAY=<0|1> KV=<kvp> MA=<ma> MS=<ms> ESTOP=<0|1> DOOR=<0|1>
    DEADMAN=<0|1> EXPOSURES=<n> FAULT=<code>``; ``-`` for a value not set (technique, fault);
    interlocks 1 = closed (safe), 0 = open.

While a pulse runs only ``ABORT``, ``STATUS?`` and ``ID?`` are served (others: ``BUSY``).

Stage (lift + rotary)
---------------------
``ID?`` -> ``OK ID? <model> <version>``
    Identification.
``POS?`` -> ``OK POS? <rot_deg> <lift_mm> <t_s> <pstop> <moving>``
    Measured position; ``t_s`` on the controller's clock, s; ``pstop`` (protective stop) and
    ``moving`` are 0/1.
``MOVE <rot_deg> <lift_mm>`` -> ``OK MOVE <duration_s>``
    Point-to-point move, answered at once with its planned duration from rest, s. Each axis
    follows an acceleration-limited (trapezoidal) velocity profile within the speed and
    acceleration limits; the host polls ``POS?`` until ``moving`` is 0 (``RANGE`` outside the
    travel, ``PSTOP``).
``SERVO <rot_deg> <lift_mm> <dt_s>`` -> ``OK SERVO``
    Streamed set-point, to be reached ``dt_s`` from now (0 < dt_s <= 1 s); answered at once
    (``RANGE``, ``PSTOP``).
``STOP`` -> ``OK STOP``
    Decelerate to standstill at the acceleration limits; ends MOVE and SERVO; answered at once.

A protective stop halts the stage, sets ``pstop`` and refuses ``MOVE`` and ``SERVO`` with
``PSTOP`` until it is cleared at the controller (there is no host command for it).

Other framings
--------------
:class:`SerialLink` takes the framing as an object (:class:`Framing`: the text of a request,
its bytes, where a received frame ends, its :class:`Reply`); :class:`LineFraming`, the framing
above, is the default. ``scanner.spellman`` gives it Spellman's ``<STX>CMD,ARG,...,<CSUM><ETX>``
frames; request, reply, timeout, the urgent command and the error messages are the same.
"""

from __future__ import annotations

import io
import os
import select
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import serial

from scanner.hardware import DeviceError, DeviceTimeout

DEFAULT_BAUDRATE = 115200
"""Baud rate of both devices (irrelevant on a pty)."""

MAX_LINE_BYTES = 256
"""Longest line either side sends, terminator included."""

_READ_SLICE_S = 0.01  # serial read timeout: how often a waiting read checks its deadline
_HEX = frozenset(b"0123456789ABCDEFabcdef")


class FrameError(ValueError):
    """A received line is not a valid frame (checksum, characters, shape)."""


def checksum(body: bytes) -> int:
    """The frame checksum: the sum of the bytes of ``body`` modulo 256."""
    return sum(body) & 0xFF


def encode_frame(body: str) -> bytes:
    """``body`` as one frame: ``<body>*XX\\r\\n``."""
    raw = body.encode("ascii")
    if any(c < 0x20 or c > 0x7E for c in raw) or b"*" in raw:
        raise ValueError(f"not a printable frame body: {body!r}")
    return raw + b"*%02X\r\n" % checksum(raw)


def decode_frame(line: bytes) -> str:
    """The body of one received line (terminator optional); raises FrameError when invalid."""
    stripped = line.rstrip(b"\r\n")
    star = stripped.rfind(b"*")
    if star < 0 or len(stripped) - star != 3 or not set(stripped[star + 1 :]) <= _HEX:
        raise FrameError("no '*XX' checksum at the end")
    body = stripped[:star]
    if any(c < 0x20 or c > 0x7E for c in body):
        raise FrameError("non-printable bytes")
    sent, computed = int(stripped[star + 1 :], 16), checksum(body)
    if sent != computed:
        raise FrameError(f"checksum {sent:02X} does not match the body's {computed:02X}")
    return body.decode("ascii")


@dataclass(frozen=True)
class Reply:
    """One reply line.

    Attributes:
        ok: ``OK`` (True) or ``ERR`` (False).
        command: the command word it answers.
        fields: the values after the command word of an ``OK`` reply.
        code: the error code of an ``ERR`` reply.
        message: the error message of an ``ERR`` reply.
        request: the request body it answers.
        line: the reply body as received.
    """

    ok: bool
    command: str
    fields: tuple[str, ...] = ()
    code: str = ""
    message: str = ""
    request: str = ""
    line: str = ""


def parse_reply(body: str, request: str = "") -> Reply:
    """An ``OK``/``ERR`` reply from a frame body; raises FrameError for anything else."""
    words = body.split()
    if len(words) >= 2 and words[0] == "OK":
        return Reply(True, words[1], tuple(words[2:]), request=request, line=body)
    if len(words) >= 3 and words[0] == "ERR":
        message = body.split(None, 3)[3] if len(words) > 3 else ""
        return Reply(False, words[1], code=words[2], message=message, request=request, line=body)
    raise FrameError("neither 'OK <CMD> ...' nor 'ERR <CMD> <CODE> ...'")


def time_left(deadline: float) -> float:
    """Seconds until the ``time.monotonic`` deadline, never negative."""
    return max(deadline - time.monotonic(), 0.0)


def format_number(value: float) -> str:
    """A finite number as a protocol word (plain decimal, up to 6 decimals)."""
    value = float(value)
    if value != value or value in (float("inf"), float("-inf")):
        raise ValueError(f"not a finite number: {value}")
    text = f"{value:.6f}".rstrip("0").rstrip(".")
    return "0" if text in ("", "-0") else text


class Framing(Protocol):
    """How requests and replies are framed on the wire (one instance serves any number of
    links: it keeps no state).

    Attributes:
        unit: what a frame is called in messages ("line", "frame").
        end: what ends a frame, in messages ("a line end", "ETX").
        max_frame_bytes: longest reply frame accepted, its end included.
    """

    unit: str
    end: str
    max_frame_bytes: int

    def request_text(self, command: str, args: tuple[object, ...]) -> str:
        """The request as text (in messages, the audit and :attr:`Reply.request`); raises
        ValueError for a command or argument the framing cannot carry."""
        ...

    def encode(self, text: str) -> bytes:
        """The bytes of the request :meth:`request_text` gave."""
        ...

    def frame_end(self, buffer: bytes | bytearray) -> int:
        """The length of the first complete frame at the start of ``buffer`` (junk before it
        included), or -1 while none is complete."""
        ...

    def decode(self, frame: bytes, request: str) -> Reply:
        """The reply one frame carries (``request``: the text it answers); raises FrameError
        for a frame that is not a valid reply."""
        ...


class LineFraming:
    """The line framing of this module: ``<body>*XX\\r\\n``, ``OK``/``ERR`` replies."""

    unit = "line"
    end = "a line end"
    max_frame_bytes = MAX_LINE_BYTES

    def request_text(self, command: str, args: tuple[object, ...]) -> str:
        """``command`` and ``args`` separated by single spaces."""
        if not command or any(c.isspace() for c in command):
            raise ValueError(f"not a command word: {command!r}")
        return " ".join([command, *(str(a) for a in args)])

    def encode(self, text: str) -> bytes:
        """``<text>*XX\\r\\n``."""
        return encode_frame(text)

    def frame_end(self, buffer: bytes | bytearray) -> int:
        """Up to and including the first ``\\n``."""
        end = buffer.find(b"\n")
        return -1 if end < 0 else end + 1

    def decode(self, frame: bytes, request: str) -> Reply:
        """The ``OK``/``ERR`` reply of one line."""
        return parse_reply(decode_frame(frame), request=request)


LINE_FRAMING = LineFraming()
"""The default framing of :class:`SerialLink`."""


class SerialLink:
    """Request/response over one serial port, thread-safe (one request at a time).

    The port opens on first use (``serial.serial_for_url``: a device path such as
    ``/dev/ttyUSB0`` or ``/dev/pts/3``, or a pyserial URL) and reopens after a port error.

    Args:
        port: device path or pyserial URL.
        device: the device's name in error messages.
        baudrate: bits per second.
        write_timeout_s: longest a write may block, s.
        on_sent: called with each frame's body and the ``time.monotonic()`` taken just before
            its last check (a request's ``gate``) and write, once it is written: an audit of
            what was commanded when.
        framing: how frames are made and read (default: the line framing of this module).
    """

    def __init__(
        self,
        port: str,
        *,
        device: str,
        baudrate: int = DEFAULT_BAUDRATE,
        write_timeout_s: float = 1.0,
        on_sent: Callable[[str, float], None] | None = None,
        framing: Framing = LINE_FRAMING,
    ) -> None:
        self.port = port
        self.framing = framing
        self.device = device
        self.baudrate = baudrate
        self.write_timeout_s = write_timeout_s
        self.on_sent = on_sent
        self._serial: serial.SerialBase | None = None
        self._buffer = bytearray()
        self._lock = threading.Lock()  # one request (write + read of its reply) at a time
        self._write_lock = threading.Lock()  # frames are written whole
        self._urgent_lock = threading.Lock()  # guards the two below
        self._urgent_waiting: set[str] = set()
        self._urgent_replies: dict[str, Reply] = {}

    @property
    def is_open(self) -> bool:
        return self._serial is not None and self._serial.is_open

    def open(self, timeout_s: float = 1.0) -> None:
        """Open the port now (requests also open it on demand)."""
        if not self._lock.acquire(timeout=timeout_s):
            raise DeviceTimeout(f"{self.device}: link busy, port not opened within {timeout_s} s")
        try:
            self._ensure_open("open")
        finally:
            self._lock.release()

    def close(self) -> None:
        """Close the port; safe to call twice."""
        with self._write_lock:
            port, self._serial = self._serial, None
            self._buffer.clear()
        if port is not None:
            try:
                port.close()
            except (OSError, serial.SerialException):
                pass

    def request(
        self,
        command: str,
        *args: object,
        timeout_s: float,
        gate: Callable[[], None] | None = None,
    ) -> Reply:
        """Send ``command args`` and return its reply (``OK`` or ``ERR``).

        ``gate`` is called immediately before the frame is written, with the link held; what it
        raises is raised and nothing is sent (e.g. the operator's stop before an ``EXP``).

        Raises:
            DeviceTimeout: no complete reply within ``timeout_s`` s (link lock wait included).
            DeviceError: a bad frame, a reply for another command, or a port error.
        """
        body = self._body(command, args)
        deadline = time.monotonic() + timeout_s
        if not self._lock.acquire(timeout=max(timeout_s, 0.0)):
            raise DeviceTimeout(
                f"{self.device}: {body!r} not sent: link busy for {timeout_s:.3g} s"
            )
        try:
            self._ensure_open(body)
            self._discard_input(body)
            self._write(self.framing.encode(body), body, gate)
            return self._read_reply(command, body, deadline, timeout_s)
        finally:
            self._lock.release()

    def urgent(self, command: str, *args: object, timeout_s: float) -> Reply:
        """Send an idempotent command (ABORT) now, even while another request is outstanding.

        The frame is written at once; the reply is taken whenever it comes, skipping replies to
        other commands, and the command is resent when a garbled line may have been its reply.
        """
        body = self._body(command, args)
        frame = self.framing.encode(body)
        deadline = time.monotonic() + timeout_s
        if self._lock.acquire(blocking=False):
            try:
                self._ensure_open(body)
                self._discard_input(body)
                self._write(frame, body)
                return self._read_reply(command, body, deadline, timeout_s, frame)
            finally:
                self._lock.release()
        # another request is outstanding: write now, then wait for the link
        with self._urgent_lock:
            self._urgent_waiting.add(command)
            self._urgent_replies.pop(command, None)
        try:
            try:
                self._write(frame, body)
                sent = True
            except DeviceError:  # the port failed under the other request: retry below
                sent = False
            if not self._lock.acquire(timeout=time_left(deadline)):
                state = "sent, but no reply" if sent else "not sent"
                raise DeviceTimeout(
                    f"{self.device}: {body!r} {state} within {timeout_s:.3g} s (link busy)"
                )
            try:
                with self._urgent_lock:
                    stashed = self._urgent_replies.pop(command, None)
                if stashed is not None:
                    return stashed
                self._ensure_open(body)
                if not sent:
                    self._write(frame, body)
                return self._read_reply(command, body, deadline, timeout_s, frame)
            finally:
                self._lock.release()
        finally:
            with self._urgent_lock:
                self._urgent_waiting.discard(command)
                self._urgent_replies.pop(command, None)

    def refused(self, reply: Reply, error: type[DeviceError] = DeviceError) -> DeviceError:
        """The exception for an ``ERR`` reply: device, request, code and the device's message."""
        return error(f"{self.device}: {reply.request!r} refused: {reply.code} {reply.message}")

    def numbers(self, reply: Reply, count: int) -> list[float]:
        """The ``count`` numbers of an ``OK`` reply; DeviceError naming the line otherwise."""
        try:
            values = [float(word) for word in reply.fields]
        except ValueError:
            values = []
        if len(values) != count:
            raise DeviceError(
                f"{self.device}: {reply.request!r}: expected {count} number(s): {reply.line!r}"
            )
        return values

    # -- internals -------------------------------------------------------------------------

    def _body(self, command: str, args: tuple[object, ...]) -> str:
        return self.framing.request_text(command, args)

    def _ensure_open(self, body: str) -> None:
        if self.is_open:
            return
        self.close()
        try:
            port = serial.serial_for_url(self.port, do_not_open=True)
            port.baudrate = self.baudrate
            port.timeout = _READ_SLICE_S
            port.write_timeout = self.write_timeout_s
            port.open()
        except (OSError, serial.SerialException, ValueError) as exc:
            raise DeviceError(f"{self.device}: {body!r}: cannot open {self.port}: {exc}") from exc
        self._serial = port

    def _port_error(self, body: str, exc: BaseException) -> DeviceError:
        self.close()
        return DeviceError(f"{self.device}: {body!r}: port {self.port} failed: {exc}")

    def _discard_input(self, body: str) -> None:
        # the check and the discard under the urgent lock, which an urgent command takes to
        # register before it is written: its reply cannot come in between and be discarded
        with self._urgent_lock:
            if self._urgent_waiting:  # an urgent reply may be in the input already
                return
            self._buffer.clear()
            port = self._serial
            assert port is not None
            try:
                port.reset_input_buffer()
                return
            except (OSError, serial.SerialException) as exc:
                failure = exc
        raise self._port_error(body, failure) from failure

    def _write(self, frame: bytes, body: str, gate: Callable[[], None] | None = None) -> None:
        with self._write_lock:
            port = self._serial
            if port is None:
                raise DeviceError(f"{self.device}: {body!r}: port {self.port} is closed")
            t_s = time.monotonic()
            if gate is not None:
                gate()
            try:
                _write_all(port, frame, self.write_timeout_s)
            except (OSError, serial.SerialException) as exc:
                failure = exc
            else:
                failure = None
        if failure is not None:
            raise self._port_error(body, failure) from failure
        if self.on_sent is not None:
            self.on_sent(body, t_s)

    def _read_frame(self, body: str, deadline: float, timeout_s: float) -> bytes:
        port = self._serial
        assert port is not None
        framing = self.framing
        while True:
            end = framing.frame_end(self._buffer)
            if end >= 0:
                frame = bytes(self._buffer[:end])
                del self._buffer[:end]
                return frame
            if len(self._buffer) > framing.max_frame_bytes:
                junk = bytes(self._buffer[:64])
                self._buffer.clear()
                raise DeviceError(
                    f"{self.device}: reply to {body!r}: over {framing.max_frame_bytes} bytes "
                    f"without {framing.end}: {junk!r}..."
                )
            if time.monotonic() >= deadline:
                got = "nothing"
                if self._buffer:
                    got = f"partial {framing.unit} {bytes(self._buffer)!r}"
                self._buffer.clear()
                raise DeviceTimeout(
                    f"{self.device}: no reply to {body!r} within {timeout_s:.3g} s (received {got})"
                )
            try:
                chunk = _read_some(port, min(_READ_SLICE_S, time_left(deadline)))
            except (OSError, serial.SerialException) as exc:
                raise self._port_error(body, exc) from exc
            self._buffer += chunk

    def _read_reply(
        self,
        command: str,
        body: str,
        deadline: float,
        timeout_s: float,
        resend: bytes | None = None,
    ) -> Reply:
        """The reply to ``command``; ``resend`` (urgent mode) skips other replies and resends
        the frame after a garbled one."""
        while True:
            frame = self._read_frame(body, deadline, timeout_s)
            try:
                reply = self.framing.decode(frame, body)
            except FrameError as exc:
                if resend is not None:
                    self._write(resend, body)
                    continue
                raise DeviceError(
                    f"{self.device}: bad reply to {body!r}: {exc}: {frame!r}"
                ) from None
            if reply.command == command:
                return reply
            with self._urgent_lock:
                if reply.command in self._urgent_waiting:
                    self._urgent_replies[reply.command] = reply
                    continue
            if resend is not None:
                continue
            raise DeviceError(
                f"{self.device}: reply to {body!r} answers another command: {reply.line!r}"
            )


# The port's file descriptor, where it has one (a tty or pty: every device path), is read and
# written with one system call each way instead of pyserial's several (ioctl, select, a read of
# one byte, ioctl, select, read; write, select, tcdrain): each system call releases the GIL, and
# taking it back behind the scan's other threads is most of a request's latency. Ports without
# one (pyserial URLs such as loop://) go through pyserial.


def _fd(port: serial.SerialBase) -> int | None:
    try:
        return port.fileno()
    except (AttributeError, io.UnsupportedOperation):
        return None


def _read_some(port: serial.SerialBase, wait_s: float) -> bytes:
    """What the port has received, waiting up to ``wait_s`` for the first byte (b"" if none)."""
    fd = _fd(port)
    if fd is None:
        return port.read(max(1, port.in_waiting))
    if not select.select([fd], [], [], wait_s)[0]:
        return b""
    try:
        data = os.read(fd, 4 * MAX_LINE_BYTES)
    except BlockingIOError:  # the port is non-blocking; the input was taken meanwhile
        return b""
    if not data:  # what pyserial says of a readable port that returns nothing
        raise serial.SerialException(
            "device reports readiness to read but returned no data (device disconnected?)"
        )
    return data


def _write_all(port: serial.SerialBase, frame: bytes, timeout_s: float) -> None:
    """Hand the whole frame to the port's driver (not waiting for it to go out on the wire:
    the reply cannot come before it), within ``timeout_s``."""
    fd = _fd(port)
    if fd is None:
        port.write(frame)
        return
    deadline = time.monotonic() + timeout_s
    view = memoryview(frame)
    while True:
        try:
            view = view[os.write(fd, view) :]
        except BlockingIOError:
            pass
        if not view:
            return
        if not select.select([], [fd], [], time_left(deadline))[1]:
            raise serial.SerialTimeoutException("Write timeout")
