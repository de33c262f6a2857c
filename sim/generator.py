"""A mock X-ray generator speaking the generator's serial command set over a pty.

The command set is specified in ``scanner/serial_link.py`` (``ID?``, ``KV``, ``MA``, ``MS``,
``PREP``, ``EXP``, ``ABORT``, ``STATUS?``); the driver ``scanner.generator.SerialGenerator``
opens :attr:`MockGenerator.port` as it opens a real generator.

Behaviour: technique limits are the generator's (``ERR KV RANGE kV 160 above limit 150``);
``PREP`` warms up for ``warmup_s`` seconds before READY; ``EXP`` fires only when READY with the
e-stop, door and deadman interlocks closed (:meth:`MockGenerator.set_interlock`), otherwise it is
refused and nothing fires; a pulse lasts ``ms * time_scale`` milliseconds (0: instantaneous);
``ABORT`` is always honoured, also mid-pulse, and drops READY; an interlock that opens
mid-pulse cuts it. Faults on request: ``timeout_at_exposure=k`` ignores the k-th ``EXP`` (no
pulse, no reply; later requests are served), ``stuck_on_at_exposure=k`` switches the tube on at
the k-th ``EXP`` and never answers nor ends the pulse until ``ABORT`` (or an interlock opens),
``interlock_open_at_exposure=k`` opens the door just before the k-th ``EXP``; and
:meth:`MockGenerator.set_fault` latches a fault. ``EXP`` requests are counted from 1.

Every step is logged in order (:meth:`events`, ``on_event(name, info)``): "set", "prep",
"ready", "xray_on", "xray_off" (info ``reason``: "end", "abort", "interlock"), "exposure",
"abort", "refused", "interlock", "fault", "ignored". ``on_exposure(kv, ma, ms, seq)`` is called
when a pulse has been delivered, before the ``OK EXP`` reply goes out.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

from sim.pty_device import EventCallback, PtyDevice, Refusal, number, parse_floats

INTERLOCKS = ("estop", "door", "deadman")
"""The generator's interlock inputs, in STATUS? order."""

ExposureCallback = Callable[[float, float, float, int], None]
"""``on_exposure(kv, ma, ms, seq)``."""


@dataclass
class _Pulse:
    kv: float
    ma: float
    ms: float
    t_on: float
    t_end: float | None  # None: stuck on
    answer: bool  # the EXP waits for a reply


