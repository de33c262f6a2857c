"""A mock serial device: a line protocol served on the master side of a pseudo-terminal.

The host opens :attr:`PtyDevice.port` (the pty's slave, e.g. ``/dev/pts/7``) with pyserial
exactly as it opens a real device. Frames are ``<body>*XX\\r\\n`` with ``XX`` the sum of the
body's bytes modulo 256 as two upper-case hex digits; replies are ``OK <CMD> ...`` or ``ERR
<CMD> <CODE> <message>`` (the command set is specified in ``scanner/serial_link.py``; this is an
independent implementation, sim imports nothing from scanner). A daemon thread reads requests
and answers them; subclasses implement :meth:`PtyDevice._handle`.
"""

from __future__ import annotations

import os
import select
import threading
import time
import tty
from collections.abc import Callable
from typing import Any, NamedTuple, Self

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
    """

    MODEL = "MOCK"
    VERSION = "1.0"

    def __init__(self, name: str, on_event: EventCallback | None = None) -> None:
        self.name = name
        self.on_event = on_event
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
            os.write(self._master, make_frame(body))
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
                while (end := pending.find(b"\n")) >= 0:
                    line = bytes(pending[: end + 1])
                    del pending[: end + 1]
                    self._receive(line)
                if len(pending) > MAX_LINE_BYTES:
                    pending.clear()
                    with self._lock:
                        self._send("ERR ? SYNTAX line too long")
            with self._lock:
                self._tick(time.monotonic())

    def _receive(self, line: bytes) -> None:
        stripped = line.rstrip(b"\r\n")
        star = stripped.rfind(b"*")
        body = stripped[:star] if star >= 0 else stripped
        first = body.split(b" ", 1)[0]
        printable = all(0x20 <= c <= 0x7E for c in body)
        command = first.decode("ascii") if first and all(0x21 <= c <= 0x7E for c in first) else "?"
        digits = stripped[star + 1 :] if star >= 0 else b""
        with self._lock:
            if len(digits) != 2 or not all(chr(c) in "0123456789ABCDEFabcdef" for c in digits):
                self._refused(command, "CHECKSUM", "missing '*XX' checksum")
                return
            if int(digits, 16) != frame_checksum(body):
                self._refused(
                    command,
                    "CHECKSUM",
                    f"checksum {digits.decode()} != {frame_checksum(body):02X}",
                )
                return
            words = body.decode("ascii").split() if printable else []
            if not words:
                self._refused(command, "SYNTAX", "empty or non-printable request")
                return
            try:
                reply = self._handle(words[0], words[1:], time.monotonic())
            except Refusal as refusal:
                self._refused(words[0], refusal.code, refusal.message)
                return
            except Exception as exc:  # a bug in the mock: answer and keep serving
                self._refused(words[0], "FAULT", f"internal error {type(exc).__name__}: {exc}")
                return
            if reply is not None:
                self._send(reply)

    def _refused(self, command: str, code: str, message: str) -> None:
        self._event("refused", command=command, code=code, message=message)
        self._send(f"ERR {command} {code} {message}")


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
