"""Spellman X-ray generators over RS-232: :class:`SpellmanGenerator` implements ``XrayGenerator``.

Spellman's uX, XRB and PMX families of X-ray generators and HV supplies document one serial
protocol; this module is our reading of it (docs/guide/serial-protocols.md says where it is
an interpretation), written from the public documentation of the protocol, not from code.

Framing
-------
``<STX><CMD>,<ARG>,...,<CSUM><ETX>``: STX 0x02, ``CMD`` two ASCII digits, every argument
followed by a comma (the command too), one checksum character, ETX 0x03. The checksum
(:func:`spellman_checksum`) is the sum of the bytes between STX and it, negated, its 8 least
significant bits with bit 7 cleared and bit 6 set: always 0x40..0x7F, never STX nor ETX. The
supply ignores a frame whose checksum is wrong: no reply, a timeout is the only NACK.

Replies echo the command: ``10,$,`` (done), ``10,!,<code>,`` (refused: 1 incorrectly formatted
message, 2 invalid command, 3 parameter out of range), ``60,<value>,`` (a reading).

Commands used
-------------
``10,<n>`` / ``11,<n>``: kV / mA set-point, 0-4095 of the model's full scale (configured:
``kv_full_scale``, ``ma_full_scale``). ``22``: status, ``22,<hv_on>,<interlock_open>,<fault>,
<remote>,`` (0/1 each, :data:`STATUS_FLAGS`). ``23``: software version. ``26``: model number.
``60`` / ``61``: kV / mA monitor, 0-4095 of full scale. ``68``: faults, one 0/1 flag each
(:data:`FAULT_FLAGS`). ``74``: reset faults. ``98,<0|1>``: HV off / on. ``99,<0|1>``: local /
remote mode.

Exposures
---------
The supply has no exposure timer: :meth:`SpellmanGenerator.expose` switches HV on (``98,1``),
times the pulse on the host's ``time.monotonic``, polls the status meanwhile, reads the kV and
mA monitors half-way, switches HV off (``98,0``) and confirms it in the status. ``98,0`` is also
the urgent command (:meth:`SerialLink.urgent <scanner.serial_link.SerialLink.urgent>`): sent at
once, even while another request waits for its reply. Should the host die mid-pulse, HV stays
on until the interlock chain (e-stop, door and deadman in series) opens: the deadman is the
backstop of a host-timed exposure.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from scanner.hardware import DeviceError, Exposure, GeneratorStatus, Technique
from scanner.serial_link import DEFAULT_BAUDRATE, FrameError, Reply, SerialLink, time_left

STX = 0x02
"""Start of a frame."""
ETX = 0x03
"""End of a frame."""
FULL_SCALE_COUNTS = 4095
"""The set-points' and monitors' count at full scale (12 bits)."""
ERROR_CODES = {
    "1": "incorrectly formatted message",
    "2": "invalid command",
    "3": "parameter out of range",
}
"""The codes of a refusal ``<CMD>,!,<code>,``."""
STATUS_FLAGS = ("hv_on", "interlock_open", "fault", "remote")
"""The fields of the status reply ``22,...``, in order (our reading; 1 = true)."""
FAULT_FLAGS = (
    "ARC",
    "OVER_TEMPERATURE",
    "OVER_VOLTAGE",
    "UNDER_VOLTAGE",
    "OVER_CURRENT",
    "UNDER_CURRENT",
    "INTERLOCK",
)
"""The fields of the fault reply ``68,...``, in order (our reading; 1 = latched). INTERLOCK:
the interlock opened while HV was on."""

_DIGITS = frozenset("0123456789")


def spellman_checksum(content: bytes) -> int:
    """The checksum byte of ``content`` (the bytes between STX and the checksum): the two's
    complement of their sum, 8 bits, bit 7 cleared, bit 6 set (0x40..0x7F)."""
    return (-sum(content) & 0xFF) & 0x7F | 0x40


class SpellmanFraming:
    """Spellman's frames for :class:`~scanner.serial_link.SerialLink`.

    A request's text is its command and arguments joined by commas (``98,1``); on the wire it
    is ``<STX>98,1,<CSUM><ETX>``.
    """

    unit = "frame"
    end = "ETX"
    max_frame_bytes = 256

    def request_text(self, command: str, args: tuple[object, ...]) -> str:
        """``<CMD>,<ARG>,...`` (without the trailing comma); ValueError when ``command`` is
        not two digits or an argument is empty or holds a comma or a control character."""
        if len(command) != 2 or not set(command) <= _DIGITS:
            raise ValueError(f"not a two-digit command: {command!r}")
        words = [str(a) for a in args]
        for word in words:
            if not word or "," in word or any(not 0x20 <= ord(c) <= 0x7E for c in word):
                raise ValueError(f"not an argument of {command}: {word!r}")
        return ",".join([command, *words])

    def encode(self, text: str) -> bytes:
        """``<STX><text>,<CSUM><ETX>``."""
        content = text.encode("ascii") + b","
        return bytes([STX]) + content + bytes([spellman_checksum(content), ETX])

    def frame_end(self, buffer: bytes | bytearray) -> int:
        """Up to and including the first ETX."""
        end = buffer.find(ETX)
        return -1 if end < 0 else end + 1

    def decode(self, frame: bytes, request: str) -> Reply:
        """The reply of one frame (from its last STX: line noise before it is dropped)."""
        start = frame.rfind(STX)
        if start < 0:
            raise FrameError("no STX")
        inner = frame[start + 1 : -1]
        if len(inner) < 2:
            raise FrameError("too short for a command and a checksum")
        content, sent = inner[:-1], inner[-1]
        if any(not 0x20 <= c <= 0x7E for c in content):
            raise FrameError("non-printable bytes")
        computed = spellman_checksum(content)
        if sent != computed:
            raise FrameError(f"checksum 0x{sent:02X} does not match the content's 0x{computed:02X}")
        text = content.decode("ascii")
        if not text.endswith(","):
            raise FrameError("no comma before the checksum")
        command, *fields = text[:-1].split(",")
        if len(command) != 2 or not set(command) <= _DIGITS:
            raise FrameError("no two-digit command")
        if fields == ["$"]:
            return Reply(True, command, request=request, line=text)
        if fields and fields[0] == "!":
            code = fields[1] if len(fields) > 1 else "?"
            message = ERROR_CODES.get(code, "unknown error code")
            return Reply(False, command, code=code, message=message, request=request, line=text)
        return Reply(True, command, tuple(fields), request=request, line=text)


SPELLMAN_FRAMING = SpellmanFraming()
"""The framing of every Spellman link."""


@dataclass(frozen=True)
class SupplyStatus:
    """One reading of the status (``22``) and, when a fault is flagged, the faults (``68``)."""

    hv_on: bool
    interlock_open: bool
    fault: bool
    remote: bool
    faults: tuple[str, ...] = ()

    def fault_text(self) -> str | None:
        """The latched faults in words, or None."""
        if self.faults:
            return ",".join(self.faults)
        return "UNSPECIFIED" if self.fault else None


class _PulseCut(DeviceError):
    """The supply or the host ended a pulse before its width."""


class _HvOnRefused(DeviceError):
    """The supply refused HV on: nothing fired."""


class SpellmanGenerator:
    """An X-ray generator on a Spellman supply (see the module docstring).

    Args:
        port: device path (``/dev/ttyUSB1``) or pyserial URL (``socket://host:port``).
        baudrate: bits per second.
        name: the device's name in error messages.
        kv_full_scale: tube voltage at count 4095, kVp (the model's); the highest kV.
        ma_full_scale: tube current at count 4095, mA (the model's); the highest mA.
        kv_min: the tube's lowest voltage, kVp.
        ma_min: the tube's lowest current, mA.
        ms_limits: shortest and longest pulse the host times, ms.
        poll_s: status polling period during a pulse, s.
        overrun_s: longest a pulse may run past its width while a reply is overdue, s: then
            HV is switched off and the exposure fails.
        off_timeout_s: timeout of an HV off the driver sends itself (a failed pulse, close), s.
        on_sent: called with every command sent and the ``time.monotonic()`` it was sent at,
            the command's commas turned into spaces (``98 1``): the session's command log,
            a CSV file.
    """

    def __init__(
        self,
        port: str,
        baudrate: int = DEFAULT_BAUDRATE,
        name: str = "generator",
        *,
        kv_full_scale: float = 150.0,
        ma_full_scale: float = 100.0,
        kv_min: float = 40.0,
        ma_min: float = 0.5,
        ms_limits: tuple[float, float] = (5.0, 1000.0),
        poll_s: float = 0.005,
        overrun_s: float = 0.05,
        off_timeout_s: float = 0.5,
        on_sent: Callable[[str, float], None] | None = None,
    ) -> None:
        if not 0 < kv_min < kv_full_scale or not 0 < ma_min < ma_full_scale:
            raise ValueError(
                f"{name}: need 0 < minimum < full scale: kV {kv_min}..{kv_full_scale}, "
                f"mA {ma_min}..{ma_full_scale}"
            )
        if not 0 < ms_limits[0] < ms_limits[1]:
            raise ValueError(f"{name}: need 0 < shortest < longest pulse: {ms_limits} ms")
        self.name = name
        self.kv_full_scale = kv_full_scale
        self.ma_full_scale = ma_full_scale
        self.kv_min = kv_min
        self.ma_min = ma_min
        self.ms_limits = ms_limits
        self.poll_s = poll_s
        self.overrun_s = overrun_s
        self.off_timeout_s = off_timeout_s
        self.ident: str | None = None
        audit = None
        if on_sent is not None:

            def audit(text: str, t_s: float) -> None:
                on_sent(text.replace(",", " "), t_s)

        self._link = SerialLink(
            port, device=name, baudrate=baudrate, on_sent=audit, framing=SPELLMAN_FRAMING
        )
        self._technique: Technique | None = None
        self._prepared = False
        self._exposures = 0
        self._aborts = 0  # abort() calls so far: a pulse started before one is cut
        self._state_lock = threading.Lock()
        self._pulse_lock = threading.Lock()  # one exposure (or technique change) at a time
        self._woken = threading.Event()  # set by abort(): a pulse's wait ends at once

    # -- XrayGenerator -----------------------------------------------------------------------

    def connect(self, timeout_s: float) -> None:
        """Open the port, take remote control (``99,1``), switch HV off when it is on (a host
        that died mid-pulse), read the model (``26``) and software version (``23``) into
        :attr:`ident`."""
        deadline = time.monotonic() + timeout_s
        self._call("99", 1, timeout_s=timeout_s)
        if self._read_status(time_left(deadline)).hv_on:
            problem, _ = self._switch_off()
            if problem is not None:
                raise DeviceError(
                    f"{self.name}: HV on at connect: X-RAY OFF NOT CONFIRMED: {problem}"
                )
        model = self._call("26", timeout_s=time_left(deadline))
        version = self._call("23", timeout_s=time_left(deadline))
        self.ident = " ".join((*model.fields, *version.fields))

    def set_technique(self, technique: Technique, timeout_s: float) -> None:
        """Program kV (``10``) and mA (``11``) as counts of full scale; keep the pulse width.

        Every value is checked first: one above its full scale (kV, mA) or longest pulse, or
        below the tube's minimum or the shortest pulse, is refused naming value and limit and
        nothing is sent. Until both set-points are confirmed no technique is set (a refused
        one leaves none: :meth:`expose` refuses).
        """
        limits = (
            ("kV", technique.kv, self.kv_min, self.kv_full_scale),
            ("mA", technique.ma, self.ma_min, self.ma_full_scale),
            ("ms", technique.ms, *self.ms_limits),
        )
        for label, value, low, high in limits:
            if not math.isfinite(value):
                raise DeviceError(f"{self.name}: {label} {value!r} is not a number: nothing sent")
            if value < low:
                raise DeviceError(
                    f"{self.name}: {label} {value:g} below limit {low:g}: nothing sent"
                )
            if value > high:
                raise DeviceError(
                    f"{self.name}: {label} {value:g} above limit {high:g}: nothing sent"
                )
        kv_counts = round(technique.kv / self.kv_full_scale * FULL_SCALE_COUNTS)
        ma_counts = round(technique.ma / self.ma_full_scale * FULL_SCALE_COUNTS)
        if not self._pulse_lock.acquire(blocking=False):
            raise DeviceError(f"{self.name}: technique not changed: a pulse is running")
        try:
            deadline = time.monotonic() + timeout_s
            self._technique = None
            self._call("10", kv_counts, timeout_s=timeout_s)
            self._call("11", ma_counts, timeout_s=time_left(deadline))
            self._technique = Technique(
                kv=self._scale(kv_counts, self.kv_full_scale),
                ma=self._scale(ma_counts, self.ma_full_scale),
                ms=technique.ms,
            )
        finally:
            self._pulse_lock.release()

    def prepare(self, timeout_s: float) -> None:
        """Get ready to expose: a technique set, the supply in remote mode, no fault latched
        (the faults, ``68``, named when one is); there is no warm-up. The interlock is checked
        before each pulse (:attr:`GeneratorStatus.ready` needs it closed)."""
        deadline = time.monotonic() + timeout_s
        if self._technique is None:
            raise DeviceError(f"{self.name}: not prepared: no technique set")
        status = self._read_status(timeout_s)
        faults = self._read_faults(time_left(deadline))
        if faults or status.fault:
            named = ",".join(faults) or "UNSPECIFIED"
            raise DeviceError(
                f"{self.name}: not prepared: fault {named} latched (clear its cause, then "
                "reset the faults)"
            )
        if not status.remote:
            raise DeviceError(f"{self.name}: not prepared: the supply is in local mode")
        with self._state_lock:
            self._prepared = True

    def expose(self, timeout_s: float, permit: Callable[[], None] | None = None) -> Exposure:
        """Fire one pulse of the set technique; returns the technique delivered (kV and mA from
        the monitors read half-way, ms as timed on the host) and its sequence number (pulses
        this driver delivered).

        Before HV on: the status must show remote mode, the interlock closed, no fault and HV
        off, else DeviceError and nothing is sent. ``permit`` is called immediately before
        ``98,1`` is written (the link held); what it raises is raised and nothing is sent.
        During the pulse the status is polled; HV that goes off, an interlock that opens, a
        fault, :meth:`abort`, an overdue reply: HV off (``98,0``), then DeviceError
        (DeviceTimeout for an overdue reply) saying whether the X-ray off was confirmed. After
        the pulse width: HV off, confirmed in the status (DeviceError with X-RAY OFF NOT
        CONFIRMED otherwise).
        """
        if not self._pulse_lock.acquire(blocking=False):
            raise DeviceError(f"{self.name}: '98,1' not sent: a pulse is running")
        try:
            return self._expose(timeout_s, permit)
        finally:
            self._pulse_lock.release()

    def abort(self, timeout_s: float) -> None:
        """HV off now (``98,0``); returns when the supply confirms it (``98,$``).

        Independent of earlier state: (re)opens the port if needed and is written at once even
        while another request waits for its reply. A pulse running is cut (its :meth:`expose`
        raises) and the generator is no longer prepared.
        """
        with self._state_lock:
            self._aborts += 1
            self._prepared = False
        self._woken.set()
        reply = self._link.urgent("98", 0, timeout_s=timeout_s)
        if not reply.ok:
            raise self._link.refused(reply)

    def status(self, timeout_s: float) -> GeneratorStatus:
        """The supply's status (``22``; ``68`` when a fault is flagged): ready (prepared,
        remote, no fault, interlock closed), the technique this driver set, the interlock
        (True = closed), the pulses this driver delivered, the fault."""
        status = self._read_status(timeout_s)
        with self._state_lock:
            prepared = self._prepared
        return GeneratorStatus(
            ready=prepared and status.remote and not status.fault and not status.interlock_open,
            technique=self._technique,
            interlocks={"interlock": not status.interlock_open},
            exposures=self._exposures,
            fault=status.fault_text(),
        )

    def reset_faults(self, timeout_s: float) -> None:
        """Reset the latched faults (``74``): an operator's action, never taken by itself."""
        self._call("74", timeout_s=timeout_s)

    def close(self) -> None:
        """HV off (best effort, when connected) and release the port; safe to call twice."""
        if self._link.is_open:
            try:
                self.abort(self.off_timeout_s)
            except DeviceError:
                pass
        self._link.close()

    def __enter__(self) -> SpellmanGenerator:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    # -- internals -----------------------------------------------------------------------------

    def _expose(self, timeout_s: float, permit: Callable[[], None] | None) -> Exposure:
        deadline = time.monotonic() + timeout_s
        technique = self._technique
        if technique is None:
            raise DeviceError(f"{self.name}: '98,1' not sent: no technique set")
        with self._state_lock:
            prepared, aborts = self._prepared, self._aborts
        self._woken.clear()
        if not prepared:
            raise DeviceError(f"{self.name}: '98,1' not sent: not prepared (prepare first)")
        pulse_s = technique.ms * 1e-3
        if pulse_s >= timeout_s:
            raise DeviceError(
                f"{self.name}: '98,1' not sent: the {technique.ms:g} ms pulse does not fit in "
                f"the {timeout_s:.3g} s timeout"
            )
        status = self._read_status(time_left(deadline))
        if status.hv_on:
            problem, _ = self._switch_off()
            raise DeviceError(
                f"{self.name}: '98,1' not sent: HV was on before the pulse; {_off_note(problem)}"
            )
        blocker = self._blocker(status)
        if blocker is not None:
            raise DeviceError(f"{self.name}: '98,1' not sent: {blocker}")
        t_on: float | None = None

        def gate() -> None:
            nonlocal t_on
            if permit is not None:
                permit()
            if self._aborts != aborts:
                raise DeviceError(f"{self.name}: '98,1' not sent: aborted")
            t_on = time.monotonic()

        try:
            reply = self._link.request(
                "98", 1, timeout_s=min(time_left(deadline), pulse_s + self.overrun_s), gate=gate
            )
            if not reply.ok:
                raise self._hv_on_refused(reply)
            assert t_on is not None
            kv, ma = self._watch(t_on, pulse_s, aborts)
        except _HvOnRefused:
            raise
        except BaseException as err:
            if t_on is None:  # nothing sent
                raise
            self._off_after(err, t_on)
            raise
        t_off = time.monotonic()
        problem, after = self._switch_off()
        on_ms = (t_off - t_on) * 1e3
        if problem is not None:
            raise DeviceError(f"{self.name}: pulse of {on_ms:.1f} ms ended: {_off_note(problem)}")
        assert after is not None
        if after.interlock_open or after.fault:  # it may have ended the pulse early
            raise DeviceError(
                f"{self.name}: pulse of {on_ms:.1f} ms spoilt: {self._cut_reason(after)}; "
                "X-ray off confirmed; not counted"
            )
        self._exposures += 1
        return Exposure(Technique(kv=kv, ma=ma, ms=round(on_ms, 3)), self._exposures)

    def _watch(self, t_on: float, pulse_s: float, aborts: int) -> tuple[float, float]:
        """Wait out the pulse from ``t_on``, polling the status; the kV and mA monitors read
        half-way. Raises _PulseCut or DeviceError (HV still to be switched off)."""
        t_end = t_on + pulse_s
        t_monitors = t_on + pulse_s / 2
        round_trip = time.monotonic() - t_on  # the HV on's
        polled = False
        monitors: tuple[float, float] | None = None
        while True:
            if self._aborts != aborts:
                raise _PulseCut("aborted")
            now = time.monotonic()
            if monitors is None and now >= t_monitors:
                monitors = (
                    self._monitor("60", self.kv_full_scale, t_end),
                    self._monitor("61", self.ma_full_scale, t_end),
                )
                round_trip = max(round_trip, (time.monotonic() - now) / 2)
                continue
            if now >= t_end and monitors is not None:
                return monitors
            if not polled or t_end - now > 2 * round_trip:
                timeout = t_end - now + self.overrun_s
                status = self._read_status(timeout)
                round_trip = max(round_trip, time.monotonic() - now)
                polled = True
                cut = self._cut_reason(status)
                if cut is not None:
                    raise _PulseCut(cut)
            wake = t_end if monitors is not None else t_monitors
            if t_end - time.monotonic() > 2 * round_trip:
                wake = min(wake, time.monotonic() + self.poll_s)
            self._woken.wait(max(wake - time.monotonic(), 0.0))

    def _monitor(self, command: str, full_scale: float, t_end: float) -> float:
        reply = self._call(command, timeout_s=max(t_end - time.monotonic(), 0.0) + self.overrun_s)
        (count,) = self._counts(reply, 1)
        return self._scale(count, full_scale)

    def _off_after(self, err: BaseException, t_on: float) -> None:
        """HV off after a pulse failed; the note on X-ray off joins ``err``'s message."""
        on_ms = (time.monotonic() - t_on) * 1e3
        problem, _ = self._switch_off()
        note = _off_note(problem)
        if isinstance(err, _PulseCut):
            raise DeviceError(
                f"{self.name}: pulse cut after {on_ms:.1f} ms: {err}; {note}; not counted"
            ) from None
        if isinstance(err, DeviceError):
            raise type(err)(f"{err}; HV switched off after {on_ms:.1f} ms: {note}") from err
        err.add_note(f"{self.name}: HV switched off after {on_ms:.1f} ms: {note}")

    def _switch_off(self) -> tuple[str | None, SupplyStatus | None]:
        """HV off (``98,0``, urgent) and confirmed in the status: (None, the status) when
        confirmed, else (why not, the status if one was read)."""
        try:
            reply = self._link.urgent("98", 0, timeout_s=self.off_timeout_s)
            if not reply.ok:
                return str(self._link.refused(reply)), None
            status = self._read_status(self.off_timeout_s)
        except DeviceError as exc:
            return str(exc), None
        if status.hv_on:
            return "the status still reports HV on", status
        return None, status

    def _read_status(self, timeout_s: float) -> SupplyStatus:
        deadline = time.monotonic() + timeout_s
        reply = self._call("22", timeout_s=timeout_s)
        flags = self._flags(reply, len(STATUS_FLAGS))
        status = SupplyStatus(**dict(zip(STATUS_FLAGS, flags, strict=True)))
        if status.fault:
            faults = self._read_faults(time_left(deadline))
            status = SupplyStatus(**dict(zip(STATUS_FLAGS, flags, strict=True)), faults=faults)
        return status

    def _read_faults(self, timeout_s: float) -> tuple[str, ...]:
        reply = self._call("68", timeout_s=timeout_s)
        flags = self._flags(reply, len(FAULT_FLAGS))
        return tuple(name for name, flag in zip(FAULT_FLAGS, flags, strict=True) if flag)

    def _blocker(self, status: SupplyStatus) -> str | None:
        """Why a pulse may not start, or None."""
        if not status.remote:
            return "the supply is in local mode"
        if status.interlock_open:
            return "interlock open"
        if status.fault:
            return f"fault {status.fault_text()} latched"
        return None

    def _cut_reason(self, status: SupplyStatus) -> str | None:
        """Why a running pulse ended (or must end), or None."""
        if status.interlock_open:
            return "interlock opened"
        if status.fault:
            return f"fault {status.fault_text()}"
        if not status.remote:
            return "the supply went to local mode"
        if not status.hv_on:
            return "HV went off"
        return None

    def _hv_on_refused(self, reply: Reply) -> _HvOnRefused:
        """HV on refused (nothing fired): the code, and why from the status where it says."""
        why = ""
        try:
            blocker = self._blocker(self._read_status(self.off_timeout_s))
            if blocker is not None:
                why = f": {blocker}"
        except DeviceError:
            pass
        return _HvOnRefused(
            f"{self.name}: '98,1' refused: {reply.code} {reply.message}{why}; nothing fired"
        )

    def _call(self, command: str, *args: object, timeout_s: float) -> Reply:
        reply = self._link.request(command, *args, timeout_s=timeout_s)
        if not reply.ok:
            raise self._link.refused(reply)
        return reply

    def _counts(self, reply: Reply, count: int) -> list[int]:
        """The ``count`` integers 0-4095 of a reply; DeviceError naming the frame otherwise."""
        words = reply.fields
        if len(words) != count or not all(w and set(w) <= _DIGITS for w in words):
            raise DeviceError(
                f"{self.name}: {reply.request!r}: expected {count} count(s): {reply.line!r}"
            )
        values = [int(w) for w in words]
        if any(v > FULL_SCALE_COUNTS for v in values):
            raise DeviceError(
                f"{self.name}: {reply.request!r}: count above {FULL_SCALE_COUNTS}: {reply.line!r}"
            )
        return values

    def _flags(self, reply: Reply, count: int) -> list[bool]:
        """The ``count`` 0/1 flags of a reply; DeviceError naming the frame otherwise."""
        if len(reply.fields) != count or not all(w in ("0", "1") for w in reply.fields):
            raise DeviceError(
                f"{self.name}: {reply.request!r}: expected {count} 0/1 flags: {reply.line!r}"
            )
        return [w == "1" for w in reply.fields]

    @staticmethod
    def _scale(count: int, full_scale: float) -> float:
        return count * full_scale / FULL_SCALE_COUNTS


def _off_note(problem: str | None) -> str:
    """``X-ray off confirmed``, or ``X-RAY OFF NOT CONFIRMED: <problem>``."""
    return "X-ray off confirmed" if problem is None else f"X-RAY OFF NOT CONFIRMED: {problem}"
