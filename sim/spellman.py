"""A mock Spellman X-ray generator speaking Spellman's serial protocol over a pty.

The protocol as the driver reads it is described in ``scanner/spellman.py`` and
docs/guide/serial-protocols.md; this is an independent implementation (sim imports nothing
from scanner). ``scanner.spellman.SpellmanGenerator`` opens :attr:`MockSpellman.port` as it
opens a real supply.

Frames are ``<STX><CMD>,<ARG>,...,<CSUM><ETX>``; a frame whose checksum is wrong is ignored (no
reply, event "ignored"). Replies echo the command: ``<CMD>,$,`` done, ``<CMD>,!,<code>,``
refused (1 incorrectly formatted, 2 invalid command, 3 parameter out of range), ``<CMD>,<value>,
...`` a reading.

Behaviour: the supply powers up in local mode; ``99,1`` takes remote control. HV on (``98,1``)
is refused (``!,2``) in local mode, with a fault latched or the interlock open; HV off
(``98,0``) is always honoured. Set-points (``10``, ``11``) are counts 0-4095 of full scale; the
monitors (``60``, ``61``) read the set-point while HV is on, 0 while it is off. The interlock
input (:meth:`MockSpellman.set_interlock`: the e-stop, door and deadman in series) opening
while HV is on switches HV off and latches the INTERLOCK fault; :meth:`MockSpellman.set_fault`
latches a fault (switching HV off), ``74`` resets them. There is no exposure timer: HV stays on
until the host switches it off. Faults on request, counted in HV-on commands from 1:
``timeout_at_exposure=k`` ignores the k-th ``98,1`` (no HV, no reply; later frames are served),
``interlock_open_at_exposure=k`` opens the interlock just before the k-th ``98,1``.

Every step is logged in order (:meth:`events`, ``on_event(name, info)``): "remote", "set",
"xray_on", "xray_off" (info ``reason``: "command", "interlock", "fault", "local"; ``on_s``),
"exposure", "abort" (an HV off that found HV off: the supply cannot tell a pulse's end from an
abort, both are ``98,0``), "refused", "interlock", "fault", "reset", "ignored".
``on_exposure(kv, ma, ms, seq)`` is called whenever HV goes off after being on (``ms``: how long
it was on), before the reply to the command that switched it off goes out.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from sim.pty_device import EventCallback, FrameRejected, PtyDevice, Refusal

STX = b"\x02"
ETX = b"\x03"
COUNTS = 4095
"""Count of a set-point or monitor at full scale."""
FAULTS = (
    "ARC",
    "OVER_TEMPERATURE",
    "OVER_VOLTAGE",
    "UNDER_VOLTAGE",
    "OVER_CURRENT",
    "UNDER_CURRENT",
    "INTERLOCK",
)
"""The faults, in the order of the ``68`` reply's flags."""

ExposureCallback = Callable[[float, float, float, int], None]
"""``on_exposure(kv, ma, ms, seq)``."""


def spellman_checksum(content: bytes) -> int:
    """Spellman's checksum character of ``content`` (what lies between STX and it)."""
    total = 0
    for byte in content:
        total += byte
    twos_complement = (0x100 - total % 0x100) % 0x100
    return (twos_complement & 0x7F) | 0x40


class SpellmanFraming:
    """Spellman's frames on the device side: bad checksums ignored, replies
    ``<STX><body><CSUM><ETX>`` with ``body`` ending in a comma."""

    max_frame_bytes = 256
    internal_error = "2"
    overflow_reply: str | None = None

    def frame_end(self, pending: bytes | bytearray) -> int:
        """Up to and including the first ETX."""
        end = pending.find(ETX)
        return -1 if end < 0 else end + 1

    def decode(self, frame: bytes) -> tuple[str, list[str]]:
        """The command and arguments of one request frame (from its last STX)."""
        start = frame.rfind(STX)
        inner = frame[start + 1 : -1] if start >= 0 else b""
        if len(inner) < 2:
            raise FrameRejected("?", "1", "no STX, command and checksum", answer=False)
        content, sent = inner[:-1], inner[-1]
        command = content.split(b",", 1)[0].decode("ascii", "replace")
        if sent != spellman_checksum(content):
            raise FrameRejected(command, "", f"bad checksum 0x{sent:02X}", answer=False)
        if any(c < 0x20 or c > 0x7E for c in content) or not content.endswith(b","):
            raise FrameRejected(command, "1", "not printable, or no comma before the checksum")
        words = content.decode("ascii")[:-1].split(",")
        if len(words[0]) != 2 or not words[0].isdigit():
            raise FrameRejected(command, "1", "no two-digit command")
        return words[0], words[1:]

    def encode(self, body: str) -> bytes:
        """``<STX><body><CSUM><ETX>``."""
        content = body.encode("ascii")
        return STX + content + bytes([spellman_checksum(content)]) + ETX

    def refusal(self, command: str, code: str, message: str) -> str:
        """``<CMD>,!,<code>,`` (the message is only logged)."""
        return f"{command},!,{code},"