class MockGenerator(PtyDevice):
    """The mock generator (see the module docstring).

    Args:
        kv_limits: lowest and highest tube voltage, kVp.
        ma_limits: lowest and highest tube current, mA.
        ms_limits: shortest and longest pulse, ms.
        warmup_s: warm-up time after PREP, s.
        time_scale: real seconds per nominal pulse second (0: pulses take no time).
        timeout_at_exposure: the EXP (1-based) that is ignored.
        stuck_on_at_exposure: the EXP whose pulse never ends by itself and is never answered.
        interlock_open_at_exposure: the EXP just before which the door opens.
        on_event: ``on_event(name, info)`` for every logged event.
        on_exposure: ``on_exposure(kv, ma, ms, seq)`` for every delivered pulse.
        name: device name.
    """

    MODEL = "MOCKGEN"

    def __init__(
        self,
        *,
        kv_limits: tuple[float, float] = (40.0, 150.0),
        ma_limits: tuple[float, float] = (0.5, 500.0),
        ms_limits: tuple[float, float] = (1.0, 1000.0),
        warmup_s: float = 0.05,
        time_scale: float = 1.0,
        timeout_at_exposure: int | None = None,
        stuck_on_at_exposure: int | None = None,
        interlock_open_at_exposure: int | None = None,
        on_event: EventCallback | None = None,
        on_exposure: ExposureCallback | None = None,
        name: str = "generator",
    ) -> None:
        super().__init__(name, on_event)
        self.limits = {"KV": kv_limits, "MA": ma_limits, "MS": ms_limits}
        self.warmup_s = warmup_s
        self.time_scale = time_scale
        self.timeout_at_exposure = timeout_at_exposure
        self.stuck_on_at_exposure = stuck_on_at_exposure
        self.interlock_open_at_exposure = interlock_open_at_exposure
        self.on_exposure = on_exposure
        self._technique: dict[str, float | None] = {"KV": None, "MA": None, "MS": None}
        self._interlocks = dict.fromkeys(INTERLOCKS, True)
        self._fault: str | None = None
        self._warm_until: float | None = None
        self._ready = False
        self._pulse: _Pulse | None = None
        self._exposures = 0
        self._exp_requests = 0

    # -- Python-side controls and readings -------------------------------------------------

    def set_interlock(self, name: str, closed: bool) -> None:
        """Close (True) or open (False) interlock ``name`` ("estop", "door", "deadman"); an
        opening interlock cuts a running pulse."""
        if name not in INTERLOCKS:
            raise ValueError(f"unknown interlock {name!r}; one of {INTERLOCKS}")
        with self._lock:
            self._set_interlock(name, closed)
        self._wake()

    def set_fault(self, code: str | None) -> None:
        """Latch a fault (a word such as "TUBE_ARC"; PREP and EXP are refused) or clear it."""
        if code is not None and (not code or any(c.isspace() for c in code) or code == "-"):
            raise ValueError(f"a fault code is one word: {code!r}")
        with self._lock:
            self._fault = code
            self._event("fault", code=code)

    @property
    def exposures(self) -> int:
        """Pulses delivered since start."""
        with self._lock:
            return self._exposures

    @property
    def xray_on(self) -> bool:
        """The tube is on now."""
        with self._lock:
            return self._pulse is not None

    @property
    def ready(self) -> bool:
        """Warmed up and able to expose (interlocks aside)."""
        with self._lock:
            self._tick(time.monotonic())
            return self._ready

    # -- protocol --------------------------------------------------------------------------

    def _handle(self, command: str, args: list[str], now: float) -> str | None:
        self._tick(now)
        if self._pulse is not None and command not in ("ABORT", "STATUS?", "ID?"):
            raise Refusal("BUSY", "pulse running")
        if command in ("ID?", "PREP", "EXP", "ABORT", "STATUS?") and args:
            raise Refusal("SYNTAX", f"{command} takes no arguments")
        if command == "ID?":
            return f"OK ID? {self.MODEL} {self.VERSION}"
        if command in ("KV", "MA", "MS"):
            return self._set(command, args)
        if command == "PREP":
            return self._prep(now)
        if command == "EXP":
            return self._exp(now)
        if command == "ABORT":
            return self._abort(now)
        if command == "STATUS?":
            return self._status()
        raise Refusal("UNKNOWN", f"unknown command {command}")

    def _set(self, command: str, args: list[str]) -> str:
        (value,) = parse_floats(command, args, 1)
        low, high = self.limits[command]
        label = {"KV": "kV", "MA": "mA", "MS": "ms"}[command]
        if value < low:
            raise Refusal("RANGE", f"{label} {number(value)} below limit {number(low)}")
        if value > high:
            raise Refusal("RANGE", f"{label} {number(value)} above limit {number(high)}")
        self._technique[command] = value
        self._event("set", command=command, value=value)
        return f"OK {command} {number(value)}"

    def _prep(self, now: float) -> str:
        if self._fault is not None:
            raise Refusal("FAULT", f"fault {self._fault} latched")
        if None in self._technique.values():
            raise Refusal("NOTECH", "technique not set")
        if self._ready:
            return "OK PREP 0"
        if self._warm_until is None:
            self._warm_until = now + self.warmup_s
            self._event("prep", warmup_s=self.warmup_s)
        return f"OK PREP {max(self._warm_until - now, 0.0):.3f}"

    def _exp(self, now: float) -> str | None:
        self._exp_requests += 1
        k = self._exp_requests
        if k == self.timeout_at_exposure:
            self._event("ignored", command="EXP", request=k)
            return None
        if k == self.interlock_open_at_exposure:
            self._set_interlock("door", False)
        if self._fault is not None:
            raise Refusal("FAULT", f"fault {self._fault} latched")
        kv, ma, ms = (self._technique[c] for c in ("KV", "MA", "MS"))
        if kv is None or ma is None or ms is None:
            raise Refusal("NOTECH", "technique not set")
        opened = [name for name, closed in self._interlocks.items() if not closed]
        if opened:
            raise Refusal("INTERLOCK", f"interlock {','.join(opened)} open")
        if not self._ready:
            if self._warm_until is not None:
                raise Refusal("NOTREADY", f"warming up, {self._warm_until - now:.3f} s left")
            raise Refusal("NOTREADY", "not prepared (PREP first)")
        stuck = k == self.stuck_on_at_exposure
        duration_s = ms * 1e-3 * self.time_scale
        self._pulse = _Pulse(kv, ma, ms, now, None if stuck else now + duration_s, not stuck)
        self._event("xray_on", kv=kv, ma=ma, ms=ms, request=k)
        if not stuck and duration_s <= 0.0:
            return self._deliver(now)
        return None

    def _deliver(self, now: float) -> str:
        """End the running pulse normally; the OK EXP reply."""
        pulse = self._pulse
        assert pulse is not None
        self._pulse = None
        self._exposures += 1
        seq = self._exposures
        self._event("xray_off", reason="end", on_s=now - pulse.t_on)
        if self.on_exposure is not None:
            self.on_exposure(pulse.kv, pulse.ma, pulse.ms, seq)
        self._event("exposure", kv=pulse.kv, ma=pulse.ma, ms=pulse.ms, seq=seq)
        return f"OK EXP {number(pulse.kv)} {number(pulse.ma)} {number(pulse.ms)} {seq}"

    def _cut(self, now: float, reason: str) -> None:
        """End the running pulse early (not counted); answer its EXP with ABORTED."""
        pulse = self._pulse
        assert pulse is not None
        self._pulse = None
        on_ms = (now - pulse.t_on) * 1e3
        self._event("xray_off", reason=reason, on_s=now - pulse.t_on)
        if pulse.answer:
            self._send(f"ERR EXP ABORTED pulse cut after {on_ms:.1f} ms: {reason}")

    def _abort(self, now: float) -> str:
        self._event("abort", xray_on=self._pulse is not None)
        if self._pulse is not None:
            self._cut(now, "abort")
        else:
            self._event("xray_off", reason="abort", on_s=0.0)
        self._ready = False
        self._warm_until = None
        return "OK ABORT"

    def _status(self) -> str:
        def value(command: str) -> str:
            v = self._technique[command]
            return "-" if v is None else number(v)

        words = [
            "OK STATUS?",
            f"READY={int(self._ready)}",
            f"XRAY={int(self._pulse is not None)}",
            f"KV={value('KV')}",
            f"MA={value('MA')}",
            f"MS={value('MS')}",
            *(f"{name.upper()}={int(closed)}" for name, closed in self._interlocks.items()),
            f"EXPOSURES={self._exposures}",
            f"FAULT={self._fault or '-'}",
        ]
        return " ".join(words)

    def _set_interlock(self, name: str, closed: bool) -> None:
        self._interlocks[name] = closed
        self._event("interlock", name=name, closed=closed)
        if not closed and self._pulse is not None:
            self._cut(time.monotonic(), "interlock")

    def _tick(self, now: float) -> None:
        if self._warm_until is not None and now >= self._warm_until:
            self._warm_until = None
            self._ready = True
            self._event("ready")
        pulse = self._pulse
        if pulse is not None and pulse.t_end is not None and now >= pulse.t_end:
            self._send(self._deliver(now))

    def _next_wakeup(self, now: float) -> float | None:
        deadlines = [self._warm_until]
        if self._pulse is not None:
            deadlines.append(self._pulse.t_end)
        times = [t for t in deadlines if t is not None]
        return max(min(times) - now, 0.0) if times else None
