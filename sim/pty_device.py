"""A mock serial device: a request/reply protocol served on the master side of a pseudo-terminal.

The host opens :attr:`PtyDevice.port` (the pty's slave, e.g. ``/dev/pts/7``) with pyserial
exactly as it opens a real device. A daemon thread reads requests and answers them; subclasses
implement :meth:`PtyDevice._handle`. How frames look is a :class:`DeviceFraming` object; the
default, :class:`LineFraming`, is the project's line protocol: frames ``<body>*XX\\r\\n`` with
``XX`` the sum of the body's bytes modulo 256 as two upper-case hex digits, replies ``OK <CMD>
...`` or ``ERR <CMD> <CODE> <message>`` (the command set is specified in
``scanner/serial_link.py``; this is an independent implementation, sim imports nothing from
scanner). ``sim.spellman`` frames Spellman's protocol.
"""

from __future__ import annotations

import os
import select
import threading
import time
import tty
from collections.abc import Callable
from typing import Any, NamedTuple, Protocol, Self

MAX_LINE_BYTES = 256
"""Longest request line accepted, terminator included."""

EventCallback = Callable[[str, dict[str, Any]], None]
"""``on_event(name, info)``: called from the device's thread, in order."""


def frame_checksum(body: bytes) -> int:
    """Sum of the bytes of ``body`` modulo 256."""
    total = 0
    for byte in body:
        total = (total + byte) % 256
    return total


def make_frame(body: str) -> bytes:
    """``<body>*XX\\r\\n``."""
    data = body.encode("ascii")
    return data + f"*{frame_checksum(data):02X}\r\n".encode("ascii")


def number(value: float) -> str:
    """A number as a reply word (up to 6 significant digits)."""
    return f"{value:.6g}"