class MockSpellman(PtyDevice):
    """The mock Spellman generator (see the module docstring).

    Args:
        kv_full_scale: tube voltage at count 4095, kVp (for ``on_exposure``).
        ma_full_scale: tube current at count 4095, mA (for ``on_exposure``).
        timeout_at_exposure: the HV-on command (1-based) that is ignored.
        interlock_open_at_exposure: the HV-on command just before which the interlock opens.
        on_event: ``on_event(name, info)`` for every logged event.
        on_exposure: ``on_exposure(kv, ma, ms, seq)`` whenever HV goes off after being on.
        name: device name.
    """

    MODEL = "MOCKSPELLMAN"
    VERSION = "1.0"

    def __init__(
        self,
        *,
        kv_full_scale: float = 150.0,
        ma_full_scale: float = 100.0,
        timeout_at_exposure: int | None = None,
        interlock_open_at_exposure: int | None = None,
        on_event: EventCallback | None = None,
        on_exposure: ExposureCallback | None = None,
        name: str = "generator",
    ) -> None:
        super().__init__(name, on_event, framing=SpellmanFraming())
        self.kv_full_scale = kv_full_scale
        self.ma_full_scale = ma_full_scale
        self.timeout_at_exposure = timeout_at_exposure
        self.interlock_open_at_exposure = interlock_open_at_exposure
        self.on_exposure = on_exposure
        self._remote = False
        self._setpoints = {"10": 0, "11": 0}  # kV, mA counts
        self._hv_since: float | None = None  # when HV went on; None: off
        self._interlock_closed = True
        self._faults: set[str] = set()
        self._exposures = 0
        self._hv_on_requests = 0

    # -- Python-side controls and readings -------------------------------------------------

    def set_interlock(self, closed: bool) -> None:
        """Close (True) or open (False) the interlock input; opening it while HV is on switches
        HV off and latches the INTERLOCK fault."""
        with self._lock:
            self._set_interlock(closed)

    def set_fault(self, fault: str | None) -> None:
        """Latch ``fault`` (one of :data:`FAULTS`; HV goes off) or, with None, clear all."""
        if fault is not None and fault not in FAULTS:
            raise ValueError(f"unknown fault {fault!r}; one of {FAULTS}")
        with self._lock:
            self._latch(fault)

    def set_remote(self, remote: bool) -> None:
        """The front panel's local/remote switch; going local switches HV off."""
        with self._lock:
            self._set_remote(remote)

    @property
    def xray_on(self) -> bool:
        """HV is on now."""
        with self._lock:
            return self._hv_since is not None

    @property
    def exposures(self) -> int:
        """HV-on periods ended since start."""
        with self._lock:
            return self._exposures

    @property
    def remote(self) -> bool:
        """In remote mode."""
        with self._lock:
            return self._remote

    @property
    def faults(self) -> tuple[str, ...]:
        """The latched faults, in :data:`FAULTS` order."""
        with self._lock:
            return tuple(f for f in FAULTS if f in self._faults)

    # -- protocol --------------------------------------------------------------------------

    def _handle(self, command: str, args: list[str], now: float) -> str | None:
        if command in ("10", "11"):
            (count,) = self._counts(command, args, 1)
            if count > COUNTS:
                raise Refusal("3", f"{command}: {count} above {COUNTS}")
            self._setpoints[command] = count
            self._event("set", command=command, count=count)
            return f"{command},$,"
        if command == "98":
            return self._hv(self._switch(command, args), now)
        if command == "99":
            self._set_remote(self._switch(command, args))
            return "99,$,"
        if command == "74":
            self._no_args(command, args)
            self._faults.clear()
            self._event("reset")
            return "74,$,"
        readings = {
            "14": lambda: [self._setpoints["10"]],
            "15": lambda: [self._setpoints["11"]],
            "20": lambda: [self._monitor("10"), self._monitor("11")],
            "22": lambda: [
                int(self._hv_since is not None),
                int(not self._interlock_closed),
                int(bool(self._faults)),
                int(self._remote),
            ],
            "23": lambda: [self.VERSION],
            "26": lambda: [self.MODEL],
            "60": lambda: [self._monitor("10")],
            "61": lambda: [self._monitor("11")],
            "68": lambda: [int(f in self._faults) for f in FAULTS],
        }
        if command in readings:
            self._no_args(command, args)
            return ",".join([command, *(str(v) for v in readings[command]())]) + ","
        raise Refusal("2", f"unknown command {command}")

    def _hv(self, on: bool, now: float) -> str | None:
        if not on:
            if self._hv_since is None:
                self._event("abort", xray_on=False)
            else:
                self._hv_off(now, "command")
            return "98,$,"
        self._hv_on_requests += 1
        k = self._hv_on_requests
        if k == self.timeout_at_exposure:
            self._event("ignored", command="98", request=k)
            return None
        if k == self.interlock_open_at_exposure:
            self._set_interlock(False)
        if not self._remote:
            raise Refusal("2", "HV on refused: local mode")
        if self._faults:
            raise Refusal("2", f"HV on refused: fault {','.join(sorted(self._faults))} latched")
        if not self._interlock_closed:
            raise Refusal("2", "HV on refused: interlock open")
        if self._hv_since is None:
            self._hv_since = now
            kv, ma = self._physical()
            self._event("xray_on", kv=kv, ma=ma, request=k)
        return "98,$,"

    def _hv_off(self, now: float, reason: str) -> None:
        """HV off after it was on: log it, count it, tell ``on_exposure``."""
        since = self._hv_since
        assert since is not None
        self._hv_since = None
        on_s = now - since
        self._exposures += 1
        seq = self._exposures
        kv, ma = self._physical()
        self._event("xray_off", reason=reason, on_s=on_s)
        if self.on_exposure is not None:
            self.on_exposure(kv, ma, on_s * 1e3, seq)
        self._event("exposure", kv=kv, ma=ma, ms=on_s * 1e3, seq=seq)

    def _set_interlock(self, closed: bool) -> None:
        self._interlock_closed = closed
        self._event("interlock", closed=closed)
        if not closed and self._hv_since is not None:
            self._hv_off(time.monotonic(), "interlock")
            self._latch("INTERLOCK")

    def _latch(self, fault: str | None) -> None:
        if fault is None:
            self._faults.clear()
            self._event("fault", code=None)
            return
        self._faults.add(fault)
        self._event("fault", code=fault)
        if self._hv_since is not None:
            self._hv_off(time.monotonic(), "fault")

    def _set_remote(self, remote: bool) -> None:
        self._remote = remote
        self._event("remote", remote=remote)
        if not remote and self._hv_since is not None:
            self._hv_off(time.monotonic(), "local")

    def _monitor(self, setpoint: str) -> int:
        return self._setpoints[setpoint] if self._hv_since is not None else 0

    def _physical(self) -> tuple[float, float]:
        """The set-points in kV and mA."""
        kv = self._setpoints["10"] * self.kv_full_scale / COUNTS
        ma = self._setpoints["11"] * self.ma_full_scale / COUNTS
        return kv, ma

    @staticmethod
    def _counts(command: str, args: list[str], count: int) -> list[int]:
        if len(args) != count or not all(a.isdigit() and a.isascii() for a in args):
            raise Refusal("1", f"{command} takes {count} unsigned integer(s): {args}")
        return [int(a) for a in args]

    def _switch(self, command: str, args: list[str]) -> bool:
        (value,) = self._counts(command, args, 1)
        if value not in (0, 1):
            raise Refusal("3", f"{command}: {value} is neither 0 nor 1")
        return value == 1

    @staticmethod
    def _no_args(command: str, args: list[str]) -> None:
        if args:
            raise Refusal("1", f"{command} takes no arguments: {args}")
