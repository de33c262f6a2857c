"""The X-ray generator over serial: :class:`SerialGenerator` implements ``XrayGenerator``.

The command set (framing, checksum, replies, commands) is specified in
``scanner/serial_link.py``. Limits are the generator's: an out-of-range technique comes back as
``ERR KV RANGE kV 160 above limit 150`` and is raised as :class:`DeviceError` with that message.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from scanner.hardware import (
    DeviceError,
    DeviceTimeout,
    Exposure,
    GeneratorStatus,
    Technique,
)
from scanner.serial_link import DEFAULT_BAUDRATE, Reply, SerialLink, format_number, time_left

INTERLOCKS = ("estop", "door", "deadman")
"""Interlock inputs reported by STATUS?."""


class SerialGenerator:
    """An X-ray generator on a serial port (see ``scanner.serial_link`` for the protocol).

    Args:
        port: device path (``/dev/ttyUSB0``) or pyserial URL.
        baudrate: bits per second.
        name: the device's name in error messages.
        poll_s: STATUS? polling period while waiting for READY, s.
        close_abort_timeout_s: timeout of the ABORT sent by :meth:`close`, s.
        on_sent: called with every command sent and the ``time.monotonic()`` it was sent at
            (:class:`~scanner.serial_link.SerialLink`): the session's command log.
    """

    def __init__(
        self,
        port: str,
        baudrate: int = DEFAULT_BAUDRATE,
        name: str = "generator",
        *,
        poll_s: float = 0.01,
        close_abort_timeout_s: float = 0.5,
        on_sent: Callable[[str, float], None] | None = None,
    ) -> None:
        self.name = name
        self.poll_s = poll_s
        self.close_abort_timeout_s = close_abort_timeout_s
        self.ident: str | None = None
        self._link = SerialLink(port, device=name, baudrate=baudrate, on_sent=on_sent)

    def connect(self, timeout_s: float) -> None:
        """Open the port and read the generator's identification (``ID?``)."""
        reply = self._call("ID?", timeout_s=timeout_s)
        self.ident = " ".join(reply.fields)

    def set_technique(self, technique: Technique, timeout_s: float) -> None:
        """Set kVp, mA and ms (in that order; a refused value leaves the earlier ones set)."""
        deadline = time.monotonic() + timeout_s
        for command, value in (("KV", technique.kv), ("MA", technique.ma), ("MS", technique.ms)):
            try:
                word = format_number(value)
            except ValueError as exc:
                raise DeviceError(f"{self.name}: {command} {value!r}: {exc}") from None
            reply = self._call(command, word, timeout_s=time_left(deadline))
            self._link.numbers(reply, 1)

    def prepare(self, timeout_s: float) -> None:
        """Start the warm-up (PREP) and return once STATUS? reports READY."""
        deadline = time.monotonic() + timeout_s
        self._call("PREP", timeout_s=timeout_s)
        while True:
            status = self.status(time_left(deadline))
            if status.fault is not None:
                raise DeviceError(f"{self.name}: 'PREP': fault {status.fault}")
            if status.ready:
                return
            if time.monotonic() + self.poll_s > deadline:
                raise DeviceTimeout(f"{self.name}: 'PREP': not READY within {timeout_s:.3g} s")
            time.sleep(self.poll_s)

    def expose(self, timeout_s: float, permit: Callable[[], None] | None = None) -> Exposure:
        """Fire one pulse; returns the technique delivered and its sequence number.

        ``permit`` is called immediately before ``EXP`` is written (the link held); what it
        raises is raised and nothing is sent. Raises DeviceError when the generator refuses
        (interlock open, not ready, fault: nothing fired) or cuts the pulse, DeviceTimeout when
        it does not answer in ``timeout_s`` s: the pulse's state is then unknown, so call
        :meth:`abort`.
        """
        reply = self._call("EXP", timeout_s=timeout_s, gate=permit)
        kv, ma, ms, seq = self._link.numbers(reply, 4)
        if seq != int(seq):
            raise DeviceError(f"{self.name}: 'EXP': sequence not an integer: {reply.line!r}")
        return Exposure(Technique(kv=kv, ma=ma, ms=ms), int(seq))

    def abort(self, timeout_s: float) -> None:
        """X-ray off now; returns when the generator confirms (``OK ABORT``).

        Independent of earlier state: (re)opens the port if needed and is sent at once even
        while another request is waiting for its reply.
        """
        reply = self._link.urgent("ABORT", timeout_s=timeout_s)
        if not reply.ok:
            raise self._link.refused(reply)

    def status(self, timeout_s: float) -> GeneratorStatus:
        """STATUS?: READY, technique, interlocks (True = closed), exposures, fault."""
        reply = self._call("STATUS?", timeout_s=timeout_s)
        values: dict[str, str] = {}
        for word in reply.fields:
            key, sep, value = word.partition("=")
            if not sep:
                raise DeviceError(f"{self.name}: 'STATUS?': not KEY=VALUE: {reply.line!r}")
            values[key] = value
        try:
            flags = {key: _flag(values[key]) for key in ("READY", *(i.upper() for i in INTERLOCKS))}
            technique_words = [values[key] for key in ("KV", "MA", "MS")]
            technique = (
                None
                if "-" in technique_words
                else Technique(*(float(word) for word in technique_words))
            )
            exposures = int(values["EXPOSURES"])
            fault = None if values["FAULT"] == "-" else values["FAULT"]
        except (KeyError, ValueError) as exc:
            raise DeviceError(
                f"{self.name}: 'STATUS?': unreadable reply ({exc}): {reply.line!r}"
            ) from None
        return GeneratorStatus(
            ready=flags["READY"],
            technique=technique,
            interlocks={name: flags[name.upper()] for name in INTERLOCKS},
            exposures=exposures,
            fault=fault,
        )

    def close(self) -> None:
        """X-ray off (best effort, when connected) and release the port; safe to call twice."""
        if self._link.is_open:
            try:
                self.abort(self.close_abort_timeout_s)
            except DeviceError:
                pass
        self._link.close()

    def __enter__(self) -> SerialGenerator:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    def _call(
        self, command: str, *args: str, timeout_s: float, gate: Callable[[], None] | None = None
    ) -> Reply:
        reply = self._link.request(command, *args, timeout_s=timeout_s, gate=gate)
        if not reply.ok:
            raise self._link.refused(reply)
        return reply


def _flag(word: str) -> bool:
    if word not in ("0", "1"):
        raise ValueError(f"flag {word!r} not 0/1")
    return word == "1"