class Refusal(Exception):
    """Raised by a handler: the request is answered ``ERR <CMD> <code> <message>``."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code
        self.message = message


class FrameRejected(Exception):
    """Raised by :meth:`DeviceFraming.decode`: the frame is not served; it is answered with a
    refusal (``answer``) or ignored (no reply)."""

    def __init__(self, command: str, code: str, message: str, *, answer: bool = True) -> None:
        super().__init__(message)
        self.command = command
        self.code = code
        self.message = message
        self.answer = answer


class DeviceFraming(Protocol):
    """How a mock device reads requests and frames its replies (stateless, shareable).

    Attributes:
        max_frame_bytes: longest request frame accepted, its end included.
        internal_error: the refusal code a mock's internal error is answered with.
        overflow_reply: the reply body to a frame over ``max_frame_bytes`` (None: dropped).
    """

    max_frame_bytes: int
    internal_error: str
    overflow_reply: str | None

    def frame_end(self, pending: bytes | bytearray) -> int:
        """The length of the first complete frame at the start of ``pending`` (junk before it
        included), or -1 while none is complete."""
        ...

    def decode(self, frame: bytes) -> tuple[str, list[str]]:
        """The command and arguments of one request frame; raises :class:`FrameRejected`."""
        ...

    def encode(self, body: str) -> bytes:
        """One reply frame around ``body``."""
        ...

    def refusal(self, command: str, code: str, message: str) -> str:
        """The reply body refusing ``command``."""
        ...


class LineFraming:
    """The line protocol: ``<body>*XX\\r\\n``; a bad frame is answered ``ERR``."""

    max_frame_bytes = MAX_LINE_BYTES
    internal_error = "FAULT"
    overflow_reply = "ERR ? SYNTAX line too long"

    def frame_end(self, pending: bytes | bytearray) -> int:
        """Up to and including the first ``\\n``."""
        end = pending.find(b"\n")
        return -1 if end < 0 else end + 1

    def decode(self, frame: bytes) -> tuple[str, list[str]]:
        """The words of one line: checksum, then printable words."""
        stripped = frame.rstrip(b"\r\n")
        star = stripped.rfind(b"*")
        body = stripped[:star] if star >= 0 else stripped
        first = body.split(b" ", 1)[0]
        printable = all(0x20 <= c <= 0x7E for c in body)
        command = first.decode("ascii") if first and all(0x21 <= c <= 0x7E for c in first) else "?"
        digits = stripped[star + 1 :] if star >= 0 else b""
        if len(digits) != 2 or not all(chr(c) in "0123456789ABCDEFabcdef" for c in digits):
            raise FrameRejected(command, "CHECKSUM", "missing '*XX' checksum")
        if int(digits, 16) != frame_checksum(body):
            raise FrameRejected(
                command, "CHECKSUM", f"checksum {digits.decode()} != {frame_checksum(body):02X}"
            )
        words = body.decode("ascii").split() if printable else []
        if not words:
            raise FrameRejected(command, "SYNTAX", "empty or non-printable request")
        return words[0], words[1:]

    def encode(self, body: str) -> bytes:
        """``<body>*XX\\r\\n``."""
        return make_frame(body)

    def refusal(self, command: str, code: str, message: str) -> str:
        """``ERR <CMD> <CODE> <message>``."""
        return f"ERR {command} {code} {message}"


LINE_FRAMING = LineFraming()
"""The default framing of :class:`PtyDevice`."""


class Event(NamedTuple):
    """One logged event: monotonic sequence number, time since start (s), name, details."""

    seq: int
    t_s: float
    name: str
    info: dict[str, Any]


class PtyDevice:
    """Base of the mock devices: pty, serving thread, event log.

    Args:
        name: device name (thread name, logs).
        on_event: ``on_event(name, info)`` for every logged event.
        framing: how requests and replies are framed (default: the line protocol).
    """

    MODEL = "MOCK"
    VERSION = "1.0"

    def __init__(
        self,
        name: str,
        on_event: EventCallback | None = None,
        framing: DeviceFraming = LINE_FRAMING,
    ) -> None:
        self.name = name
        self.on_event = on_event
        self.framing = framing
        self.port: str | None = None
        self._lock = threading.RLock()  # device state; held while handling and replying
        self._events: list[Event] = []
        self._t0 = time.monotonic()
        self._master = -1
        self._slave = -1
        self._wake_r = -1
        self._wake_w = -1
        self._thread: threading.Thread | None = None
        self._stopping = threading.Event()

    # -- life cycle ------------------------------------------------------------------------

    def start(self) -> Self:
        """Open the pty and start serving; :attr:`port` is then the path to open."""
        if self._thread is not None:
            return self
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no echo, no line editing, no CR/LF translation
        os.set_blocking(self._master, False)
        self._wake_r, self._wake_w = os.pipe()
        self.port = os.ttyname(self._slave)
        self._stopping.clear()
        self._thread = threading.Thread(target=self._serve, name=f"mock-{self.name}", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        """Stop serving and close the pty; safe to call twice."""
        thread, self._thread = self._thread, None
        if thread is None:
            return
        self._stopping.set()
        self._wake()
        thread.join(timeout=2.0)
        for fd in (self._master, self._slave, self._wake_r, self._wake_w):
            try:
                os.close(fd)
            except OSError:
                pass
        self._master = self._slave = self._wake_r = self._wake_w = -1

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *_: object) -> None:
        self.close()

    # -- event log -------------------------------------------------------------------------

    def events(self) -> list[Event]:
        """A copy of the event log, oldest first."""
        with self._lock:
            return list(self._events)

    def event_names(self) -> list[str]:
        """The names of the logged events, oldest first."""
        with self._lock:
            return [event.name for event in self._events]

    def _event(self, event_name: str, /, **info: Any) -> None:
        with self._lock:
            event = Event(len(self._events), time.monotonic() - self._t0, event_name, info)
            self._events.append(event)
            if self.on_event is not None:
                self.on_event(event_name, info)

    # -- subclass interface ----------------------------------------------------------------

    def _handle(self, command: str, args: list[str], now: float) -> str | None:
        """The reply body to one request (None: no reply now); may raise :class:`Refusal`.
        Called with the device lock held."""
        raise NotImplementedError

    def _tick(self, now: float) -> None:
        """Advance internal state to ``now`` (called with the lock held after every wake-up)."""

    def _next_wakeup(self, now: float) -> float | None:
        """Seconds until :meth:`_tick` must run again, or None (only on requests)."""
        return None

    # -- transport -------------------------------------------------------------------------

    def _wake(self) -> None:
        if self._wake_w >= 0:
            try:
                os.write(self._wake_w, b"!")
            except OSError:
                pass

    def _send(self, body: str) -> None:
        """Write one reply frame (call with the lock held)."""
        try:
            os.write(self._master, self.framing.encode(body))
        except OSError:  # nobody reading and the pty buffer full, or closed: drop it
            pass

    def _serve(self) -> None:
        pending = bytearray()
        while not self._stopping.is_set():
            with self._lock:
                timeout = self._next_wakeup(time.monotonic())
            try:
                readable, _, _ = select.select([self._master, self._wake_r], [], [], timeout)
            except (OSError, ValueError):
                return
            if self._wake_r in readable:
                try:
                    os.read(self._wake_r, 4096)
                except OSError:
                    pass
            if self._master in readable:
                try:
                    pending += os.read(self._master, 4096)
                except BlockingIOError:
                    pass
                except OSError:
                    return
                while (end := self.framing.frame_end(pending)) >= 0:
                    frame = bytes(pending[:end])
                    del pending[:end]
                    self._receive(frame)
                if len(pending) > self.framing.max_frame_bytes:
                    pending.clear()
                    overflow = self.framing.overflow_reply
                    if overflow is not None:
                        with self._lock:
                            self._send(overflow)
            with self._lock:
                self._tick(time.monotonic())

    def _receive(self, frame: bytes) -> None:
        with self._lock:
            try:
                command, args = self.framing.decode(frame)
            except FrameRejected as rejected:
                if rejected.answer:
                    self._refused(rejected.command, rejected.code, rejected.message)
                else:
                    self._event("ignored", command=rejected.command, reason=rejected.message)
                return
            try:
                reply = self._handle(command, args, time.monotonic())
            except Refusal as refusal:
                self._refused(command, refusal.code, refusal.message)
                return
            except Exception as exc:  # a bug in the mock: answer and keep serving
                message = f"internal error {type(exc).__name__}: {exc}"
                self._refused(command, self.framing.internal_error, message)
                return
            if reply is not None:
                self._send(reply)

    def _refused(self, command: str, code: str, message: str) -> None:
        self._event("refused", command=command, code=code, message=message)
        self._send(self.framing.refusal(command, code, message))


def parse_floats(command: str, args: list[str], count: int) -> list[float]:
    """``count`` finite numbers from ``args``; raises Refusal SYNTAX otherwise."""
    if len(args) != count:
        raise Refusal("SYNTAX", f"{command} takes {count} number(s), got {len(args)}")
    values = []
    for word in args:
        try:
            value = float(word)
        except ValueError:
            raise Refusal("SYNTAX", f"not a number: {word}") from None
        if value != value or abs(value) == float("inf"):
            raise Refusal("SYNTAX", f"not a finite number: {word}")
        values.append(value)
    return values
